#include "model/pipeline/frame_pipeline.h"

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <set>
#include <tuple>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/runtime/batch_invariance.h"
#include "model/runtime/companion_thread.h"
#include "model/runtime/device_transfer.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

using Clock = std::chrono::steady_clock;

double MsSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

std::string Shape(const torch::Tensor& t) {
  return absl::StrCat("[", absl::StrJoin(t.sizes(), ", "), "]");
}

absl::Status ItemError(size_t item, absl::string_view field, absl::string_view what) {
  return absl::InvalidArgumentError(absl::StrCat("item ", item, ": ", field, " ", what));
}

// Floating tensors must be finite.
absl::Status CheckFinite(size_t item, absl::string_view field, const torch::Tensor& t) {
  if (t.is_floating_point() && !torch::isfinite(t).all().item<bool>()) {
    return ItemError(item, field, "contains NaN or Inf");
  }
  return absl::OkStatus();
}

// An HWC image ([H, W, C] or [H, W] for C = 1) -> [1, C, H, W] (same dtype,
// CPU), validated: uint8 or floating point in [0, 1], finite.
absl::StatusOr<torch::Tensor> ImageToNchw(size_t item, absl::string_view field,
                                          const torch::Tensor& image, int64_t channels) {
  if (!image.defined()) return ItemError(item, field, "is missing");
  torch::Tensor hwc = image;
  if (hwc.dim() == 2 && channels == 1) hwc = hwc.unsqueeze(2);
  if (hwc.dim() != 3 || hwc.size(2) != channels) {
    return ItemError(item, field,
                     absl::StrCat("must be [H, W, ", channels, "] (HWC), got ", Shape(image)));
  }
  if (hwc.scalar_type() != torch::kUInt8 && !hwc.is_floating_point()) {
    return ItemError(item, field, "must be uint8 or floating point");
  }
  hwc = hwc.to(torch::kCPU);
  if (hwc.is_floating_point()) {
    FD_RETURN_IF_ERROR(CheckFinite(item, field, hwc));
    if (hwc.numel() > 0 && (hwc.min().item<double>() < 0 || hwc.max().item<double>() > 1)) {
      return ItemError(item, field, "has values outside [0, 1]");
    }
  }
  return hwc.permute({2, 0, 1}).unsqueeze(0).contiguous();
}

absl::Status CheckSize(size_t item, absl::string_view field, const torch::Tensor& nchw, int64_t h,
                       int64_t w) {
  if (nchw.size(2) != h || nchw.size(3) != w) {
    return ItemError(item, field,
                     absl::StrCat("is ", nchw.size(2), "x", nchw.size(3), ", expected ", h, "x", w,
                                  " (the basecolor's size)"));
  }
  return absl::OkStatus();
}

// A given [1, C, h, w] float tensor (noise, latent, condition).
absl::StatusOr<torch::Tensor> GivenTensor(size_t item, absl::string_view field,
                                          const torch::Tensor& t, int64_t c, int64_t h, int64_t w) {
  if (t.dim() != 4 || t.size(0) != 1 || t.size(1) != c || t.size(2) != h || t.size(3) != w) {
    return ItemError(item, field,
                     absl::StrCat("must be [1, ", c, ", ", h, ", ", w, "], got ", Shape(t)));
  }
  if (!t.is_floating_point()) return ItemError(item, field, "must be floating point");
  FD_RETURN_IF_ERROR(CheckFinite(item, field, t));
  return t.to(torch::kFloat32);
}

// Sets the calling thread's LibTorch intra-op threads for a scope (0: leaves
// them); restores the previous count (it is per thread under OpenMP).
class ScopedIntraOpThreads {
 public:
  explicit ScopedIntraOpThreads(int threads)
      : previous_(at::get_num_threads()), set_(threads > 0 && threads != previous_) {
    if (set_) at::set_num_threads(threads);
  }
  ~ScopedIntraOpThreads() {
    if (set_) at::set_num_threads(previous_);
  }
  ScopedIntraOpThreads(const ScopedIntraOpThreads&) = delete;
  ScopedIntraOpThreads& operator=(const ScopedIntraOpThreads&) = delete;

 private:
  int previous_;
  bool set_;
};

// torch::cat along the batch, without the copy for a single item (a group of
// one is the common case at low load).
torch::Tensor CatRows(const std::vector<torch::Tensor>& rows) {
  return rows.size() == 1 ? rows.front() : torch::cat(rows, 0);
}

