// Tests for model/schedulers/scheduler.h: the diffusers goldens (DPM-Solver++ tables and
// loops of configs A/B, UniPC of the FrameDiffuser checkpoint), analytic
// checks for DDIM and Euler (which have no goldens), batch independence of
// items at different steps, and the error paths.
#include "model/schedulers/scheduler.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <map>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "model/checkpoint/safetensors.h"
#include "model/schedulers/scheduler_settings.h"
#include "tests/testing/golden.h"
#include "tests/testing/golden_tensors.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

using ::testing::HasSubstr;

using ::fd::testing::TensorMap;

using ::fd::testing::ExpectGoldenClose;
using ::fd::testing::GoldenTensor;
using ::fd::testing::LoadGoldenTensors;

void ExpectEqualInt(const std::string& name, const torch::Tensor& actual,
                    const torch::Tensor& expected) {
  EXPECT_TRUE(fd::testing::TensorsEqual(actual, expected)) << name;
}

SchedulerSettings SettingsFromGolden(const std::string& relative, SchedulerType type) {
  auto s = SchedulerSettingsFromFile(fd::testing::GoldenPath(relative), type);
  EXPECT_TRUE(s.ok()) << s.status();
  return s.ok() ? *s : SchedulerSettings{};
}

Scheduler MakeScheduler(const SchedulerSettings& settings) {
  auto scheduler = Scheduler::Create(settings);
  EXPECT_TRUE(scheduler.ok()) << scheduler.status();
  return *scheduler;
}

