// Training tables, timestep spacing and the batched step entry point shared by
// all scheduler types. The type-specific updates live in scheduler_unipc.cc,
// scheduler_dpmsolver.cc, scheduler_ddim.cc and scheduler_euler.cc.
#include "model/schedulers/scheduler.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <set>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/string_view.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"
#include "model/schedulers/scheduler_internal.h"

namespace fd::model {
namespace {

using scheduler_internal::FromSigma;

// diffusers' betas_for_alpha_bar(T) with the "cosine" (Glide) transform,
// evaluated in double as Python does, then stored as float32.
torch::Tensor CosineBetas(int num_train_timesteps) {
  auto alpha_bar = [](double t) {
    const double c = std::cos((t + 0.008) / 1.008 * M_PI / 2);
    return c * c;
  };
  std::vector<float> betas(num_train_timesteps);
  for (int i = 0; i < num_train_timesteps; ++i) {
    const double t1 = static_cast<double>(i) / num_train_timesteps;
    const double t2 = static_cast<double>(i + 1) / num_train_timesteps;
    betas[i] = static_cast<float>(std::min(1 - alpha_bar(t2) / alpha_bar(t1), 0.999));
  }
  return torch::tensor(betas, torch::kFloat32);
}

// diffusers' rescale_zero_terminal_snr (float32 tensor ops, same order).
torch::Tensor RescaleZeroTerminalSnr(const torch::Tensor& betas) {
  torch::Tensor alphas = 1.0 - betas;
  torch::Tensor alphas_bar_sqrt = torch::cumprod(alphas, 0).sqrt();
  torch::Tensor first = alphas_bar_sqrt[0].clone();
  torch::Tensor last = alphas_bar_sqrt[-1].clone();
  alphas_bar_sqrt -= last;
  alphas_bar_sqrt *= first / (first - last);
  torch::Tensor alphas_bar = alphas_bar_sqrt.pow(2);
  torch::Tensor rescaled = alphas_bar.slice(0, 1) / alphas_bar.slice(0, 0, -1);
  rescaled = torch::cat({alphas_bar.slice(0, 0, 1), rescaled});
  return 1 - rescaled;
}

absl::Status Unimplemented(absl::string_view what) {
  return absl::UnimplementedError(
      absl::StrCat("scheduler config: ", what, " is not implemented by this port"));
}

absl::Status CheckOneOf(absl::string_view key, const std::string& value,
                        std::initializer_list<absl::string_view> allowed) {
  for (absl::string_view a : allowed) {
    if (value == a) return absl::OkStatus();
  }
  return absl::InvalidArgumentError(absl::StrCat("scheduler config: ", key, " '", value,
                                                 "' is not one of ", absl::StrJoin(allowed, ", ")));
}

// Normalises the type-specific choices exactly as the diffusers constructors
// do (e.g. UniPC maps DPM-Solver's solver types to bh2) and rejects the rest.
absl::Status NormalizeSettings(SchedulerSettings& s) {
  if (s.num_train_timesteps < 2) {
    return absl::InvalidArgumentError(absl::StrCat(
        "scheduler config: num_train_timesteps must be >= 2, got ", s.num_train_timesteps));
  }
  if (!s.trained_betas.empty() &&
      static_cast<int>(s.trained_betas.size()) != s.num_train_timesteps) {
    return absl::InvalidArgumentError(
        absl::StrCat("scheduler config: trained_betas has ", s.trained_betas.size(),
                     " entries but num_train_timesteps is ", s.num_train_timesteps));
  }
  if (s.trained_betas.empty()) {
    FD_RETURN_IF_ERROR(CheckOneOf("beta_schedule", s.beta_schedule,
                                  {"linear", "scaled_linear", "squaredcos_cap_v2"}));
  }
  FD_RETURN_IF_ERROR(
      CheckOneOf("prediction_type", s.prediction_type, {"epsilon", "sample", "v_prediction"}));
  if (s.thresholding) return Unimplemented("thresholding");
  if (s.use_karras_sigmas) return Unimplemented("use_karras_sigmas");
  if (s.use_exponential_sigmas) return Unimplemented("use_exponential_sigmas");
  if (s.use_beta_sigmas) return Unimplemented("use_beta_sigmas");

  switch (s.type) {
    case SchedulerType::kUniPCMultistep:
      if (s.solver_type.empty() || s.solver_type == "midpoint" || s.solver_type == "heun" ||
          s.solver_type == "logrho") {
        s.solver_type = "bh2";
      }
      FD_RETURN_IF_ERROR(CheckOneOf("solver_type", s.solver_type, {"bh1", "bh2"}));
      FD_RETURN_IF_ERROR(
          CheckOneOf("final_sigmas_type", s.final_sigmas_type, {"zero", "sigma_min"}));
      if (s.solver_order < 1) {
        return absl::InvalidArgumentError(
            absl::StrCat("scheduler config: solver_order must be >= 1, got ", s.solver_order));
      }
      break;
    case SchedulerType::kDPMSolverMultistep:
      if (s.algorithm_type == "deis") s.algorithm_type = "dpmsolver++";
      if (s.algorithm_type == "sde-dpmsolver++" || s.algorithm_type == "sde-dpmsolver") {
        return Unimplemented(absl::StrCat("algorithm_type ", s.algorithm_type));
      }
      FD_RETURN_IF_ERROR(
          CheckOneOf("algorithm_type", s.algorithm_type, {"dpmsolver++", "dpmsolver"}));
      if (s.solver_type.empty() || s.solver_type == "logrho" || s.solver_type == "bh1" ||
          s.solver_type == "bh2") {
        s.solver_type = "midpoint";
      }
      FD_RETURN_IF_ERROR(CheckOneOf("solver_type", s.solver_type, {"midpoint", "heun"}));
      FD_RETURN_IF_ERROR(
          CheckOneOf("final_sigmas_type", s.final_sigmas_type, {"zero", "sigma_min"}));
      if (s.algorithm_type != "dpmsolver++" && s.final_sigmas_type == "zero") {
        return absl::InvalidArgumentError(
            "scheduler config: final_sigmas_type 'zero' is not supported for algorithm_type "
            "'dpmsolver'; choose 'sigma_min'");
      }
      if (s.solver_order < 1 || s.solver_order > 3) {
        return absl::InvalidArgumentError(
            absl::StrCat("scheduler config: solver_order must be 1, 2 or 3, got ", s.solver_order));
      }
      if (s.use_lu_lambdas) return Unimplemented("use_lu_lambdas");
      if (!s.variance_type.empty())
        return Unimplemented(absl::StrCat("variance_type ", s.variance_type));
      break;
    case SchedulerType::kDDIM:
      if (s.clip_sample && !(s.clip_sample_range > 0)) {
        return absl::InvalidArgumentError("scheduler config: clip_sample_range must be > 0");
      }
      break;
    case SchedulerType::kEulerDiscrete:
      FD_RETURN_IF_ERROR(
          CheckOneOf("final_sigmas_type", s.final_sigmas_type, {"zero", "sigma_min"}));
      if (s.interpolation_type != "linear") {
        return Unimplemented(absl::StrCat("interpolation_type ", s.interpolation_type));
      }
      if (s.timestep_type != "discrete") {
        return Unimplemented(absl::StrCat("timestep_type ", s.timestep_type));
      }
      break;
  }
  return absl::OkStatus();
}

// numpy's linspace(0, stop, num) (endpoint included), in double.
std::vector<double> NpLinspace(double stop, int num) {
  std::vector<double> y(num);
  const int div = num - 1;
  for (int i = 0; i < num; ++i) y[i] = div > 0 ? i * (stop / div) : i * stop;
  if (num > 1) y[num - 1] = stop;
  return y;
}

// numpy's arange(start, 0, -step) for float step: v0 = start, v1 = start -
// step, v_i = start + i * (v1 - start) (numpy's fill), ceil(start/step) values.
std::vector<double> NpArangeDown(double start, double step) {
  const int64_t length = static_cast<int64_t>(std::ceil((0.0 - start) / -step));
  std::vector<double> y(std::max<int64_t>(length, 0));
  if (y.empty()) return y;
  y[0] = start;
  if (y.size() > 1) y[1] = start + -step;
  const double delta = (start + -step) - start;
  for (size_t i = 2; i < y.size(); ++i) y[i] = start + static_cast<double>(i) * delta;
  return y;
}

// numpy's round(): half to even (the default FP rounding mode).
double NpRound(double x) { return std::nearbyint(x); }

// np.interp(x, arange(len(fp)), fp) in double.
double NpInterp(double x, const std::vector<float>& fp) {
  const int64_t n = static_cast<int64_t>(fp.size());
  if (x <= 0) return fp[0];
  if (x >= n - 1) return fp[n - 1];
  const int64_t j = static_cast<int64_t>(std::floor(x));
  const double slope = (static_cast<double>(fp[j + 1]) - fp[j]) / 1.0;
  double r = slope * (x - j) + fp[j];
  if (std::isnan(r)) r = slope * (x - (j + 1)) + fp[j + 1];
  return r;
}

}  // namespace

namespace scheduler_internal {

std::vector<float> SolveSmall(std::vector<float> a, std::vector<float> b) {
  const int n = static_cast<int>(b.size());
  std::vector<int> perm(n);
  for (int i = 0; i < n; ++i) perm[i] = i;
  // LU factorisation (sgetf2: pivot = max |a| in the column, the column below
  // the pivot scaled by the pivot's reciprocal).
  for (int k = 0; k < n; ++k) {
    int p = k;
    for (int i = k + 1; i < n; ++i) {
      if (std::fabs(a[i * n + k]) > std::fabs(a[p * n + k])) p = i;
    }
    if (p != k) {
      for (int j = 0; j < n; ++j) std::swap(a[k * n + j], a[p * n + j]);
      std::swap(b[k], b[p]);
    }
    const float inv = 1.0f / a[k * n + k];
    for (int i = k + 1; i < n; ++i) {
      a[i * n + k] *= inv;
      for (int j = k + 1; j < n; ++j) a[i * n + j] -= a[i * n + k] * a[k * n + j];
    }
  }
  // Forward substitution with the unit lower factor, then back substitution.
  for (int i = 1; i < n; ++i) {
    for (int k = 0; k < i; ++k) b[i] -= a[i * n + k] * b[k];
  }
  for (int i = n - 1; i >= 0; --i) {
    b[i] /= a[i * n + i];
    for (int k = 0; k < i; ++k) b[k] -= b[i] * a[k * n + i];
  }
  return b;
}

}  // namespace scheduler_internal

absl::StatusOr<Scheduler> Scheduler::Create(const SchedulerSettings& settings) {
  return TorchCall("Scheduler::Create", [&]() -> absl::StatusOr<Scheduler> {
    auto tables = std::make_shared<Tables>();
    tables->settings = settings;
    SchedulerSettings& s = tables->settings;
    FD_RETURN_IF_ERROR(NormalizeSettings(s));
    tables->spacing = EffectiveTimestepSpacing(s);

    const int T = s.num_train_timesteps;
    torch::Tensor betas;
    if (!s.trained_betas.empty()) {
      betas = torch::tensor(s.trained_betas, torch::kFloat64).to(torch::kFloat32);
    } else if (s.beta_schedule == "linear") {
      betas = torch::linspace(s.beta_start, s.beta_end, T, torch::kFloat32);
    } else if (s.beta_schedule == "scaled_linear") {
      // "this schedule is very specific to the latent diffusion model."
      betas = torch::linspace(std::sqrt(s.beta_start), std::sqrt(s.beta_end), T, torch::kFloat32)
                  .pow(2);
    } else {
      betas = CosineBetas(T);
    }
    if (s.rescale_betas_zero_snr) betas = RescaleZeroTerminalSnr(betas);
    torch::Tensor alphas_cumprod = torch::cumprod(1.0 - betas, 0);
    if (s.rescale_betas_zero_snr && s.type != SchedulerType::kDDIM) {
      // "Close to 0 without being 0 so first sigma is not inf" (not in DDIM).
      alphas_cumprod[-1] = std::ldexp(1.0, -24);
    }
    tables->betas = betas.contiguous();
    tables->alphas_cumprod = alphas_cumprod.contiguous();
    tables->train_sigmas = ((1 - alphas_cumprod) / alphas_cumprod).pow(0.5).contiguous();
    const float* ac = tables->alphas_cumprod.data_ptr<float>();
    const float* ts = tables->train_sigmas.data_ptr<float>();
    tables->alphas_cumprod_values.assign(ac, ac + T);
    tables->train_sigma_values.assign(ts, ts + T);
    tables->final_alpha_cumprod = s.set_alpha_to_one ? 1.0f : ac[0];
    return Scheduler(std::move(tables));
  });
}

const SchedulerSettings& Scheduler::settings() const { return tables_->settings; }
const torch::Tensor& Scheduler::betas() const { return tables_->betas; }
const torch::Tensor& Scheduler::alphas_cumprod() const { return tables_->alphas_cumprod; }
const torch::Tensor& Scheduler::train_sigmas() const { return tables_->train_sigmas; }

absl::StatusOr<SchedulerState> Scheduler::NewState(int num_inference_steps) const {
  const SchedulerSettings& s = tables_->settings;
  const int T = s.num_train_timesteps;
  const int n = num_inference_steps;
  if (n < 1 || n > T) {
    return absl::InvalidArgumentError(
        absl::StrCat("num_inference_steps must be in [1, ", T, "] (num_train_timesteps), got ", n));
  }
  return TorchCall("Scheduler::NewState", [&]() -> absl::StatusOr<SchedulerState> {
    SchedulerState state;
    state.owner_ = tables_.get();
    std::vector<double> t;  // timesteps, as diffusers computes them
    const TimestepSpacing spacing = tables_->spacing;
    switch (s.type) {
      case SchedulerType::kUniPCMultistep:
      case SchedulerType::kDPMSolverMultistep: {
        int last_timestep = T;
        if (s.type == SchedulerType::kDPMSolverMultistep) {
          // "Clipping the minimum of all lambda(t) for numerical stability":
          // searchsorted(flip(lambda_t), lambda_min_clipped).
          torch::Tensor lambda_t = torch::log(tables_->alphas_cumprod.sqrt()) -
                                   torch::log((1 - tables_->alphas_cumprod).sqrt());
          const int64_t clipped =
              (lambda_t < static_cast<float>(s.lambda_min_clipped)).sum().item<int64_t>();
          last_timestep = T - static_cast<int>(clipped);
        }
        if (spacing == TimestepSpacing::kLinspace) {
          std::vector<double> y = NpLinspace(last_timestep - 1, n + 1);
          for (int i = n; i >= 1; --i) t.push_back(NpRound(y[i]));
        } else if (spacing == TimestepSpacing::kLeading) {
          const int step_ratio = last_timestep / (n + 1);
          for (int i = n; i >= 1; --i)
            t.push_back(NpRound(double(i) * step_ratio) + s.steps_offset);
        } else {
          const double step_ratio = static_cast<double>(T) / n;
          for (double v : NpArangeDown(last_timestep, step_ratio)) t.push_back(NpRound(v) - 1);
        }
        break;
      }
      case SchedulerType::kDDIM: {
        if (spacing == TimestepSpacing::kLinspace) {
          std::vector<double> y = NpLinspace(T - 1, n);
          for (int i = n - 1; i >= 0; --i) t.push_back(NpRound(y[i]));
        } else if (spacing == TimestepSpacing::kLeading) {
          const int step_ratio = T / n;
          for (int i = n - 1; i >= 0; --i)
            t.push_back(NpRound(double(i) * step_ratio) + s.steps_offset);
        } else {
          for (double v : NpArangeDown(T, static_cast<double>(T) / n)) t.push_back(NpRound(v) - 1);
        }
        break;
      }
      case SchedulerType::kEulerDiscrete: {
        // Euler keeps float32 timesteps (linspace ones may be fractional).
        if (spacing == TimestepSpacing::kLinspace) {
          std::vector<double> y = NpLinspace(T - 1, n);
          for (int i = n - 1; i >= 0; --i) t.push_back(static_cast<float>(y[i]));
        } else if (spacing == TimestepSpacing::kLeading) {
          const int step_ratio = T / n;
          for (int i = n - 1; i >= 0; --i) {
            t.push_back(static_cast<float>(static_cast<float>(NpRound(double(i) * step_ratio)) +
                                           static_cast<float>(s.steps_offset)));
          }
        } else {
          for (double v : NpArangeDown(T, static_cast<double>(T) / n)) {
            t.push_back(static_cast<float>(static_cast<float>(NpRound(v)) - 1.0f));
          }
        }
        break;
      }
    }
    // DPM-Solver's lambda clipping may leave trailing spacing with fewer
    // steps; diffusers then runs len(timesteps) steps, and so do we.
    if (t.empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat("timestep spacing produced no timesteps for ", n, " steps"));
    }
    if (s.type == SchedulerType::kDDIM) {
      for (double v : t) {
        if (v < 0 || v >= T) {
          return absl::InvalidArgumentError(absl::StrCat("DDIM timestep ", v, " (", n,
                                                         " steps, steps_offset ", s.steps_offset,
                                                         ") is outside [0, ", T, ")"));
        }
      }
    }
    state.timestep_values_ = t;
    if (s.type == SchedulerType::kEulerDiscrete) {
      std::vector<float> tf(t.begin(), t.end());
      state.timesteps_ = torch::tensor(tf, torch::kFloat32);
    } else {
      std::vector<int64_t> ti(t.begin(), t.end());
      state.timesteps_ = torch::tensor(ti, torch::kInt64);
    }
    if (s.type != SchedulerType::kDDIM) {
      // sigmas = np.interp(timesteps, arange(T), train_sigmas) + final sigma.
      std::vector<float> sig;
      for (double v : t)
        sig.push_back(static_cast<float>(NpInterp(v, tables_->train_sigma_values)));
      sig.push_back(s.final_sigmas_type == "zero" ? 0.0f : tables_->train_sigma_values[0]);
      state.sigma_values_ = sig;
      state.sigmas_ = torch::tensor(sig, torch::kFloat32);
    }
    return state;
  });
}