torch::Tensor DrawNoise(uint64_t seed, int64_t c, int64_t h, int64_t w) {
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  return at::randn({1, c, h, w}, gen, torch::TensorOptions().dtype(torch::kFloat32));
}

// Begin's phases, in order, for item `i` (messages name it). Each fills its
// part of `state`; errors are INVALID_ARGUMENT naming the field unless said.

// The frame size, from the ready condition or the basecolor: a multiple of
// 8 and of the VAE's downsampling `factor`.
absl::Status FrameSize(size_t i, const PipelineInput& req, int64_t factor, FrameState& state) {
  const bool ready_condition = req.condition.defined();
  if (ready_condition) {
    if (req.basecolor.defined() || req.normals.defined() || req.depth.defined() ||
        req.roughness.defined() || req.metallic.defined()) {
      return ItemError(i, "condition", "is given together with G-buffer images");
    }
    if (req.condition.dim() != 4) {
      return ItemError(i, "condition",
                       absl::StrCat("must be [1, 10, H, W], got ", Shape(req.condition)));
    }
    state.height = req.condition.size(2);
    state.width = req.condition.size(3);
  } else {
    if (!req.basecolor.defined()) return ItemError(i, "basecolor", "is missing");
    if (req.basecolor.dim() < 2) return ItemError(i, "basecolor", "must be [H, W, 3]");
    state.height = req.basecolor.size(0);
    state.width = req.basecolor.size(1);
  }
  const int64_t H = state.height, W = state.width;
  if (H <= 0 || W <= 0 || H % 8 != 0 || W % 8 != 0 || H % factor != 0 || W % factor != 0) {
    return ItemError(
        i, ready_condition ? "condition" : "basecolor",
        absl::StrCat("size ", H, "x", W, " is not a multiple of ", std::max<int64_t>(8, factor)));
  }
  return absl::OkStatus();
}

// Steps, sampler, guidance and conditioning scale: the request's, else the
// environment's. Returns the number of steps. NOT_FOUND for a sampler the
// environment does not have.
absl::StatusOr<int> ResolveSettings(size_t i, const PipelineInput& req, const Environment& env,
                                    FrameState& state) {
  if (req.steps < 0) return ItemError(i, "steps", "must be >= 1");
  const int steps = req.steps > 0 ? req.steps : env.settings.steps;
  state.scheduler_type = req.scheduler.value_or(env.settings.scheduler);
  FD_ASSIGN_OR_RETURN(state.scheduler, env.GetScheduler(state.scheduler_type));
  state.guidance_scale = req.guidance_scale.value_or(env.settings.guidance_scale);
  if (!(state.guidance_scale >= 1)) return ItemError(i, "guidance_scale", "must be >= 1");
  state.conditioning_scale = req.conditioning_scale.value_or(env.settings.conditioning_scale);
  if (!std::isfinite(state.conditioning_scale)) {
    return ItemError(i, "conditioning_scale", "must be finite");
  }
  state.want_float = req.want_float;
  return steps;
}

// The prompt embeddings [1, T, cross_dim] (and the negative ones for
// guidance > 1) on the model's device. FAILED_PRECONDITION when the
// environment has none to offer.
absl::Status PromptEmbeddings(size_t i, const PipelineInput& req, const Environment& env,
                              FrameState& state) {
  const int64_t cross_dim = env.unet->config().cross_attention_dim[0];
  torch::Tensor embeds = req.prompt_embeds.defined() ? req.prompt_embeds : env.prompt_embeds;
  if (!embeds.defined()) {
    return absl::FailedPreconditionError(
        absl::StrCat("item ", i, ": the environment has no prompt embeddings and none were given"));
  }
  if (embeds.dim() != 3 || embeds.size(0) != 1 || embeds.size(2) != cross_dim ||
      !embeds.is_floating_point()) {
    return ItemError(i, "prompt_embeds",
                     absl::StrCat("must be floating [1, T, ", cross_dim, "], got ", Shape(embeds)));
  }
  FD_RETURN_IF_ERROR(CheckFinite(i, "prompt_embeds", embeds));
  state.prompt_embeds = embeds.to(env.device, torch::kFloat32);
  if (state.guidance_scale > 1) {
    if (!env.negative_prompt_embeds.defined() ||
        env.negative_prompt_embeds.size(1) != embeds.size(1)) {
      return absl::FailedPreconditionError(absl::StrCat(
          "item ", i, ": guidance_scale > 1 needs negative prompt embeddings of length ",
          embeds.size(1), " (text encoder or negative_prompt_embeds.safetensors)"));
    }
    state.negative_embeds = env.negative_prompt_embeds.to(env.device, torch::kFloat32);
  }
  return absl::OkStatus();
}