// The integers n of keys "<prefix><n>" in `m`.
std::vector<int> Suffixes(const TensorMap& m, const std::string& prefix) {
  std::vector<int> out;
  for (const auto& [key, value] : m) {
    int n;
    if (absl::StartsWith(key, prefix) && absl::SimpleAtoi(key.substr(prefix.size()), &n)) {
      out.push_back(n);
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

TimestepSpacing SpacingFromName(const std::string& name) {
  if (name == "leading") return TimestepSpacing::kLeading;
  if (name == "trailing") return TimestepSpacing::kTrailing;
  EXPECT_EQ(name, "linspace");
  return TimestepSpacing::kLinspace;
}

SchedulerStepOutput StepOne(const Scheduler& scheduler, SchedulerState& state,
                            const torch::Tensor& model_output, const torch::Tensor& sample) {
  SchedulerState* states[] = {&state};
  auto out = scheduler.Step(states, model_output, sample);
  EXPECT_TRUE(out.ok()) << out.status();
  return out.ok() ? *out : SchedulerStepOutput{};
}

// A golden loop over a batch: diffusers runs one scheduler over the whole
// batch, here every item has its own state (all at the same step).
struct BatchLoop {
  std::vector<SchedulerState> states;

  BatchLoop(const Scheduler& scheduler, int num_steps, int64_t batch) {
    for (int64_t i = 0; i < batch; ++i) {
      auto state = scheduler.NewState(num_steps);
      EXPECT_TRUE(state.ok()) << state.status();
      states.push_back(state.ok() ? *state : SchedulerState());
    }
  }
  SchedulerStepOutput Step(const Scheduler& scheduler, const torch::Tensor& model_output,
                           const torch::Tensor& sample) {
    std::vector<SchedulerState*> ptrs;
    for (SchedulerState& st : states) ptrs.push_back(&st);
    auto out = scheduler.Step(ptrs, model_output, sample);
    EXPECT_TRUE(out.ok()) << out.status();
    return out.ok() ? *out : SchedulerStepOutput{};
  }
  // The items' last_sample() concatenated: [N, ...].
  torch::Tensor LastSample() const {
    std::vector<torch::Tensor> parts;
    for (const SchedulerState& st : states) parts.push_back(st.last_sample());
    return torch::cat(parts);
  }
};

// ---------------------------------------------------------------------------
// DPM-Solver++ goldens of configs A and B (golden/<cfg>/golden/scheduler.safetensors).

class DpmSolverGoldenTest : public ::testing::TestWithParam<std::string> {};

TEST_P(DpmSolverGoldenTest, TablesAndTimestepsForEverySpacing) {
  const std::string cfg = GetParam();
  const TensorMap golden = LoadGoldenTensors(cfg + "/golden/scheduler.safetensors");
  const SchedulerSettings base = SettingsFromGolden(cfg + "/scheduler/scheduler_config.json",
                                                    SchedulerType::kDPMSolverMultistep);
  const Scheduler scheduler = MakeScheduler(base);
  ExpectGoldenClose(cfg + "/alphas_cumprod", scheduler.alphas_cumprod(),
                    GoldenTensor(golden, "alphas_cumprod"), 1e-6);

  int checked = 0;
  for (const std::string spacing : {"linspace", "leading", "trailing"}) {
    SchedulerSettings settings = base;
    settings.timestep_spacing = SpacingFromName(spacing);
    const Scheduler sched = MakeScheduler(settings);
    for (int n : Suffixes(golden, "timesteps." + spacing + ".")) {
      const std::string tag = spacing + "." + std::to_string(n);
      auto state = sched.NewState(n);
      ASSERT_TRUE(state.ok()) << state.status();
      ExpectEqualInt(cfg + "/timesteps." + tag, state->timesteps(),
                     GoldenTensor(golden, "timesteps." + tag));
      ExpectGoldenClose(cfg + "/sigmas." + tag, state->sigmas(),
                        GoldenTensor(golden, "sigmas." + tag), 1e-6);
      ++checked;
    }
  }
  EXPECT_GT(checked, 0) << "no timesteps.* tensors in the golden file";
}

TEST_P(DpmSolverGoldenTest, StepLoopsMatch) {
  const std::string cfg = GetParam();
  const TensorMap golden = LoadGoldenTensors(cfg + "/golden/scheduler.safetensors");
  const TensorMap inputs = LoadGoldenTensors(cfg + "/golden/inputs.safetensors");
  const SchedulerSettings base = SettingsFromGolden(cfg + "/scheduler/scheduler_config.json",
                                                    SchedulerType::kDPMSolverMultistep);

  // Loop tags: "<tag>.timesteps" other than the "timesteps.*" tables, e.g.
  // sched10, sched4, sched10_leading (suffix = the spacing used).
  int loops = 0;
  for (const auto& [key, value] : golden) {
    if (!absl::EndsWith(key, ".timesteps") || absl::StartsWith(key, "timesteps.")) continue;
    const std::string tag = key.substr(0, key.size() - std::string(".timesteps").size());
    SchedulerSettings settings = base;
    if (const size_t underscore = tag.find('_'); underscore != std::string::npos) {
      settings.timestep_spacing = SpacingFromName(tag.substr(underscore + 1));
    }
    const Scheduler scheduler = MakeScheduler(settings);
    const int n = static_cast<int>(value.numel());
    torch::Tensor x = GoldenTensor(inputs, tag + ".sample");
    BatchLoop loop(scheduler, n, x.size(0));
    const SchedulerState& state0 = loop.states[0];
    ExpectEqualInt(cfg + "/" + tag + ".timesteps", state0.timesteps(), value);
    ExpectGoldenClose(cfg + "/" + tag + ".sigmas", state0.sigmas(),
                      GoldenTensor(golden, tag + ".sigmas"), 1e-6);

    for (int i = 0; i < n; ++i) {
      const std::string step = "." + std::to_string(i);
      const SchedulerStepOutput out =
          loop.Step(scheduler, GoldenTensor(inputs, tag + ".model_output" + step), x);
      ExpectGoldenClose(cfg + "/" + tag + ".x0_pred" + step, out.pred_original_sample,
                        GoldenTensor(golden, tag + ".x0_pred" + step), 1e-5);
      ExpectGoldenClose(cfg + "/" + tag + ".prev_sample" + step, out.prev_sample,
                        GoldenTensor(golden, tag + ".prev_sample" + step), 1e-5);
      x = out.prev_sample;
    }
    EXPECT_TRUE(state0.finished());
    ++loops;
  }
  EXPECT_GT(loops, 0) << "no scheduler loops in the golden file";
}

INSTANTIATE_TEST_SUITE_P(Configs, DpmSolverGoldenTest, ::testing::Values("A", "B"));

// ---------------------------------------------------------------------------
// UniPC goldens (fd_pipeline/golden/scheduler_unipc.safetensors), built like
// FrameDiffuser's inference.py: UniPC.from_config(SD1.5's scheduler json).

SchedulerSettings UniPCSettings() {
  return SettingsFromGolden("fd_pipeline/model/scheduler/scheduler_config.json",
                            SchedulerType::kUniPCMultistep);
}

TEST(UniPCGoldenTest, Sd15JsonWithoutSpacingGivesLinspace) {
  const SchedulerSettings settings = UniPCSettings();
  EXPECT_FALSE(settings.timestep_spacing.has_value());
  EXPECT_EQ(EffectiveTimestepSpacing(settings), TimestepSpacing::kLinspace);
  EXPECT_EQ(settings.steps_offset, 1);
  EXPECT_EQ(settings.beta_schedule, "scaled_linear");
}

TEST(UniPCGoldenTest, TablesAndTimesteps) {
  const TensorMap golden = LoadGoldenTensors("fd_pipeline/golden/scheduler_unipc.safetensors");
  const Scheduler scheduler = MakeScheduler(UniPCSettings());
  ExpectGoldenClose("unipc/alphas_cumprod", scheduler.alphas_cumprod(),
                    GoldenTensor(golden, "alphas_cumprod"), 1e-6);
  ExpectGoldenClose("unipc/train_sigmas", scheduler.train_sigmas(),
                    GoldenTensor(golden, "train_sigmas"), 1e-6);
  const std::vector<int> counts = Suffixes(golden, "timesteps.");
  ASSERT_FALSE(counts.empty());
  for (int n : counts) {
    auto state = scheduler.NewState(n);
    ASSERT_TRUE(state.ok()) << state.status();
    const std::string tag = std::to_string(n);
    ExpectEqualInt("unipc/timesteps." + tag, state->timesteps(),
                   GoldenTensor(golden, "timesteps." + tag));
    ExpectGoldenClose("unipc/sigmas." + tag, state->sigmas(), GoldenTensor(golden, "sigmas." + tag),
                      1e-6);
  }
  // What the other spacings would give (diagnostic entries of the golden).
  for (const std::string spacing : {"leading", "trailing"}) {
    SchedulerSettings settings = UniPCSettings();
    settings.timestep_spacing = SpacingFromName(spacing);
    const Scheduler other = MakeScheduler(settings);
    const std::string prefix = "aside." + spacing + ".timesteps.";
    const std::vector<int> aside = Suffixes(golden, prefix);
    EXPECT_FALSE(aside.empty()) << prefix;
    for (int n : aside) {
      auto state = other.NewState(n);
      ASSERT_TRUE(state.ok()) << state.status();
      ExpectEqualInt("unipc/" + prefix + std::to_string(n), state->timesteps(),
                     GoldenTensor(golden, prefix + std::to_string(n)));
    }
  }
}

TEST(UniPCGoldenTest, StepLoopsMatchIncludingCorrectorAndOrders) {
  const TensorMap golden = LoadGoldenTensors("fd_pipeline/golden/scheduler_unipc.safetensors");
  const Scheduler scheduler = MakeScheduler(UniPCSettings());
  int loops = 0;
  for (const auto& [key, value] : golden) {
    if (!absl::StartsWith(key, "loop") || !absl::EndsWith(key, ".timesteps")) continue;
    const std::string tag = key.substr(0, key.find('.'));
    const int n = static_cast<int>(value.numel());
    torch::Tensor x = GoldenTensor(golden, tag + ".sample");
    BatchLoop loop(scheduler, n, x.size(0));
    ExpectEqualInt("unipc/" + tag + ".timesteps", loop.states[0].timesteps(), value);
    for (int i = 0; i < n; ++i) {
      const std::string step = "." + std::to_string(i);
      const SchedulerStepOutput out =
          loop.Step(scheduler, GoldenTensor(golden, tag + ".model_output" + step), x);
      EXPECT_EQ(loop.states[0].last_order(),
                GoldenTensor(golden, tag + ".order" + step).item<int64_t>())
          << tag << " step " << i;
      if (i >= 1) {
        ExpectGoldenClose("unipc/" + tag + ".corrected_sample" + step, loop.LastSample(),
                          GoldenTensor(golden, tag + ".corrected_sample" + step), 1e-5);
      }
      ExpectGoldenClose("unipc/" + tag + ".x0_pred" + step, out.pred_original_sample,
                        GoldenTensor(golden, tag + ".x0_pred" + step), 1e-5);
      ExpectGoldenClose("unipc/" + tag + ".prev_sample" + step, out.prev_sample,
                        GoldenTensor(golden, tag + ".prev_sample" + step), 1e-5);
      x = out.prev_sample;
    }
    ++loops;
  }
  EXPECT_GT(loops, 0);
}

// ---------------------------------------------------------------------------
// Analytic checks. With a perfect model (eps = the true noise, x0 = the true
// data) every deterministic scheduler here stays on the exact trajectory
// x_t = alpha_t x0 + sigma_t eps (VP form; Euler: x0 + sigma eps) and ends at
// x0. The expected values are computed here in double from the beta formula,
// independently of the scheduler's tables.

// SD1.5's scaled_linear schedule in double.
std::vector<double> Sd15AlphasCumprod() {
  const int T = 1000;
  std::vector<double> ac(T);
  double prod = 1;
  for (int i = 0; i < T; ++i) {
    const double b = std::sqrt(0.00085) + (std::sqrt(0.012) - std::sqrt(0.00085)) * i / (T - 1);
    prod *= 1 - b * b;
    ac[i] = prod;
  }
  return ac;
}

SchedulerSettings Sd15Settings(SchedulerType type) {
  SchedulerSettings s;
  s.type = type;
  s.beta_start = 0.00085;
  s.beta_end = 0.012;
  s.beta_schedule = "scaled_linear";
  s.steps_offset = 1;
  s.set_alpha_to_one = false;
  s.clip_sample = false;
  return s;
}

struct Perfect {
  torch::Tensor x0;
  torch::Tensor eps;
};
Perfect MakePerfect(int64_t batch = 1) {
  torch::manual_seed(1234);
  return {torch::randn({batch, 4, 6, 5}), torch::randn({batch, 4, 6, 5})};
}

TEST(DdimAnalyticTest, TimestepsOfEachSpacing) {
  SchedulerSettings s = Sd15Settings(SchedulerType::kDDIM);
  auto expect = [&](TimestepSpacing spacing, int n, std::vector<int64_t> want) {
    s.timestep_spacing = spacing;
    auto state = MakeScheduler(s).NewState(n);
    ASSERT_TRUE(state.ok()) << state.status();
    EXPECT_TRUE(torch::equal(state->timesteps(), torch::tensor(want, torch::kInt64)))
        << state->timesteps();
  };
  // leading: arange(n) * (1000 // n) reversed, + steps_offset.
  expect(TimestepSpacing::kLeading, 10, {901, 801, 701, 601, 501, 401, 301, 201, 101, 1});
  // linspace: round(linspace(0, 999, n)) reversed.
  expect(TimestepSpacing::kLinspace, 4, {999, 666, 333, 0});
  // trailing: round(arange(1000, 0, -1000/n)) - 1.
  expect(TimestepSpacing::kTrailing, 3, {999, 666, 332});
  // DDIM's own default spacing is leading (an SD1.5 json has no spacing key).
  s.timestep_spacing.reset();
  auto state = MakeScheduler(s).NewState(10);
  ASSERT_TRUE(state.ok());
  EXPECT_EQ(state->timesteps()[0].item<int64_t>(), 901);
}

TEST(DdimAnalyticTest, PerfectModelFollowsTheExactTrajectory) {
  const std::vector<double> ac = Sd15AlphasCumprod();
  for (const std::string prediction : {"epsilon", "sample", "v_prediction"}) {
    for (bool alpha_to_one : {false, true}) {
      SchedulerSettings s = Sd15Settings(SchedulerType::kDDIM);
      s.prediction_type = prediction;
      s.set_alpha_to_one = alpha_to_one;
      const Scheduler scheduler = MakeScheduler(s);
      const int n = 10;
      auto state = scheduler.NewState(n);
      ASSERT_TRUE(state.ok());
      const Perfect p = MakePerfect();
      auto on_trajectory = [&](double a) {
        return (std::sqrt(a) * p.x0.to(torch::kFloat64) +
                std::sqrt(1 - a) * p.eps.to(torch::kFloat64))
            .to(torch::kFloat32);
      };
      int64_t t = 901;  // leading, offset 1
      torch::Tensor x = on_trajectory(ac[t]);
      for (int i = 0; i < n; ++i) {
        const double a = ac[t];
        torch::Tensor model_output = prediction == "epsilon" ? p.eps
                                     : prediction == "sample"
                                         ? p.x0
                                         : (std::sqrt(a) * p.eps - std::sqrt(1 - a) * p.x0);
        const SchedulerStepOutput out = StepOne(scheduler, *state, model_output, x);
        const int64_t prev = t - 1000 / n;
        const double a_prev = prev >= 0 ? ac[prev] : (alpha_to_one ? 1.0 : ac[0]);
        ExpectGoldenClose("ddim/" + prediction + "/x0." + std::to_string(i),
                          out.pred_original_sample, p.x0, 1e-5, 1e-5);
        ExpectGoldenClose("ddim/" + prediction + "/prev." + std::to_string(i), out.prev_sample,
                          on_trajectory(a_prev), 1e-5, 1e-5);
        x = out.prev_sample;
        t = prev;
      }
      if (alpha_to_one) ExpectGoldenClose("ddim/final_is_x0", x, p.x0, 1e-5, 1e-5);
      EXPECT_TRUE(state->finished());
    }
  }
}

TEST(DdimAnalyticTest, ClipSampleClampsThePredictedX0) {
  SchedulerSettings s = Sd15Settings(SchedulerType::kDDIM);
  s.clip_sample = true;
  s.clip_sample_range = 0.25;
  const Scheduler scheduler = MakeScheduler(s);
  auto state = scheduler.NewState(10);
  ASSERT_TRUE(state.ok());
  const std::vector<double> ac = Sd15AlphasCumprod();
  const Perfect p = MakePerfect();
  const torch::Tensor x = (std::sqrt(ac[901]) * p.x0 + std::sqrt(1 - ac[901]) * p.eps);
  const SchedulerStepOutput out = StepOne(scheduler, *state, p.eps, x);
  const torch::Tensor x0 = p.x0.clamp(-0.25, 0.25);
  ExpectGoldenClose("ddim/clipped_x0", out.pred_original_sample, x0, 1e-5, 1e-5);
  // Epsilon is NOT recomputed from the clipped x0 (diffusers).
  ExpectGoldenClose("ddim/clipped_prev", out.prev_sample,
                    std::sqrt(ac[801]) * x0 + std::sqrt(1 - ac[801]) * p.eps, 1e-5, 1e-5);
}

TEST(EulerAnalyticTest, TimestepsSigmasAndInitNoiseSigma) {
  const std::vector<double> ac = Sd15AlphasCumprod();
  auto sigma = [&](double t) {
    const int64_t lo = static_cast<int64_t>(std::floor(t));
    auto s = [&](int64_t i) { return std::sqrt((1 - ac[i]) / ac[i]); };
    return lo == t ? s(lo) : s(lo) + (s(lo + 1) - s(lo)) * (t - lo);
  };
  SchedulerSettings s = Sd15Settings(SchedulerType::kEulerDiscrete);
  struct Case {
    TimestepSpacing spacing;
    int n;
    std::vector<float> timesteps;
  };
  for (const Case& c : std::vector<Case>{
           {TimestepSpacing::kLinspace, 3, {999, 499.5f, 0}},
           {TimestepSpacing::kLinspace, 4, {999, 666, 333, 0}},
           {TimestepSpacing::kLeading, 4, {751, 501, 251, 1}},
           {TimestepSpacing::kTrailing, 4, {999, 749, 499, 249}},
       }) {
    s.timestep_spacing = c.spacing;
    const Scheduler scheduler = MakeScheduler(s);
    auto state = scheduler.NewState(c.n);
    ASSERT_TRUE(state.ok());
    ASSERT_EQ(state->timesteps().scalar_type(), torch::kFloat32);
    EXPECT_TRUE(torch::equal(state->timesteps(), torch::tensor(c.timesteps))) << state->timesteps();
    std::vector<float> want;
    for (float t : c.timesteps) want.push_back(static_cast<float>(sigma(t)));
    want.push_back(0);  // final_sigmas_type zero
    ExpectGoldenClose("euler/sigmas", state->sigmas(), torch::tensor(want), 2e-6);
    const double max_sigma = sigma(c.timesteps[0]);
    const double expected_init =
        c.spacing == TimestepSpacing::kLeading ? std::sqrt(max_sigma * max_sigma + 1) : max_sigma;
    EXPECT_NEAR(scheduler.InitNoiseSigma(*state), expected_init, 1e-5 * expected_init);
    // scale_model_input divides by sqrt(sigma^2 + 1) of the current step.
    const torch::Tensor x = torch::ones({1, 2, 2, 2});
    const SchedulerState* states[] = {&*state};
    auto scaled = scheduler.ScaleModelInput(states, x);
    ASSERT_TRUE(scaled.ok());
    ExpectGoldenClose("euler/scale_model_input", *scaled, x / std::sqrt(max_sigma * max_sigma + 1),
                      1e-6);
  }
}

TEST(EulerAnalyticTest, PerfectModelFollowsTheExactTrajectory) {
  const std::vector<double> ac = Sd15AlphasCumprod();
  for (const std::string prediction : {"epsilon", "sample", "v_prediction"}) {
    SchedulerSettings s = Sd15Settings(SchedulerType::kEulerDiscrete);
    s.prediction_type = prediction;
    const Scheduler scheduler = MakeScheduler(s);
    auto state = scheduler.NewState(4);  // linspace: 999, 666, 333, 0
    ASSERT_TRUE(state.ok());
    const std::vector<int64_t> t = {999, 666, 333, 0};
    auto sigma = [&](int i) { return i < 4 ? std::sqrt((1 - ac[t[i]]) / ac[t[i]]) : 0.0; };
    const Perfect p = MakePerfect();
    torch::Tensor x = p.x0 + sigma(0) * p.eps;  // VE form: x = x0 + sigma * eps
    for (int i = 0; i < 4; ++i) {
      const double sg = sigma(i);
      // v-prediction in VE form: v = (eps - sigma * x0) / sqrt(sigma^2 + 1)... with
      // the scaled input c_in*x, diffusers' denoised = v * -sigma/sqrt(s^2+1) + x/(s^2+1).
      torch::Tensor model_output =
          prediction == "epsilon"  ? p.eps
          : prediction == "sample" ? p.x0
                                   : ((x / (sg * sg + 1)) - p.x0) * (std::sqrt(sg * sg + 1) / sg);
      const SchedulerStepOutput out = StepOne(scheduler, *state, model_output, x);
      ExpectGoldenClose("euler/" + prediction + "/x0." + std::to_string(i),
                        out.pred_original_sample, p.x0, 1e-5, 1e-5);
      ExpectGoldenClose("euler/" + prediction + "/prev." + std::to_string(i), out.prev_sample,
                        p.x0 + sigma(i + 1) * p.eps, 1e-5, 1e-5);
      x = out.prev_sample;
    }
    ExpectGoldenClose("euler/final_is_x0", x, p.x0, 1e-5, 1e-5);
  }
}

// The multistep solvers collapse to the exact trajectory too: with a
// perfect model every difference term D1 is zero, for data (x0) and noise
// (eps) prediction alike, in every order.
TEST(MultistepAnalyticTest, PerfectModelFollowsTheExactTrajectory) {
  struct Case {
    SchedulerType type;
    std::string solver_type;
    bool data_prediction;  // UniPC predict_x0 / DPM-Solver++ (else noise)
    int solver_order;
  };
  const std::vector<Case> cases = {
      {SchedulerType::kUniPCMultistep, "bh1", true, 2},
      {SchedulerType::kUniPCMultistep, "bh2", true, 2},
      {SchedulerType::kUniPCMultistep, "bh2", true, 3},
      {SchedulerType::kUniPCMultistep, "bh2", false, 2},
      {SchedulerType::kUniPCMultistep, "bh1", false, 3},
      {SchedulerType::kDPMSolverMultistep, "midpoint", true, 2},
      {SchedulerType::kDPMSolverMultistep, "heun", true, 2},
      {SchedulerType::kDPMSolverMultistep, "midpoint", true, 3},
      {SchedulerType::kDPMSolverMultistep, "midpoint", false, 2},
      {SchedulerType::kDPMSolverMultistep, "heun", false, 3},
  };
  for (const Case& c : cases) {
    SchedulerSettings s = Sd15Settings(c.type);
    s.solver_type = c.solver_type;
    s.solver_order = c.solver_order;
    s.predict_x0 = c.data_prediction;
    if (c.type == SchedulerType::kDPMSolverMultistep && !c.data_prediction) {
      s.algorithm_type = "dpmsolver";
      s.final_sigmas_type = "sigma_min";  // diffusers refuses "zero" here
    }
    const std::string name = std::string(SchedulerTypeName(c.type)) + "/" + c.solver_type +
                             (c.data_prediction ? "/x0" : "/eps") + "/order" +
                             std::to_string(c.solver_order);
    const Scheduler scheduler = MakeScheduler(s);
    const int n = 7;
    auto state = scheduler.NewState(n);
    ASSERT_TRUE(state.ok());
    const Perfect p = MakePerfect();
    auto on_trajectory = [&](float sigma) {
      const double alpha = 1 / std::sqrt(double(sigma) * sigma + 1);
      return (alpha * p.x0.to(torch::kFloat64) + alpha * sigma * p.eps.to(torch::kFloat64))
          .to(torch::kFloat32);
    };
    const auto sigmas = state->sigmas();
    torch::Tensor x = on_trajectory(sigmas[0].item<float>());
    std::vector<int> orders;
    for (int i = 0; i < n; ++i) {
      const SchedulerStepOutput out = StepOne(scheduler, *state, p.eps, x);
      orders.push_back(state->last_order());
      ExpectGoldenClose(name + "/prev." + std::to_string(i), out.prev_sample,
                        on_trajectory(sigmas[i + 1].item<float>()), 1e-5, 1e-5);
      ExpectGoldenClose(name + "/x0." + std::to_string(i), out.pred_original_sample, p.x0, 1e-5,
                        1e-5);
      x = out.prev_sample;
    }
    // Warm-up, then the configured order, then lower_order_final (< 15 steps).
    std::vector<int> expected_orders;
    for (int i = 0; i < n; ++i) {
      expected_orders.push_back(std::min({c.solver_order, i + 1, n - i}));
    }
    if (c.type == SchedulerType::kDPMSolverMultistep) expected_orders.back() = 1;
    EXPECT_EQ(orders, expected_orders) << name;
  }
}

// ---------------------------------------------------------------------------
// Step-level batching: items at different steps (and with different step
// counts) in one batch give the same result as each run alone.

struct BatchRun {
  int num_steps;
  int start_after;  // number of solo steps before joining the batch
};

torch::Tensor FakeModelOutput(int item, int step) {
  torch::manual_seed(100 * item + step);
  return torch::randn({1, 4, 6, 5});
}

TEST(SchedulerBatchTest, ItemsAtDifferentStepsMatchSoloRuns) {
  const std::vector<BatchRun> runs = {{10, 0}, {4, 0}, {10, 3}, {7, 5}, {25, 1}};
  for (SchedulerType type : {SchedulerType::kUniPCMultistep, SchedulerType::kDPMSolverMultistep,
                             SchedulerType::kDDIM, SchedulerType::kEulerDiscrete}) {
    SchedulerSettings s = Sd15Settings(type);
    if (type == SchedulerType::kDPMSolverMultistep) s.solver_order = 3;  // exercise all orders
    const Scheduler scheduler = MakeScheduler(s);

    // Solo references: every sample of every step.
    std::vector<std::vector<torch::Tensor>> solo(runs.size());
    for (size_t r = 0; r < runs.size(); ++r) {
      auto state = scheduler.NewState(runs[r].num_steps);
      ASSERT_TRUE(state.ok());
      torch::manual_seed(7 + r);
      torch::Tensor x = torch::randn({1, 4, 6, 5});
      solo[r].push_back(x);
      for (int i = 0; i < runs[r].num_steps; ++i) {
        x = StepOne(scheduler, *state, FakeModelOutput(r, i), x).prev_sample;
        solo[r].push_back(x);
      }
    }

    // Batched: each run first takes `start_after` solo steps, then all
    // unfinished runs step together, each at its own index.
    std::vector<SchedulerState> states;
    std::vector<torch::Tensor> x(runs.size());
    for (size_t r = 0; r < runs.size(); ++r) {
      auto state = scheduler.NewState(runs[r].num_steps);
      ASSERT_TRUE(state.ok());
      states.push_back(*state);
      x[r] = solo[r][0];
      for (int i = 0; i < runs[r].start_after; ++i) {
        x[r] = StepOne(scheduler, states[r], FakeModelOutput(r, i), x[r]).prev_sample;
      }
    }
    double max_diff = 0;
    int batched_steps = 0;
    while (true) {
      std::vector<size_t> active;
      for (size_t r = 0; r < runs.size(); ++r) {
        if (!states[r].finished()) active.push_back(r);
      }
      if (active.empty()) break;
      std::vector<SchedulerState*> batch_states;
      std::vector<torch::Tensor> outputs, samples;
      for (size_t r : active) {
        batch_states.push_back(&states[r]);
        outputs.push_back(FakeModelOutput(r, states[r].step_index()));
        samples.push_back(x[r]);
      }
      auto out = scheduler.Step(batch_states, torch::cat(outputs), torch::cat(samples));
      ASSERT_TRUE(out.ok()) << out.status();
      for (size_t j = 0; j < active.size(); ++j) {
        const size_t r = active[j];
        x[r] = out->prev_sample.narrow(0, j, 1);
        const torch::Tensor& want = solo[r][states[r].step_index()];
        max_diff = std::max(max_diff, (x[r] - want).abs().max().item<double>());
      }
      ++batched_steps;
    }
    EXPECT_GT(batched_steps, 5);
    EXPECT_LE(max_diff, 1e-6) << SchedulerTypeName(type);
    std::cout << "[batch] " << SchedulerTypeName(type) << " max_abs_diff_vs_solo=" << max_diff
              << "\n";
  }
}

// ---------------------------------------------------------------------------
// Settings parsing and errors.

TEST(SchedulerSettingsTest, ParsesPythonInfinityAndKeepsTypeDefaults) {
  auto s = SchedulerSettingsFromJson(
      R"({"_class_name": "DPMSolverMultistepScheduler", "lambda_min_clipped": -Infinity,
          "variance_type": null, "timestep_spacing": "trailing", "solver_order": 3})",
      SchedulerType::kDPMSolverMultistep);
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_TRUE(std::isinf(s->lambda_min_clipped) && s->lambda_min_clipped < 0);
  EXPECT_EQ(s->solver_order, 3);
  EXPECT_EQ(s->solver_type, "midpoint");
  EXPECT_EQ(EffectiveTimestepSpacing(*s), TimestepSpacing::kTrailing);

  auto ddim = SchedulerSettingsFromFile(
      fd::testing::GoldenPath("fd_pipeline/model/scheduler/scheduler_config.json"),
      SchedulerType::kDDIM);
  ASSERT_TRUE(ddim.ok()) << ddim.status();
  EXPECT_EQ(EffectiveTimestepSpacing(*ddim), TimestepSpacing::kLeading);
  EXPECT_FALSE(ddim->set_alpha_to_one);
  EXPECT_FALSE(ddim->clip_sample);
}

TEST(SchedulerSettingsTest, RejectsMalformedConfigs) {
  auto bad_json = SchedulerSettingsFromJson("{not json", SchedulerType::kDDIM);
  EXPECT_EQ(bad_json.status().code(), absl::StatusCode::kInvalidArgument);
  auto wrong_type =
      SchedulerSettingsFromJson(R"({"solver_order": "two"})", SchedulerType::kUniPCMultistep);
  EXPECT_EQ(wrong_type.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(wrong_type.status().message(), HasSubstr("solver_order"));
  auto spacing = SchedulerSettingsFromJson(R"({"timestep_spacing": "sideways"})",
                                           SchedulerType::kUniPCMultistep);
  EXPECT_THAT(spacing.status().message(), HasSubstr("timestep_spacing"));
  auto missing =
      SchedulerSettingsFromFile("/nonexistent/scheduler_config.json", SchedulerType::kDDIM);
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);

  EXPECT_EQ(*SchedulerTypeFromName("UniPCMultistepScheduler"), SchedulerType::kUniPCMultistep);
  EXPECT_EQ(*SchedulerTypeFromName("dpmsolver++"), SchedulerType::kDPMSolverMultistep);
  EXPECT_EQ(*SchedulerTypeFromName("Euler"), SchedulerType::kEulerDiscrete);
  EXPECT_EQ(SchedulerTypeFromName("pndm").status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(SchedulerCreateTest, RejectsUnsupportedOptions) {
  SchedulerSettings s;
  s.beta_schedule = "quadratic";
  EXPECT_THAT(Scheduler::Create(s).status().message(), HasSubstr("beta_schedule"));
  s = SchedulerSettings();
  s.prediction_type = "flow";
  EXPECT_THAT(Scheduler::Create(s).status().message(), HasSubstr("prediction_type"));
  s = SchedulerSettings();
  s.thresholding = true;
  EXPECT_EQ(Scheduler::Create(s).status().code(), absl::StatusCode::kUnimplemented);
  s = SchedulerSettings();
  s.use_karras_sigmas = true;
  EXPECT_EQ(Scheduler::Create(s).status().code(), absl::StatusCode::kUnimplemented);
  s = SchedulerSettings();
  s.type = SchedulerType::kDPMSolverMultistep;
  s.algorithm_type = "sde-dpmsolver++";
  EXPECT_EQ(Scheduler::Create(s).status().code(), absl::StatusCode::kUnimplemented);
  s.algorithm_type = "dpmsolver";  // with final_sigmas_type zero: diffusers raises
  EXPECT_EQ(Scheduler::Create(s).status().code(), absl::StatusCode::kInvalidArgument);
  s = SchedulerSettings();
  s.type = SchedulerType::kUniPCMultistep;
  s.solver_type = "midpoint";  // diffusers maps it to bh2
  auto unipc = Scheduler::Create(s);
  ASSERT_TRUE(unipc.ok());
  EXPECT_EQ(unipc->settings().solver_type, "bh2");
  s.trained_betas = {0.1, 0.2};
  EXPECT_THAT(Scheduler::Create(s).status().message(), HasSubstr("trained_betas"));
}

TEST(SchedulerStepTest, RejectsBadInputsWithoutTouchingStates) {
  const Scheduler scheduler = MakeScheduler(Sd15Settings(SchedulerType::kUniPCMultistep));
  EXPECT_EQ(scheduler.NewState(0).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(scheduler.NewState(1001).status().code(), absl::StatusCode::kInvalidArgument);

  auto a = scheduler.NewState(2);
  auto b = scheduler.NewState(2);
  ASSERT_TRUE(a.ok() && b.ok());
  const torch::Tensor x = torch::zeros({2, 4, 6, 5});
  SchedulerState* both[] = {&*a, &*b};
  SchedulerState* one[] = {&*a};
  SchedulerState* twice[] = {&*a, &*a};
  SchedulerState* null_state[] = {&*a, nullptr};

  auto count = scheduler.Step(one, x, x);
  EXPECT_EQ(count.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(count.status().message(), HasSubstr("states"));
  auto shape = scheduler.Step(both, x, torch::zeros({2, 4, 6, 6}));
  EXPECT_THAT(shape.status().message(), HasSubstr("shape"));
  EXPECT_EQ(scheduler.Step(twice, x, x).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(scheduler.Step(null_state, x, x).status().code(), absl::StatusCode::kInvalidArgument);
  auto ints = scheduler.Step(both, x.to(torch::kInt64), x.to(torch::kInt64));
  EXPECT_EQ(ints.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(a->step_index(), 0);

  const Scheduler other = MakeScheduler(Sd15Settings(SchedulerType::kUniPCMultistep));
  auto foreign = other.Step(both, x, x);
  EXPECT_EQ(foreign.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(foreign.status().message(), HasSubstr("not created by this scheduler"));

  ASSERT_TRUE(scheduler.Step(both, x, x).ok());
  // The history now has [4, 6, 5] items: another latent size is refused.
  auto resized = scheduler.Step(both, torch::zeros({2, 4, 8, 8}), torch::zeros({2, 4, 8, 8}));
  EXPECT_EQ(resized.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(a->step_index(), 1);
  ASSERT_TRUE(scheduler.Step(both, x, x).ok());
  auto finished = scheduler.Step(both, x, x);
  EXPECT_EQ(finished.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(finished.status().message(), HasSubstr("finished"));
}

TEST(SchedulerStepTest, ReturnsTheSampleDtype) {
  const Scheduler scheduler = MakeScheduler(Sd15Settings(SchedulerType::kDPMSolverMultistep));
  auto state = scheduler.NewState(3);
  ASSERT_TRUE(state.ok());
  const torch::Tensor x = torch::randn({1, 4, 6, 5}).to(torch::kFloat64);
  SchedulerState* states[] = {&*state};
  auto out = scheduler.Step(states, x, x);
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ(out->prev_sample.scalar_type(), torch::kFloat64);
  EXPECT_EQ(out->pred_original_sample.scalar_type(), torch::kFloat32);
}

}  // namespace
}  // namespace fd::model