double Scheduler::InitNoiseSigma(const SchedulerState& state) const {
  if (type() != SchedulerType::kEulerDiscrete || state.sigma_values_.empty()) return 1.0;
  const float max_sigma = *std::max_element(state.sigma_values_.begin(), state.sigma_values_.end());
  if (tables_->spacing == TimestepSpacing::kLinspace ||
      tables_->spacing == TimestepSpacing::kTrailing) {
    return max_sigma;
  }
  return std::sqrt(max_sigma * max_sigma + 1.0f);
}

absl::Status Scheduler::ValidateStates(absl::Span<const SchedulerState* const> states,
                                       int64_t batch) const {
  if (static_cast<int64_t>(states.size()) != batch) {
    return absl::InvalidArgumentError(
        absl::StrCat("scheduler: got ", states.size(), " states for a batch of ", batch));
  }
  std::set<const SchedulerState*> seen;
  for (size_t i = 0; i < states.size(); ++i) {
    const SchedulerState* st = states[i];
    if (st == nullptr)
      return absl::InvalidArgumentError(absl::StrCat("scheduler: states[", i, "] is null"));
    if (!seen.insert(st).second) {
      return absl::InvalidArgumentError(
          absl::StrCat("scheduler: states[", i, "] appears twice in the batch"));
    }
    if (st->owner_ != tables_.get()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "scheduler: states[", i, "] was not created by this scheduler (use NewState)"));
    }
    if (st->finished()) {
      return absl::FailedPreconditionError(absl::StrCat(
          "scheduler: states[", i, "] has finished all its ", st->num_inference_steps(), " steps"));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<torch::Tensor> Scheduler::CurrentTimesteps(
    absl::Span<const SchedulerState* const> states) const {
  FD_RETURN_IF_ERROR(ValidateStates(states, static_cast<int64_t>(states.size())));
  return TorchCall("Scheduler::CurrentTimesteps", [&]() -> absl::StatusOr<torch::Tensor> {
    std::vector<float> t;
    for (const SchedulerState* st : states) t.push_back(static_cast<float>(st->current_timestep()));
    return torch::tensor(t, torch::kFloat32);
  });
}

absl::StatusOr<torch::Tensor> Scheduler::ScaleModelInput(
    absl::Span<const SchedulerState* const> states, const torch::Tensor& sample) const {
  if (!sample.defined() || sample.dim() < 1 || !sample.is_floating_point()) {
    return absl::InvalidArgumentError("scheduler: sample must be a floating-point tensor [N, ...]");
  }
  FD_RETURN_IF_ERROR(ValidateStates(states, sample.size(0)));
  if (type() != SchedulerType::kEulerDiscrete) return sample;
  return TorchCall("Scheduler::ScaleModelInput", [&]() -> absl::StatusOr<torch::Tensor> {
    // sample / ((sigma**2 + 1) ** 0.5), per item.
    std::vector<float> scale;
    for (const SchedulerState* st : states) {
      const float sigma = st->sigma_values_[st->step_index_];
      scale.push_back(std::sqrt(sigma * sigma + 1.0f));
    }
    torch::Tensor x = sample.to(torch::kFloat32);
    return (x / scheduler_internal::PerItem(scale, x)).to(sample.scalar_type());
  });
}

absl::StatusOr<SchedulerStepOutput> Scheduler::Step(absl::Span<SchedulerState* const> states,
                                                    const torch::Tensor& model_output,
                                                    const torch::Tensor& sample) const {
  if (!sample.defined() || !model_output.defined()) {
    return absl::InvalidArgumentError("scheduler: sample and model_output must be defined");
  }
  if (sample.dim() < 1 || !sample.is_floating_point() || !model_output.is_floating_point()) {
    return absl::InvalidArgumentError(
        "scheduler: sample and model_output must be floating-point tensors [N, ...]");
  }
  if (sample.sizes() != model_output.sizes()) {
    return absl::InvalidArgumentError(
        absl::StrCat("scheduler: model_output shape [", absl::StrJoin(model_output.sizes(), ", "),
                     "] differs from sample shape [", absl::StrJoin(sample.sizes(), ", "), "]"));
  }
  if (sample.device() != model_output.device()) {
    return absl::InvalidArgumentError(
        "scheduler: model_output and sample are on different devices");
  }
  std::vector<const SchedulerState*> const_states(states.begin(), states.end());
  FD_RETURN_IF_ERROR(ValidateStates(const_states, sample.size(0)));
  std::vector<int64_t> item_shape = sample.sizes().vec();
  item_shape[0] = 1;
  for (size_t i = 0; i < states.size(); ++i) {
    for (const torch::Tensor& h : states[i]->model_outputs_) {
      if (h.defined() &&
          (h.sizes() != torch::IntArrayRef(item_shape) || h.device() != sample.device())) {
        return absl::InvalidArgumentError(absl::StrCat(
            "scheduler: states[", i, "] was stepped with samples of shape [",
            absl::StrJoin(h.sizes().slice(1), ", "), "] on ", h.device().str(), ", now [",
            absl::StrJoin(sample.sizes().slice(1), ", "), "] on ", sample.device().str()));
      }
    }
  }
  return TorchCall("Scheduler::Step", [&]() -> absl::StatusOr<SchedulerStepOutput> {
    torch::NoGradGuard no_grad;
    const torch::Tensor mo = model_output.to(torch::kFloat32);
    const torch::Tensor x = sample.to(torch::kFloat32);
    absl::StatusOr<SchedulerStepOutput> out;
    switch (type()) {
      case SchedulerType::kUniPCMultistep:
        out = StepUniPC(states, mo, x);
        break;
      case SchedulerType::kDPMSolverMultistep:
        out = StepDPMSolver(states, mo, x);
        break;
      case SchedulerType::kDDIM:
        out = StepDDIM(states, mo, x);
        break;
      case SchedulerType::kEulerDiscrete:
        out = StepEuler(states, mo, x);
        break;
    }
    if (out.ok()) out->prev_sample = out->prev_sample.to(sample.scalar_type());
    return out;
  });
}

void Scheduler::CommitMultistepStates(std::vector<SchedulerState>& next,
                                      absl::Span<SchedulerState* const> states, int solver_order) {
  for (size_t i = 0; i < next.size(); ++i) {
    SchedulerState& st = next[i];
    if (st.lower_order_nums_ < solver_order) ++st.lower_order_nums_;
    ++st.step_index_;
    *states[i] = std::move(st);
  }
}

}  // namespace fd::model