// The previous frame and its basecolor as NCHW [1, 3, H, W] (undefined when
// not given), validated before the conditioning and the VAE use them.
struct PreviousImages {
  torch::Tensor frame;
  torch::Tensor basecolor;
};
absl::StatusOr<PreviousImages> PreviousFrame(size_t i, const PipelineInput& req, int64_t H,
                                             int64_t W) {
  PreviousImages prev;
  if (req.previous_frame.defined()) {
    FD_ASSIGN_OR_RETURN(prev.frame, ImageToNchw(i, "previous_frame", req.previous_frame, 3));
    FD_RETURN_IF_ERROR(CheckSize(i, "previous_frame", prev.frame, H, W));
  }
  if (req.previous_basecolor.defined()) {
    FD_ASSIGN_OR_RETURN(prev.basecolor,
                        ImageToNchw(i, "previous_basecolor", req.previous_basecolor, 3));
    FD_RETURN_IF_ERROR(CheckSize(i, "previous_basecolor", prev.basecolor, H, W));
  }
  return prev;
}

// The ControlNet condition [1, 10, H, W] on the model's device: the ready
// one, or built from the G-buffer, the irradiance and the sky fill
// (conditioning.h), which also fill the state's irradiance and basecolor.
absl::Status Condition(size_t i, const PipelineInput& req, const Environment& env,
                       const PreviousImages& prev, FrameState& state) {
  const int64_t H = state.height, W = state.width;
  if (req.condition.defined()) {
    FD_ASSIGN_OR_RETURN(state.condition,
                        GivenTensor(i, "condition", req.condition, kConditionChannels, H, W));
    return absl::OkStatus();
  }
  FrameConditionInputs in;
  FD_ASSIGN_OR_RETURN(in.gbuffer.basecolor, ImageToNchw(i, "basecolor", req.basecolor, 3));
  FD_ASSIGN_OR_RETURN(in.gbuffer.normals, ImageToNchw(i, "normals", req.normals, 3));
  FD_ASSIGN_OR_RETURN(in.gbuffer.depth, ImageToNchw(i, "depth", req.depth, 1));
  FD_ASSIGN_OR_RETURN(in.gbuffer.roughness, ImageToNchw(i, "roughness", req.roughness, 1));
  FD_RETURN_IF_ERROR(CheckSize(i, "normals", in.gbuffer.normals, H, W));
  FD_RETURN_IF_ERROR(CheckSize(i, "depth", in.gbuffer.depth, H, W));
  FD_RETURN_IF_ERROR(CheckSize(i, "roughness", in.gbuffer.roughness, H, W));
  if (req.metallic.defined()) {
    FD_ASSIGN_OR_RETURN(in.gbuffer.metallic, ImageToNchw(i, "metallic", req.metallic, 1));
    FD_RETURN_IF_ERROR(CheckSize(i, "metallic", in.gbuffer.metallic, H, W));
  }
  if (prev.frame.defined() != prev.basecolor.defined()) {
    return ItemError(i, prev.frame.defined() ? "previous_basecolor" : "previous_frame",
                     "is missing (the irradiance needs both)");
  }
  in.previous_output = prev.frame;
  in.previous_basecolor = prev.basecolor;
  in.black_irradiance = !env.settings.irradiance_from_previous;
  in.sky_fill = req.sky_mode.value_or(env.settings.sky_mode);
  if (in.sky_fill == SkyFillMode::kSkyImage) {
    FD_ASSIGN_OR_RETURN(in.sky_image, ImageToNchw(i, "sky_image", req.sky_image, 3));
    FD_RETURN_IF_ERROR(CheckSize(i, "sky_image", in.sky_image, H, W));
  } else if (in.sky_fill == SkyFillMode::kPreviousOutput && !prev.frame.defined()) {
    // G-buffer-only start: nothing to fill the sky from.
    in.sky_fill = SkyFillMode::kNone;
  }
  absl::StatusOr<FrameCondition> cond = BuildFrameCondition(in);
  if (!cond.ok()) {
    return absl::Status(cond.status().code(),
                        absl::StrCat("item ", i, ": ", cond.status().message()));
  }
  state.condition = ToDeviceAsync(cond->condition.to(torch::kFloat32), env.device);
  if (state.keep_intermediates) {
    state.irradiance = cond->irradiance;
    state.irradiance_u8 = cond->irradiance_u8;
    state.basecolor = cond->basecolor;
  }
  return absl::OkStatus();
}

// The ControlNet's condition embedding [1, C0, h, w], once per frame (it
// would be the same at every step); the condition itself is dropped unless
// kept for inspection.
absl::Status ConditionEmbedding(const Environment& env, FrameState& state) {
  ControlNetModel controlnet = env.controlnet;  // holders share the module
  FD_ASSIGN_OR_RETURN(state.condition_embedding,
                      controlnet->RunConditionEmbedding(state.condition));
  if (!state.keep_intermediates) state.condition = torch::Tensor();
  return absl::OkStatus();
}

// The previous latent [1, C, h, w] (scaled) on the model's device: given,
// the VAE-encoded previous frame (prepare_lora_conditions, one posterior
// sample), or zeros for a G-buffer-only start.
absl::Status PreviousLatent(size_t i, const PipelineInput& req, const Environment& env,
                            const torch::Tensor& prev_frame, FrameState& state) {
  AutoencoderKL vae = env.vae;  // holders share the module; non-const access
  const int64_t factor = vae->downsampling_factor();
  const int64_t latent_channels = vae->config().latent_channels;
  const int64_t h = state.height / factor, w = state.width / factor;
  if (req.prev_latent.defined()) {
    FD_ASSIGN_OR_RETURN(state.prev_latent,
                        GivenTensor(i, "prev_latent", req.prev_latent, latent_channels, h, w));
    state.prev_latent = ToDeviceAsync(state.prev_latent, env.device);
    return absl::OkStatus();
  }
  if (!prev_frame.defined()) {
    state.prev_latent =
        torch::zeros({1, latent_channels, h, w}, torch::TensorOptions().device(env.device));
    return absl::OkStatus();
  }
  torch::Tensor noise;
  if (req.vae_sample_noise.defined()) {
    FD_ASSIGN_OR_RETURN(
        noise, GivenTensor(i, "vae_sample_noise", req.vae_sample_noise, latent_channels, h, w));
  } else {
    noise = DrawNoise(req.vae_noise_seed, latent_channels, h, w);
  }
  // prepare_lora_conditions: np.float32 / 255 -> * 2 - 1.
  torch::Tensor x = prev_frame.scalar_type() == torch::kUInt8
                        ? prev_frame.to(torch::kFloat32) / 255.0
                        : prev_frame.to(torch::kFloat32);
  x = x * 2 - 1;
  FD_ASSIGN_OR_RETURN(LatentPosterior posterior, vae->Encode(ToDeviceAsync(x, env.device)));
  state.prev_latent =
      (posterior.Sample(
           ToDeviceAsync(noise, posterior.mean.device()).to(posterior.mean.scalar_type())) *
       vae->config().scaling_factor)
          .to(torch::kFloat32);
  return absl::OkStatus();
}

// A UNet with basecolor patches (UNet2DConditionConfig::basecolor_patch_channels)
// takes them after the previous latent: prev_latent becomes the whole extra
// input of conv_in, [1, 4 + 3 f^2, h, w], built once per frame.
absl::Status AppendBasecolorPatches(const Environment& env, FrameState& state) {
  if (env.unet->config().basecolor_patch_channels == 0) return absl::OkStatus();
  FD_ASSIGN_OR_RETURN(torch::Tensor patches,
                      BasecolorPatches(state.condition, env.vae->downsampling_factor()));
  state.prev_latent = torch::cat({state.prev_latent, patches.to(state.prev_latent.dtype())}, 1);
  return absl::OkStatus();
}

// The sampler state for `steps` and x_T = noise * init_noise_sigma on the
// model's device.
absl::Status InitialLatents(size_t i, const PipelineInput& req, const Environment& env, int steps,
                            FrameState& state) {
  const int64_t factor = env.vae->downsampling_factor();
  const int64_t latent_channels = env.vae->config().latent_channels;
  const int64_t h = state.height / factor, w = state.width / factor;
  FD_ASSIGN_OR_RETURN(state.scheduler_state, state.scheduler->NewState(steps));
  torch::Tensor init;
  if (req.init_noise.defined()) {
    FD_ASSIGN_OR_RETURN(init, GivenTensor(i, "init_noise", req.init_noise, latent_channels, h, w));
  } else {
    init = DrawNoise(req.init_noise_seed, latent_channels, h, w);
  }
  state.latents =
      ToDeviceAsync(init * state.scheduler->InitNoiseSigma(state.scheduler_state), env.device);
  return absl::OkStatus();
}

}  // namespace

FramePipeline::FramePipeline(std::shared_ptr<const Environment> environment,
                             FramePipelineOptions options)
    : env_(std::move(environment)),
      vae_decode_(options.vae_decode),
      batch_invariant_(options.batch_invariant),
      time_embeddings_(std::make_shared<TimeEmbeddingCache>()),
      prompt_kv_(std::make_shared<PromptKvCache>()),
      intra_op_threads_(std::max(0, options.intra_op_threads)),
      controlnet_beside_unet_(options.controlnet_beside_unet),
      vae_on_free_core_(options.vae_on_free_core),
      core_budget_(options.core_budget != nullptr ? options.core_budget : &CoreBudget::Process()) {}

CoreBudget::Claim FramePipeline::ClaimCores() const {
  return core_budget_->Take(intra_op_threads_ > 0 ? intra_op_threads_ : at::get_num_threads());
}

std::optional<CoreBudget::Claim> FramePipeline::ClaimFreeCoreForVae() const {
  if (!vae_on_free_core_ || batch_invariant_ || !env_->device.is_cpu() || intra_op_threads_ != 1) {
    return std::nullopt;
  }
  return core_budget_->TryTake(1);
}

bool FramePipeline::BatchDecode() const {
  switch (vae_decode_) {
    case VaeDecodeBatching::kBatched:
      return true;
    case VaeDecodeBatching::kPerItem:
      return false;
    case VaeDecodeBatching::kAuto:
      break;
  }
  // Batch invariance keeps per-item decodes on the CPU: a batched decode
  // was not bitwise the item's own (FramePipelineTest.BatchInvariant*).
  return env_->device.is_cuda() || (!batch_invariant_ && at::get_num_threads() > 1);
}

absl::StatusOr<std::vector<FrameState>> FramePipeline::Begin(
    absl::Span<const PipelineInput> items) const {
  const Environment& env = *env_;
  const int64_t factor = env.vae->downsampling_factor();
  std::vector<FrameState> states;
  states.reserve(items.size());
  for (size_t i = 0; i < items.size(); ++i) {
    const PipelineInput& req = items[i];
    const auto start = Clock::now();
    FrameState state;
    const CoreBudget::Claim computing = ClaimCores();
    const std::optional<CoreBudget::Claim> free_core = ClaimFreeCoreForVae();
    absl::Status status = TorchCall("FramePipeline::Begin", [&]() -> absl::Status {
      torch::InferenceMode inference_mode;
      ScopedIntraOpThreads threads(free_core ? intra_op_threads_ + 1 : intra_op_threads_);
      FD_RETURN_IF_ERROR(FrameSize(i, req, factor, state));
      FD_ASSIGN_OR_RETURN(const int steps, ResolveSettings(i, req, env, state));
      FD_RETURN_IF_ERROR(PromptEmbeddings(i, req, env, state));
      FD_ASSIGN_OR_RETURN(const PreviousImages prev,
                          PreviousFrame(i, req, state.height, state.width));
      state.keep_intermediates = req.keep_intermediates;
      FD_RETURN_IF_ERROR(Condition(i, req, env, prev, state));
      FD_RETURN_IF_ERROR(PreviousLatent(i, req, env, prev.frame, state));
      FD_RETURN_IF_ERROR(AppendBasecolorPatches(env, state));
      FD_RETURN_IF_ERROR(ConditionEmbedding(env, state));
      return InitialLatents(i, req, env, steps, state);
    });
    if (!status.ok()) {
      if (status.code() == absl::StatusCode::kNotFound ||
          status.code() == absl::StatusCode::kInvalidArgument) {
        if (!absl::StartsWith(status.message(), "item ")) {
          return absl::Status(status.code(), absl::StrCat("item ", i, ": ", status.message()));
        }
      }
      return status;
    }
    state.timings.encode_ms = MsSince(start);
    states.push_back(std::move(state));
  }
  return states;
}

absl::Status FramePipeline::Step(absl::Span<FrameState* const> states) const {
  const Environment& env = *env_;
  // Group key: everything that must agree inside one network call.
  using Key = std::tuple<int64_t, int64_t, int, int64_t, double, double>;
  std::map<Key, std::vector<FrameState*>> groups;
  std::set<const FrameState*> seen;
  for (size_t i = 0; i < states.size(); ++i) {
    FrameState* s = states[i];
    if (s == nullptr) return absl::InvalidArgumentError(absl::StrCat("state ", i, " is null"));
    if (!seen.insert(s).second) {
      return absl::InvalidArgumentError(absl::StrCat("state ", i, " is given twice"));
    }
    if (s->scheduler == nullptr || !s->latents.defined()) {
      return absl::InvalidArgumentError(absl::StrCat("state ", i, " did not come from Begin"));
    }
    if (s->finished()) {
      return absl::FailedPreconditionError(absl::StrCat("state ", i, " has finished its steps"));
    }
    groups[Key(s->height, s->width, static_cast<int>(s->scheduler_type), s->prompt_embeds.size(1),
               s->guidance_scale, s->conditioning_scale)]
        .push_back(s);
  }
  const CoreBudget::Claim computing = ClaimCores();
  // A companion core for the whole call, when the mode and the budget allow.
  std::optional<CoreBudget::Claim> companion_core;
  if (env.device.is_cpu()) {
    if (controlnet_beside_unet_ == ControlNetBeside::kAlways) {
      companion_core.emplace(core_budget_->Take(1));
    } else if (controlnet_beside_unet_ == ControlNetBeside::kWhenCoreFree) {
      companion_core = core_budget_->TryTake(1);
    }
  }
  const bool beside = companion_core.has_value();
  return TorchCall("FramePipeline::Step", [&]() -> absl::Status {
    torch::InferenceMode inference_mode;
    ScopedIntraOpThreads threads(intra_op_threads_);
    BatchInvariantScope batch_invariant(batch_invariant_);
    ControlNetModel controlnet = env.controlnet;
    UNet2DConditionModel unet = env.unet;
    for (auto& [key, group] : groups) {
      const auto start = Clock::now();
      const Scheduler& scheduler = *group.front()->scheduler;
      const double guidance = group.front()->guidance_scale;
      const double cond_scale = group.front()->conditioning_scale;
      std::vector<const SchedulerState*> cstates;
      std::vector<SchedulerState*> mstates;
      std::vector<torch::Tensor> latents, cond_embs, prevs, embeds, negs;
      for (FrameState* s : group) {
        cstates.push_back(&s->scheduler_state);
        mstates.push_back(&s->scheduler_state);
        latents.push_back(s->latents);
        cond_embs.push_back(s->condition_embedding);
        prevs.push_back(s->prev_latent);
        embeds.push_back(s->prompt_embeds);
        if (guidance > 1) negs.push_back(s->negative_embeds);
      }
      const torch::Tensor sample = CatRows(latents);
      FD_ASSIGN_OR_RETURN(torch::Tensor model_in, scheduler.ScaleModelInput(cstates, sample));
      FD_ASSIGN_OR_RETURN(const torch::Tensor t, scheduler.CurrentTimesteps(cstates));
      FD_ASSIGN_OR_RETURN(TimeEmbeddingCache::Rows temb,
                          time_embeddings_->Get(controlnet, unet, t));
      torch::Tensor cond_emb = CatRows(cond_embs);
      torch::Tensor prev = CatRows(prevs);
      torch::Tensor ehs = CatRows(embeds);
      if (guidance > 1) {
        // diffusers: rows [uncond..., cond...], same condition / prev latent.
        model_in = torch::cat({model_in, model_in}, 0);
        temb.controlnet = torch::cat({temb.controlnet, temb.controlnet}, 0);
        temb.unet = torch::cat({temb.unet, temb.unet}, 0);
        cond_emb = torch::cat({cond_emb, cond_emb}, 0);
        prev = torch::cat({prev, prev}, 0);
        ehs = torch::cat({CatRows(negs), ehs}, 0);
      }
      // The rows of ehs, for the prompt K/V cache (prompt_kv_cache.h).
      std::vector<torch::Tensor> prompt_rows = guidance > 1 ? negs : std::vector<torch::Tensor>{};
      prompt_rows.insert(prompt_rows.end(), embeds.begin(), embeds.end());
      PromptKvScope prompt_kv(prompt_kv_.get(), prompt_rows);
      const torch::Tensor unet_in = torch::cat({model_in, prev}, 1);
      torch::Tensor eps;
      if (beside) {
        // The down path on the companion (with this thread's scopes), the
        // ControlNet here; then the up path with the residuals.
        absl::StatusOr<UNet2DConditionModelImpl::DownPath> down =
            absl::UnknownError("UNet down path did not run");
        CompanionWork down_work(CompanionThread::ForCurrentThread(), [&] {
          BatchInvariantScope companion_batch_invariant(batch_invariant_);
          PromptKvScope companion_prompt_kv(prompt_kv_.get(), prompt_rows);
          down = unet->RunDown(unet_in, temb.unet, ehs);
        });
        absl::StatusOr<std::vector<torch::Tensor>> residuals =
            controlnet->RunEmbedded(model_in, temb.controlnet, ehs, cond_emb, cond_scale);
        down_work.Join();
        FD_RETURN_IF_ERROR(residuals.status());
        FD_RETURN_IF_ERROR(down.status());
        FD_ASSIGN_OR_RETURN(eps, unet->RunUp(*std::move(down), temb.unet, ehs, *residuals));
      } else {
        FD_ASSIGN_OR_RETURN(
            std::vector<torch::Tensor> residuals,
            controlnet->RunEmbedded(model_in, temb.controlnet, ehs, cond_emb, cond_scale));
        FD_ASSIGN_OR_RETURN(eps, unet->RunEmbedded(unet_in, temb.unet, ehs, residuals));
      }
      eps = eps.to(torch::kFloat32);
      if (guidance > 1) {
        const int64_t n = static_cast<int64_t>(group.size());
        const torch::Tensor uncond = eps.slice(0, 0, n);
        const torch::Tensor text = eps.slice(0, n, 2 * n);
        eps = uncond + guidance * (text - uncond);
      }
      FD_ASSIGN_OR_RETURN(SchedulerStepOutput out, scheduler.Step(mstates, eps, sample));
      const double ms = MsSince(start);
      for (size_t j = 0; j < group.size(); ++j) {
        const int64_t row = static_cast<int64_t>(j);
        group[j]->latents = out.prev_sample.slice(0, row, row + 1).to(torch::kFloat32);
        if (group[j]->keep_intermediates) group[j]->noise_pred = eps.slice(0, row, row + 1);
        group[j]->timings.denoise_ms += ms;
        if (beside) ++group[j]->timings.steps_beside;
      }
    }
    return absl::OkStatus();
  });
}

absl::StatusOr<std::vector<FrameOutput>> FramePipeline::Finish(
    absl::Span<FrameState* const> states) const {
  const Environment& env = *env_;
  for (size_t i = 0; i < states.size(); ++i) {
    if (states[i] == nullptr)
      return absl::InvalidArgumentError(absl::StrCat("state ", i, " is null"));
    if (!states[i]->finished() || !states[i]->latents.defined()) {
      return absl::FailedPreconditionError(absl::StrCat("state ", i, " has not finished"));
    }
  }
  const double sf = env.vae->config().scaling_factor;
  AutoencoderKL vae = env.vae;
  std::vector<FrameOutput> outputs(states.size());
  const CoreBudget::Claim computing = ClaimCores();
  const std::optional<CoreBudget::Claim> free_core = ClaimFreeCoreForVae();
  FD_RETURN_IF_ERROR(TorchCall("FramePipeline::Finish", [&]() -> absl::Status {
    torch::InferenceMode inference_mode;
    ScopedIntraOpThreads threads(free_core ? intra_op_threads_ + 1 : intra_op_threads_);
    const int vae_threads = at::get_num_threads();
    BatchInvariantScope batch_invariant(batch_invariant_);
    // Groups of states decoded by one call: per frame size when batched.
    std::vector<std::vector<size_t>> groups;
    // A decode on a borrowed core stays per item: batched at two threads
    // it raised the server's peak RSS under load (docs/BENCHMARKS.md).
    if (!free_core && BatchDecode()) {
      std::map<std::pair<int64_t, int64_t>, size_t> group_of_size;
      for (size_t i = 0; i < states.size(); ++i) {
        const torch::Tensor& l = states[i]->latents;
        auto [it, added] =
            group_of_size.emplace(std::make_pair(l.size(2), l.size(3)), groups.size());
        if (added) groups.emplace_back();
        groups[it->second].push_back(i);
      }
    } else {
      for (size_t i = 0; i < states.size(); ++i) groups.push_back({i});
    }
    // One group's decode, postprocess and outputs (groups touch disjoint
    // states and outputs).
    const auto decode_group = [&](const std::vector<size_t>& group) -> absl::Status {
      const auto start = Clock::now();
      std::vector<torch::Tensor> latents;
      for (size_t i : group) latents.push_back(states[i]->latents);
      FD_ASSIGN_OR_RETURN(torch::Tensor decoded, vae->Decode(CatRows(latents) / sf));
      // [G, 3, H, W]; one device -> host copy for the group.
      decoded = decoded.to(torch::kCPU, torch::kFloat32);
      // VaeImageProcessor.postprocess: (x / 2 + 0.5).clamp(0, 1); numpy_to_pil:
      // (x * 255).round() (half to even, as torch.round) -> uint8.
      const torch::Tensor images = (decoded / 2 + 0.5).clamp(0, 1);
      const torch::Tensor bytes = (images * 255).round().to(torch::kUInt8);
      const double ms = MsSince(start);
      for (size_t row = 0; row < group.size(); ++row) {
        FrameState& s = *states[group[row]];
        const int64_t r = static_cast<int64_t>(row);
        FrameOutput& out = outputs[group[row]];
        out.image_uint8 = bytes[r].permute({1, 2, 0}).contiguous();
        if (s.want_float) {
          // Own storage per output when the group had several rows.
          const bool alone = group.size() == 1;
          out.image_float = alone ? images : images.slice(0, r, r + 1).clone();
          out.decoded = alone ? decoded : decoded.slice(0, r, r + 1).clone();
        }
        s.timings.decode_ms = ms;  // the group's decode, shared
        s.timings.vae_threads = vae_threads;
        out.latent = s.latents;  // [1, 4, h, w], the state's own tensor
        out.timings = s.timings;
      }
      return absl::OkStatus();
    };
    // Several per-item decodes and a free core: the companion thread decodes
    // every second group (each at one thread, so bitwise as here).
    std::optional<CoreBudget::Claim> companion_core;
    if (!free_core && groups.size() >= 2 && intra_op_threads_ == 1 && env.device.is_cpu() &&
        controlnet_beside_unet_ != ControlNetBeside::kNever) {
      companion_core = core_budget_->TryTake(1);
    }
    if (companion_core) {
      absl::Status companion_status = absl::OkStatus();
      CompanionWork odd_groups(CompanionThread::ForCurrentThread(), [&] {
        BatchInvariantScope companion_batch_invariant(batch_invariant_);
        for (size_t g = 1; g < groups.size() && companion_status.ok(); g += 2) {
          companion_status = decode_group(groups[g]);
        }
      });
      absl::Status status = absl::OkStatus();
      for (size_t g = 0; g < groups.size() && status.ok(); g += 2) status = decode_group(groups[g]);
      odd_groups.Join();
      FD_RETURN_IF_ERROR(status);
      return companion_status;
    }
    for (const std::vector<size_t>& group : groups) FD_RETURN_IF_ERROR(decode_group(group));
    return absl::OkStatus();
  }));
  return outputs;
}

absl::StatusOr<std::vector<FrameOutput>> FramePipeline::Render(
    absl::Span<const PipelineInput> items) const {
  FD_ASSIGN_OR_RETURN(std::vector<FrameState> states, Begin(items));
  std::vector<FrameState*> all;
  for (FrameState& s : states) all.push_back(&s);
  while (true) {
    std::vector<FrameState*> active;
    for (FrameState* s : all) {
      if (!s->finished()) active.push_back(s);
    }
    if (active.empty()) break;
    FD_RETURN_IF_ERROR(Step(active));
  }
  return Finish(all);
}

}  // namespace fd::model
