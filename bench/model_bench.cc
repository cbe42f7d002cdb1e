// Benchmarks of the model/ hot paths.
//
// Fixed benchmarks (CPU): on the golden config-B checkpoint
// (../shared/golden/B, or $FD_GOLDEN_DIR/B) one ControlNet + UNet step, VAE
// encode / decode, and whole frames through FramePipeline at several batch
// sizes; plus whole frames on the `small` preset of model/presets/presets.h
// (random weights, written to a temporary folder on first use), and one
// channels-last GroupNorm at the street VAE's levels, LibTorch's kernel
// against the project's thread-invariant one.
//
// Configurable benchmarks, registered at start-up from --fd_* flags (parsed
// and removed before benchmark::Initialize, so the --benchmark_* flags work
// as usual):
//   BM_PresetFrame/<preset>/<device>/<dtype>/<W>x<H>/steps:<n>/batch:<b>
//       whole frames (G-buffer conditioning, VAE encode of the previous
//       frame, the UniPC steps, decode) on a random-weight preset checkpoint,
//       one benchmark per dtype x batch. Counters: frames_per_second (=
//       items_per_second); for the SD1.5 shapes also TFLOPS (see below);
//       encode_ms / denoise_ms / decode_ms of the last iteration (host-side:
//       on CUDA the split is skewed, the decode's copy to the host waits for
//       the queued steps; the frame total is synchronised and exact).
//   BM_TextEncode/<encoder>/<device>/<dtype>
//       one prompt through the CLIP tokenizer + text model (diffusers'
//       encode_prompt: padded to 77 tokens). The checkpoint presets carry no
//       text encoder (only prompt_embeds.safetensors), so this uses the
//       golden CLIP folder ($FD_GOLDEN_DIR/clip: the real SD1.5 tokenizer and
//       a 2-layer, 32-wide random text model, `golden_clip`) and the same
//       tokenizer with an SD1.5-shaped (ViT-L/14: 12 layers, 768 wide) text
//       model of random weights (`sd15_clip`).
//
//   --fd_preset=tiny|small|sd15   checkpoint preset (default tiny), made once
//                                 into $TMPDIR (sd15: ~4.3 GB, ~7 GB of RAM
//                                 while it is made), removed at exit
//   --fd_checkpoint=DIR           an existing environment folder instead
//   --fd_device=cpu|cuda|cuda:N   (default cpu)
//   --fd_dtype=LIST               fp32, fp16, bf16, comma separated (default fp32)
//   --fd_size=WxH                 frame size (default: the VAE's sample_size,
//                                 tiny 64, small 256, sd15 512)
//   --fd_steps=N                  UniPC steps per frame (default 10)
//   --fd_batch=LIST               frames per batch, e.g. 1,2,4,8 (default 1)
//   --fd_threads=N                LibTorch CPU threads, all benchmarks (default 1:
//                                 on 2 cores one thread beat two for every
//                                 model here, docs/BENCHMARKS.md)
//   --fd_previous_latent=encode|reuse  BM_PresetFrame: the VAE encodes the
//                                 previous frame (default, the authors') or a
//                                 given previous latent stands in for it (an
//                                 environment's "previous_latent": "reuse")
//   --fd_lora=merged|live         ControlLoRA merged into the UNet (default, as
//                                 config B) or live (the authors' inference)
//   --fd_cudnn_benchmark=0|1      cuDNN autotuning (default 0)
//   --fd_choose_threads=0|1       with --fd_threads > 1, whole frames run at the
//                                 count ChooseIntraOpThreads picks (default 1;
//                                 0: always --fd_threads)
//   --fd_controlnet_beside_unet=0|1  whole frames run the UNet's down path on a
//                                 companion thread beside the ControlNet
//                                 (FramePipelineOptions; default 0; with
//                                 --fd_choose_threads=1 and --fd_threads > 1
//                                 the choice decides)
//   --fd_batch_invariant=0|1      convolutions and linear layers sample by
//                                 sample (model/runtime/batch_invariance.h), all
//                                 benchmarks (default 0)
//   --fd_fused_attention=0|1      small float32 heads at inference take the fused
//                                 CPU attention kernel (model/runtime/
//                                 attention_kernel.h; default 1, as the server)
//   --fd_min_time=S, --fd_iterations=N   per configurable benchmark
//                                 (default: Google Benchmark's own rule)
//
// TFLOPS: one SD1.5 frame at 512x512 with 10 steps is 2 x (10 x (UNet 401.6
// + ControlNet 144) + VAE encode 558 + decode 1257) GMAC = 14.5 TFLOP
// (issue 10's count, ~14.6); the per-step part scales with the steps and
// everything with the pixel area relative to 512x512 (attention actually
// grows faster than the area, so this is nominal off 512x512). Reported only
// when the UNet, ControlNet and VAE have SD1.5's shapes.
//
// On CUDA every timed iteration ends with torch::cuda::synchronize(), and
// one 1-step batch runs untimed first (kernel selection, allocator, oneDNN
// primitives on the CPU). Inputs are CPU uint8 images, as from the wire:
// FramePipeline computes the conditioning on the CPU and moves the condition,
// the previous frame and the noise to the device. The process exits 1 when
// any benchmark reported an error (for scripts).
//
//   build/<dir>/bench/fd_model_bench --benchmark_repetitions=5
//       --benchmark_report_aggregates_only=true   (one command line)
//   build/<dir>/bench/fd_model_bench --benchmark_filter='^BM_PresetFrame/'
//       --fd_preset=sd15 --fd_device=cuda --fd_dtype=fp16,bf16
//       --fd_batch=1,2,4,8 --fd_steps=10   (one command line; scripts/build-gpu.sh)
#include <ATen/CPUGeneratorImpl.h>
#include <benchmark/benchmark.h>
#include <torch/cuda.h>
#include <torch/torch.h>
#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "base/status_macros.h"
#include "bench/golden_data.h"
#include "bench/preset_checkpoint.h"
#include "model/checkpoint/checkpoint_loading.h"
#include "model/checkpoint/safetensors.h"
#include "model/networks/controlnet.h"
#include "model/networks/embeddings.h"
#include "model/networks/model_configs.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"
#include "model/pipeline/thread_choice.h"
#include "model/presets/presets.h"
#include "model/runtime/attention_kernel.h"
#include "model/runtime/batch_invariance.h"
#include "model/runtime/cpu_runtime.h"
#include "model/runtime/group_norm_kernel.h"
#include "model/runtime/torch_call.h"
#include "model/text/clip_text_model.h"
#include "model/text/clip_tokenizer.h"

namespace fd::model {
namespace {

// --fd_* flags (see the header comment).
struct BenchFlags {
  std::string preset = "tiny";
  std::string checkpoint;
  std::string device = "cpu";
  std::vector<std::string> dtypes = {"fp32"};
  int64_t width = 0;  // 0: the VAE's sample_size
  int64_t height = 0;
  int steps = 10;
  std::vector<int64_t> batches = {1};
  int threads = 1;
  std::string lora = "merged";
  bool reuse_previous_latent = false;
  bool cudnn_benchmark = false;
  bool batch_invariant = false;
  bool choose_threads = true;
  bool controlnet_beside_unet = false;
  double min_time = 0;     // 0: Google Benchmark's default
  int64_t iterations = 0;  // 0: as many as min_time needs
};

BenchFlags& Flags() {
  static BenchFlags* flags = new BenchFlags;
  return *flags;
}

// Set by Fail(); main() returns 1 when any benchmark failed, so that a
// script notices (Google Benchmark itself exits 0 after SkipWithError).
std::atomic<bool> g_failed{false};

void Fail(benchmark::State& state, const std::string& message) {
  g_failed = true;
  state.SkipWithError(message.c_str());
}

void SetUpTorch() {
  at::set_num_threads(Flags().threads);
  // FD_BENCH_MKLDNN=0 runs convolutions on ATen's native kernels instead of
  // oneDNN, to compare the two backends at these small shapes.
  if (const char* mkldnn = std::getenv("FD_BENCH_MKLDNN"); mkldnn && std::string(mkldnn) == "0") {
    at::globalContext().setUserEnabledMkldnn(false);
  }
}

absl::StatusOr<torch::Dtype> ParseDtype(const std::string& name) {
  if (name == "fp32" || name == "float32") return torch::kFloat32;
  if (name == "fp16" || name == "float16") return torch::kFloat16;
  if (name == "bf16" || name == "bfloat16") return torch::kBFloat16;
  return absl::InvalidArgumentError(
      absl::StrCat("dtype '", name, "': expected fp32, fp16 or bf16"));
}

absl::StatusOr<torch::Device> ParseDevice(const std::string& name) {
  const bool cuda_index = name.rfind("cuda:", 0) == 0 && name.size() > 5 &&
                          name.find_first_not_of("0123456789", 5) == std::string::npos;
  if (name != "cpu" && name != "cuda" && !cuda_index) {
    return absl::InvalidArgumentError(
        absl::StrCat("device '", name, "': expected cpu, cuda or cuda:N"));
  }
  return torch::Device(name);
}

// Waits for the device's queued work, so that the timing covers it.
void Synchronize(const torch::Device& device) {
  if (device.is_cuda()) torch::cuda::synchronize(device.has_index() ? device.index() : -1);
}

using fd::bench::PresetCheckpointDir;  // bench/preset_checkpoint.h

// The FramePipeline options the flags ask for.
// With --fd_choose_threads (the default) and --fd_threads > 1, the
// whole-frame benchmarks run at the count ChooseIntraOpThreads picks for
// the environment at that frame size (as framediffuser-server does).
FramePipelineOptions PipelineOptions(const std::shared_ptr<const Environment>& env, int64_t width,
                                     int64_t height) {
  FramePipelineOptions options;
  options.batch_invariant = Flags().batch_invariant;
  options.controlnet_beside_unet =
      Flags().controlnet_beside_unet ? ControlNetBeside::kAlways : ControlNetBeside::kNever;
  if (Flags().choose_threads && Flags().threads > 1) {
    ThreadChoiceOptions choice_options;
    choice_options.width = width;
    choice_options.height = height;
    absl::StatusOr<ThreadChoice> choice =
        ChooseIntraOpThreads(env, Flags().threads, choice_options);
    if (choice.ok()) {
      options.intra_op_threads = choice->threads;
      // As the server: beside the UNet while a core is free.
      options.controlnet_beside_unet = choice->controlnet_beside_unet
                                           ? ControlNetBeside::kWhenCoreFree
                                           : ControlNetBeside::kNever;
      options.vae_on_free_core = choice->vae_on_free_core;
    }
    std::fprintf(stderr,
                 "fd_model_bench: %lldx%lld: intra-op threads %d, ControlNet beside the UNet %d "
                 "(step %.1f ms at 1, %.1f ms at %d, %.1f ms at 1 beside), VAE on a free core %d "
                 "(frame %.1f ms without, %.1f ms with)\n",
                 static_cast<long long>(width), static_cast<long long>(height),
                 choice.ok() ? choice->threads : Flags().threads,
                 choice.ok() && choice->controlnet_beside_unet ? 1 : 0,
                 choice.ok() ? choice->step_ms_one : 0.0, choice.ok() ? choice->step_ms_many : 0.0,
                 Flags().threads, choice.ok() ? choice->step_ms_beside : 0.0,
                 choice.ok() && choice->vae_on_free_core ? 1 : 0,
                 choice.ok() ? choice->frame_ms_vae_one : 0.0,
                 choice.ok() ? choice->frame_ms_vae_two : 0.0);
  }
  return options;
}

std::string ReadText(const std::string& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

struct ConfigB {
  std::shared_ptr<Environment> env;
  std::map<std::string, torch::Tensor> inputs;
};

// Loaded once; aborts with a message when the checkpoint is missing.
ConfigB& GetConfigB() {
  static ConfigB* config = [] {
    SetUpTorch();
    auto* c = new ConfigB;
    EnvironmentOptions options;
    options.allow_missing_text = true;  // the goldens carry embeddings, no text encoder
    options.lora_policy = LoraPolicy::kIfPresent;
    options.lora_mode = LoraMode::kMerged;  // merged LoRA costs nothing per step
    auto env = LoadEnvironment(fd::bench::BenchGoldenPath("B"), options);
    auto inputs = LoadSafetensors(fd::bench::BenchGoldenPath("B/golden/inputs.safetensors"));
    if (!env.ok() || !inputs.ok()) {
      std::fprintf(stderr, "cannot load config B: %s %s\n", env.status().ToString().c_str(),
                   inputs.status().ToString().c_str());
      std::exit(1);
    }
    c->env = *env;
    c->inputs = *inputs;
    return c;
  }();
  return *config;
}

// One denoising step's networks: ControlNet + UNet on the golden batch
// (config B: batch 2, latent 12x16, 77 tokens).
void BM_UNetControlNetStep(benchmark::State& state) {
  ConfigB& b = GetConfigB();
  torch::InferenceMode inference_mode;
  const torch::Tensor latent = b.inputs.at("noisy_latent");
  const torch::Tensor prev = b.inputs.at("noisy_latent").flip({0});
  const torch::Tensor ehs = b.inputs.at("encoder_hidden_states");
  const torch::Tensor cond = b.inputs.at("controlnet_cond");
  const torch::Tensor t = b.inputs.at("timestep");
  ControlNetModel controlnet = b.env->controlnet;
  UNet2DConditionModel unet = b.env->unet;
  BatchInvariantScope batch_invariant(Flags().batch_invariant);
  for (auto _ : state) {
    auto residuals = controlnet->Run(latent, t, ehs, cond);
    auto eps = unet->Run(torch::cat({latent, prev}, 1), t, ehs, *residuals);
    benchmark::DoNotOptimize(eps->data_ptr());
  }
  state.SetLabel("batch " + std::to_string(latent.size(0)) + ", latent " +
                 std::to_string(latent.size(2)) + "x" + std::to_string(latent.size(3)));
}
BENCHMARK(BM_UNetControlNetStep)->Unit(benchmark::kMillisecond)->MinTime(2.0);

// VAE encode / decode of state.range(0) items in one call (config B: golden
// prev_image item 0, 96x128; latent 12x16), to compare a batched call with
// per-item calls (FramePipeline's VaeBatching).
void BM_VaeEncode(benchmark::State& state) {
  ConfigB& b = GetConfigB();
  torch::InferenceMode inference_mode;
  const torch::Tensor image =
      (b.inputs.at("prev_image").slice(0, 0, 1) * 2 - 1).expand({state.range(0), -1, -1, -1});
  const torch::Tensor batch = image.contiguous();
  AutoencoderKL vae = b.env->vae;
  for (auto _ : state) {
    auto posterior = vae->Encode(batch);
    benchmark::DoNotOptimize(posterior->mean.data_ptr());
  }
  state.SetItemsProcessed(state.iterations() * state.range(0));
}
BENCHMARK(BM_VaeEncode)->Arg(1)->Arg(2)->Arg(4)->Unit(benchmark::kMillisecond)->MinTime(2.0);

void BM_VaeDecode(benchmark::State& state) {
  ConfigB& b = GetConfigB();
  torch::InferenceMode inference_mode;
  const torch::Tensor z = (b.inputs.at("vae_decode_latents_scaled").slice(0, 0, 1) / 0.18215)
                              .expand({state.range(0), -1, -1, -1})
                              .contiguous();
  AutoencoderKL vae = b.env->vae;
  for (auto _ : state) {
    auto image = vae->Decode(z);
    benchmark::DoNotOptimize(image->data_ptr());
  }
  state.SetItemsProcessed(state.iterations() * state.range(0));
}
BENCHMARK(BM_VaeDecode)->Arg(1)->Arg(2)->Arg(4)->Unit(benchmark::kMillisecond)->MinTime(2.0);

// The work FramePipeline hoists out of the step loop, timed alone (one item):
// what each hoist saves per step it no longer repeats (docs/BENCHMARKS.md,
// "Step-invariant work"). Arg 0: config B (golden weights: the diffusers
// condition encoder at 96x128, C0 16); arg 1: SD1.5 shapes (random weights:
// the authors' 9-conv encoder 10->16->32->96->256->320 at 512x512, time
// embedding 320 -> 1280).
void BM_ConditionEmbedding(benchmark::State& state) {
  torch::InferenceMode inference_mode;
  auto gen = at::make_generator<at::CPUGeneratorImpl>(0);
  torch::Tensor cond;
  std::function<torch::Tensor()> run;
  ControlNetConditioningEmbeddingEx sd15{nullptr};
  if (state.range(0) == 0) {
    ConfigB& b = GetConfigB();
    cond = b.inputs.at("controlnet_cond").slice(0, 0, 1);
    ControlNetModel controlnet = b.env->controlnet;
    run = [controlnet, &cond]() mutable { return controlnet->EmbedCondition(cond); };
    state.SetLabel("config B, 96x128");
  } else {
    SetUpTorch();
    sd15 = ControlNetConditioningEmbeddingEx(320, 10, std::vector<int64_t>{16, 32, 96, 256});
    for (auto& p : sd15->parameters()) p.normal_(0, 0.02, gen);
    cond = at::rand({1, 10, 512, 512}, gen) * 2 - 1;
    run = [&]() { return sd15(cond); };
    state.SetLabel("SD1.5 shapes (authors' encoder), 512x512");
  }
  for (auto _ : state) benchmark::DoNotOptimize(run().data_ptr());
}
BENCHMARK(BM_ConditionEmbedding)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

void BM_TimeEmbedding(benchmark::State& state) {
  torch::InferenceMode inference_mode;
  const torch::Tensor t = torch::tensor({999.0f});
  std::function<torch::Tensor()> run;
  Timesteps proj{nullptr};
  TimestepEmbedding embed{nullptr};
  if (state.range(0) == 0) {
    ConfigB& b = GetConfigB();
    ControlNetModel controlnet = b.env->controlnet;
    UNet2DConditionModel unet = b.env->unet;
    run = [controlnet, unet, &t]() mutable {
      controlnet->EmbedTime(t);
      return unet->EmbedTime(t);
    };
    state.SetLabel("config B, ControlNet + UNet");
  } else {
    SetUpTorch();
    proj = Timesteps(320, true, 0.0);
    embed = TimestepEmbedding(320, 1280);
    run = [&]() {
      embed(proj(t));
      return embed(proj(t));
    };
    state.SetLabel("SD1.5 shapes, ControlNet + UNet (320 -> 1280)");
  }
  for (auto _ : state) benchmark::DoNotOptimize(run().data_ptr());
}
BENCHMARK(BM_TimeEmbedding)->Arg(0)->Arg(1)->Unit(benchmark::kMicrosecond);

// What ChooseIntraOpThreads (model/pipeline/thread_choice.h) picks at
// --fd_threads for config B at 128x96 (arg 0), the small preset at 256x256
// (arg 1) and the tiny preset at 64x64 (arg 2), with the median batch-1 step
// times it measured at 1 and at --fd_threads threads (counters, ms).
void BM_ThreadChoice(benchmark::State& state) {
  std::shared_ptr<const Environment> env;
  ThreadChoiceOptions options;
  options.rounds = 5;
  if (state.range(0) == 0) {
    env = GetConfigB().env;
    options.width = 128;
    options.height = 96;
  } else {
    SetUpTorch();
    const std::string preset = state.range(0) == 1 ? "small" : "tiny";
    absl::StatusOr<std::string> dir = PresetCheckpointDir(preset);
    if (!dir.ok()) return Fail(state, dir.status().ToString());
    EnvironmentOptions load;
    load.lora_mode = LoraMode::kMerged;
    absl::StatusOr<std::shared_ptr<Environment>> loaded = LoadEnvironment(*dir, load);
    if (!loaded.ok()) return Fail(state, loaded.status().ToString());
    env = *loaded;
    options.width = options.height = state.range(0) == 1 ? 256 : 64;
  }
  ThreadChoice choice;
  for (auto _ : state) {
    absl::StatusOr<ThreadChoice> c = ChooseIntraOpThreads(env, Flags().threads, options);
    if (!c.ok()) return Fail(state, c.status().ToString());
    choice = *c;
  }
  state.counters["threads"] = choice.threads;
  state.counters["step_ms_1"] = choice.step_ms_one;
  state.counters["step_ms_max"] = choice.step_ms_many;
  state.counters["step_ms_beside"] = choice.step_ms_beside;
  state.counters["beside"] = choice.controlnet_beside_unet ? 1 : 0;
  state.SetLabel(state.range(0) == 0   ? "config B 128x96"
                 : state.range(0) == 1 ? "small 256x256"
                                       : "tiny 64x64");
}
BENCHMARK(BM_ThreadChoice)->Arg(0)->Arg(1)->Arg(2)->Iterations(1)->Unit(benchmark::kMillisecond);

// One channels-last GroupNorm at the street VAE's levels (arg 0: 0 [1, 32,
// 128, 128], 1 [1, 64, 64, 64], 2 [1, 128, 32, 32]; 16 groups), through
// LibTorch's kernel (arg 1 = 0), whose result depends on the thread count,
// or the project's invariant one (arg 1 = 1; model/runtime/group_norm_kernel.h).
void BM_GroupNorm(benchmark::State& state) {
  SetUpTorch();
  const int64_t channels = int64_t{32} << state.range(0);
  const int64_t side = int64_t{128} >> state.range(0);
  torch::manual_seed(1);
  torch::nn::GroupNorm norm(torch::nn::GroupNormOptions(16, channels).eps(1e-6));
  torch::InferenceMode inference_mode;
  const torch::Tensor x =
      torch::randn({1, channels, side, side}).contiguous(at::MemoryFormat::ChannelsLast);
  const bool invariant = state.range(1) == 1;
  for (auto _ : state) {
    torch::Tensor y = invariant ? GroupNormForward(*norm, x) : norm(x);
    benchmark::DoNotOptimize(y.data_ptr());
  }
  state.SetLabel(absl::StrCat(invariant ? "invariant" : "aten", " [1, ", channels, ", ", side, ", ",
                              side, "]"));
}
BENCHMARK(BM_GroupNorm)
    ->ArgsProduct({{0, 1, 2}, {0, 1}})
    ->Unit(benchmark::kMicrosecond)
    ->MinTime(0.5);

// Whole frames: encode + 10 UniPC steps + decode, state.range(0) sessions
// in one batch (ready golden condition, float previous frame, golden
// embeddings; noise from per-item seeds).
void BM_FullFrame(benchmark::State& state) {
  ConfigB& b = GetConfigB();
  FramePipeline pipeline(b.env, PipelineOptions(b.env, 128, 96));
  std::vector<PipelineInput> requests;
  for (int64_t i = 0; i < state.range(0); ++i) {
    const int64_t k = i % b.inputs.at("controlnet_cond").size(0);
    PipelineInput r;
    r.condition = b.inputs.at("controlnet_cond").slice(0, k, k + 1);
    r.previous_frame = b.inputs.at("prev_image")[k].permute({1, 2, 0});
    r.prompt_embeds = b.inputs.at("encoder_hidden_states").slice(0, k, k + 1);
    r.vae_noise_seed = 1000 + i;
    r.init_noise_seed = 2000 + i;
    r.steps = 10;
    r.scheduler = SchedulerType::kUniPCMultistep;  // the authors' sampler
    requests.push_back(r);
  }
  for (auto _ : state) {
    auto out = pipeline.Render(requests);
    if (!out.ok()) {
      Fail(state, out.status().ToString());
      break;
    }
    benchmark::DoNotOptimize((*out)[0].image_uint8.data_ptr());
  }
  state.SetItemsProcessed(state.iterations() * state.range(0));
}
BENCHMARK(BM_FullFrame)
    ->Arg(1)
    ->Arg(2)
    ->Arg(4)
    ->Arg(8)
    ->Unit(benchmark::kMillisecond)
    ->Iterations(3);

// The `small` preset (UNet 32/64/128/128 channels, 2 layers per block,
// cross_attention_dim 128; ControlNet and VAE to match; ControlLoRA rank 8),
// seed 0, float32, made once into a temporary folder (removed at exit) and
// loaded with the ControlLoRA merged, as for config B.
std::shared_ptr<Environment> GetSmallEnvironment() {
  static std::shared_ptr<Environment>* env = [] {
    SetUpTorch();
    absl::StatusOr<std::string> dir = PresetCheckpointDir("small");
    if (!dir.ok()) {
      std::fprintf(stderr, "%s\n", dir.status().ToString().c_str());
      std::exit(1);
    }
    EnvironmentOptions options;
    options.lora_mode = LoraMode::kMerged;
    absl::StatusOr<std::shared_ptr<Environment>> loaded = LoadEnvironment(*dir, options);
    if (!loaded.ok()) {
      std::fprintf(stderr, "cannot load the small checkpoint: %s\n",
                   loaded.status().ToString().c_str());
      std::exit(1);
    }
    return new std::shared_ptr<Environment>(*loaded);
  }();
  return *env;
}

// Random uint8 G-buffer, previous frame and previous basecolor (per-item
// seed), sky mode previous_output, the environment's prompt embeddings,
// UniPC (BM_FullFrameSmall, BM_PresetFrame).
std::vector<PipelineInput> RandomFrameRequests(int64_t batch, int64_t width, int64_t height,
                                               int steps) {
  std::vector<PipelineInput> requests;
  for (int64_t i = 0; i < batch; ++i) {
    PipelineInput r = RandomGBufferFrame(height, width, 100 + static_cast<uint64_t>(i));
    r.vae_noise_seed = 1000 + i;
    r.init_noise_seed = 2000 + i;
    r.steps = steps;
    r.scheduler = SchedulerType::kUniPCMultistep;
    requests.push_back(r);
  }
  return requests;
}

// Times whole batches of `requests` through `pipeline`: one untimed 1-step
// warm-up first (kernel selection, the CUDA caching allocator and oneDNN
// primitives are made per shape on first use, which a single timed iteration
// would include), a device sync ending each iteration. Sets items processed
// (frames) and the last iteration's stage counters (encode / decode summed
// over the items; denoise once, as the steps are batched). False (and the
// benchmark marked failed) on an error.
bool TimeFrames(benchmark::State& state, const FramePipeline& pipeline,
                const std::vector<PipelineInput>& requests, const torch::Device& device) {
  std::vector<PipelineInput> warm_up = requests;
  for (PipelineInput& r : warm_up) r.steps = 1;
  if (auto out = pipeline.Render(warm_up); !out.ok()) {
    Fail(state, out.status().ToString());
    return false;
  }
  Synchronize(device);
  PipelineTimings stages;
  for (auto _ : state) {
    auto out = pipeline.Render(requests);
    if (!out.ok()) {
      Fail(state, out.status().ToString());
      return false;
    }
    benchmark::DoNotOptimize((*out)[0].image_uint8.data_ptr());
    Synchronize(device);
    stages = PipelineTimings{};
    for (const FrameOutput& o : *out) {
      stages.encode_ms += o.timings.encode_ms;
      stages.decode_ms += o.timings.decode_ms;
    }
    stages.denoise_ms = (*out)[0].timings.denoise_ms;
  }
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(requests.size()));
  state.counters["encode_ms"] = stages.encode_ms;
  state.counters["denoise_ms"] = stages.denoise_ms;
  state.counters["decode_ms"] = stages.decode_ms;
  return true;
}

// Whole frames on the small preset through the G-buffer path: random uint8
// G-buffer, previous frame and previous basecolor (per-item seed), 256x256
// images (32x32 latents, the preset's sample_size), sky mode
// previous_output, the environment's prompt embeddings (77 tokens), 10
// UniPC steps; state.range(0) sessions in one batch. Includes conditioning
// (irradiance), VAE encode of the previous frame, noise, the steps, decode.
void BM_FullFrameSmall(benchmark::State& state) {
  constexpr int64_t kSize = 256;
  FramePipeline pipeline(GetSmallEnvironment(),
                         PipelineOptions(GetSmallEnvironment(), kSize, kSize));
  if (!TimeFrames(state, pipeline, RandomFrameRequests(state.range(0), kSize, kSize, 10),
                  torch::kCPU)) {
    return;
  }
  state.SetLabel("small preset, 256x256, 10 UniPC steps");
}
// One iteration each (a batch-8 frame takes minutes on 2 loaded cores);
// frames/s from the wall time.
BENCHMARK(BM_FullFrameSmall)
    ->Arg(1)
    ->Arg(2)
    ->Arg(4)
    ->Arg(8)
    ->Unit(benchmark::kMillisecond)
    ->Iterations(1)
    ->UseRealTime();

// VAE encode / decode on the small preset (256x256 <-> 32x32), state.range(0)
// items in one call (random inputs, seed 0).
void BM_VaeSmall(benchmark::State& state, bool encode) {
  std::shared_ptr<Environment> env = GetSmallEnvironment();
  torch::InferenceMode inference_mode;
  AutoencoderKL vae = env->vae;
  auto gen = at::make_generator<at::CPUGeneratorImpl>(0);
  const int64_t n = state.range(0);
  const torch::Tensor image = at::rand({n, 3, 256, 256}, gen) * 2 - 1;
  const torch::Tensor z = at::randn({n, vae->config().latent_channels, 32, 32}, gen);
  for (auto _ : state) {
    if (encode) {
      auto posterior = vae->Encode(image);
      benchmark::DoNotOptimize(posterior->mean.data_ptr());
    } else {
      auto decoded = vae->Decode(z);
      benchmark::DoNotOptimize(decoded->data_ptr());
    }
  }
  state.SetItemsProcessed(state.iterations() * n);
}
BENCHMARK_CAPTURE(BM_VaeSmall, encode, true)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_VaeSmall, decode, false)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

// ---------------------------------------------------------------------------
// Configurable whole-frame benchmark (BM_PresetFrame).

// The folder the configurable benchmarks load: --fd_checkpoint or the made
// preset.
absl::StatusOr<std::string> FrameCheckpointDir() {
  if (!Flags().checkpoint.empty()) return Flags().checkpoint;
  return PresetCheckpointDir(Flags().preset);
}

// One environment at a time (the previous one is dropped before the next
// dtype loads: sd15 in float32 is ~4 GB).
absl::StatusOr<std::shared_ptr<Environment>> FrameEnvironment(torch::Dtype dtype) {
  static auto* cached = new std::pair<torch::Dtype, std::shared_ptr<Environment>>;
  if (cached->second != nullptr && cached->first == dtype) return cached->second;
  cached->second.reset();
  SetUpTorch();
  FD_ASSIGN_OR_RETURN(std::string dir, FrameCheckpointDir());
  FD_ASSIGN_OR_RETURN(torch::Device device, ParseDevice(Flags().device));
  EnvironmentOptions options;
  options.device = device;
  options.dtype = dtype;
  options.lora_mode = Flags().lora == "live" ? LoraMode::kLive : LoraMode::kMerged;
  options.lora_policy = LoraPolicy::kIfPresent;
  FD_ASSIGN_OR_RETURN(std::shared_ptr<Environment> env, LoadEnvironment(dir, options));
  *cached = {dtype, env};
  return env;
}

// SD1.5's UNet, ControlNet and VAE shapes (the sd15 preset, or a real
// FrameDiffuser checkpoint): the FLOP count below applies.
bool HasSd15Shapes(const Environment& env) {
  const std::vector<int64_t> unet_channels = {320, 640, 1280, 1280};
  const std::vector<int64_t> vae_channels = {128, 256, 512, 512};
  const auto& unet = env.unet->config();
  const auto& controlnet = env.controlnet->config();
  auto all_two = [](const std::vector<int64_t>& v) {
    for (int64_t x : v) {
      if (x != 2) return false;
    }
    return !v.empty();
  };
  return unet.block_out_channels == unet_channels && !unet.cross_attention_dim.empty() &&
         unet.cross_attention_dim[0] == 768 && all_two(unet.layers_per_block) &&
         controlnet.block_out_channels == unet_channels && all_two(controlnet.layers_per_block) &&
         env.vae->config().block_out_channels == vae_channels &&
         env.vae->config().layers_per_block == 2;
}

// Nominal SD1.5 FLOPs of one frame (header comment): 2 FLOP per MAC.
double Sd15FrameFlops(int steps, int64_t width, int64_t height) {
  constexpr double kUNetGmac = 401.6, kControlNetGmac = 144.0;
  constexpr double kVaeEncodeGmac = 558.0, kVaeDecodeGmac = 1257.0;
  const double area = static_cast<double>(width * height) / (512.0 * 512.0);
  return 2e9 * area * (steps * (kUNetGmac + kControlNetGmac) + kVaeEncodeGmac + kVaeDecodeGmac);
}

struct FrameCase {
  std::string dtype_name;
  torch::Dtype dtype;
  int64_t width;
  int64_t height;
  int steps;
  int64_t batch;
};

void BM_PresetFrame(benchmark::State& state, const FrameCase& c) {
  absl::StatusOr<std::shared_ptr<Environment>> env = FrameEnvironment(c.dtype);
  if (!env.ok()) {
    Fail(state, env.status().ToString());
    return;
  }
  if (Flags().cudnn_benchmark) at::globalContext().setBenchmarkCuDNN(true);
  const torch::Device device = (*env)->device;
  FramePipeline pipeline(*env, PipelineOptions(*env, c.width, c.height));
  std::vector<PipelineInput> requests = RandomFrameRequests(c.batch, c.width, c.height, c.steps);
  if (Flags().reuse_previous_latent) {
    // The previous frame still gives the irradiance; its latent (random
    // here: the arithmetic's cost does not depend on the values) replaces
    // the encode.
    const int64_t factor = (*env)->vae->downsampling_factor();
    auto gen = at::make_generator<at::CPUGeneratorImpl>(3);
    for (PipelineInput& r : requests) {
      r.prev_latent = at::randn(
          {1, (*env)->vae->config().latent_channels, c.height / factor, c.width / factor}, gen);
    }
  }
  if (!TimeFrames(state, pipeline, requests, device)) return;
  state.counters["frames_per_second"] = benchmark::Counter(
      static_cast<double>(c.batch), benchmark::Counter::kIsIterationInvariantRate);
  std::string label = absl::StrCat(
      Flags().checkpoint.empty() ? Flags().preset : "checkpoint", " ", device.str(), " ",
      c.dtype_name, " ", c.width, "x", c.height, ", ", c.steps, " UniPC steps, batch ", c.batch,
      ", LoRA ", Flags().lora, Flags().reuse_previous_latent ? ", previous latent reused" : "");
  if (HasSd15Shapes(**env)) {
    const double flops = Sd15FrameFlops(c.steps, c.width, c.height);
    // TFLOP per iteration; the rate counter divides by the (real) time.
    state.counters["TFLOPS"] = benchmark::Counter(flops * static_cast<double>(c.batch) / 1e12,
                                                  benchmark::Counter::kIsIterationInvariantRate);
    absl::StrAppend(&label, ", ", flops / 1e12, " TFLOP/frame (nominal)");
  }
  state.SetLabel(label);
}

// The frame size when --fd_size is not given: the VAE's sample_size (the
// preset's native size), from the preset's or the folder's vae config.
absl::StatusOr<int64_t> DefaultFrameSize() {
  std::string vae_json;
  if (Flags().checkpoint.empty()) {
    FD_ASSIGN_OR_RETURN(fd::model::PresetConfigs configs,
                        fd::model::GetPresetConfigs(Flags().preset));
    vae_json = configs.vae;
  } else {
    vae_json = ReadText(Flags().checkpoint + "/vae/config.json");
  }
  FD_ASSIGN_OR_RETURN(AutoencoderKLConfig vae, ParseAutoencoderKLConfig(vae_json, "vae config"));
  return vae.sample_size;
}

// ---------------------------------------------------------------------------
// Text encoder (BM_TextEncode).

constexpr char kPrompt[] =
    "a photorealistic city street at dusk, wet asphalt reflecting neon signs, parked cars, "
    "detailed brick facades, volumetric light, high quality";

// transformers' CLIPTextConfig of SD1.5's text encoder (openai
// clip-vit-large-patch14's text tower).
CLIPTextConfig Sd15ClipConfig() {
  CLIPTextConfig config;
  config.vocab_size = 49408;
  config.hidden_size = 768;
  config.intermediate_size = 3072;
  config.projection_dim = 768;
  config.num_hidden_layers = 12;
  config.num_attention_heads = 12;
  config.max_position_embeddings = 77;
  config.hidden_act = "quick_gelu";
  return config;
}

struct TextEncoder {
  ClipTokenizer tokenizer;
  ClipTextModel model{nullptr};
};

// `golden_clip` (the golden folder's weights) or `sd15_clip` (random
// N(0, 0.02^2) weights, layer norms 1 + N(0, 0.02^2); seed 0); both with the
// golden folder's SD1.5 tokenizer.
absl::StatusOr<TextEncoder> LoadTextEncoder(const std::string& which, torch::Device device,
                                            torch::Dtype dtype) {
  SetUpTorch();
  absl::StatusOr<ClipTokenizer> tokenizer =
      ClipTokenizer::FromDirectory(fd::bench::BenchGoldenPath("clip/tokenizer"));
  if (!tokenizer.ok()) {
    return absl::Status(tokenizer.status().code(),
                        absl::StrCat("the SD1.5 tokenizer of the golden CLIP folder is needed "
                                     "(the checkpoint presets carry no tokenizer): ",
                                     tokenizer.status().message()));
  }
  TextEncoder encoder{*tokenizer};
  if (which == "golden_clip") {
    FD_ASSIGN_OR_RETURN(
        encoder.model,
        LoadClipTextModel(fd::bench::BenchGoldenPath("clip/text_encoder"), device, dtype));
    return encoder;
  }
  FD_ASSIGN_OR_RETURN(encoder.model, MakeClipTextModel(Sd15ClipConfig()));
  FD_RETURN_IF_ERROR(TorchCall("random CLIP weights", [&]() -> absl::Status {
    torch::NoGradGuard no_grad;
    at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(0);
    for (auto& p : encoder.model->named_parameters()) {
      torch::Tensor t = p.value();
      t.normal_(0, 0.02, gen);
      if (absl::StrContains(p.key(), "layer_norm") && absl::EndsWith(p.key(), ".weight")) {
        t.add_(1.0);
      }
    }
    return absl::OkStatus();
  }));
  FD_RETURN_IF_ERROR(MoveModule(*encoder.model, device, dtype));
  return encoder;
}

void BM_TextEncode(benchmark::State& state, const std::string& which, const std::string& dtype_name,
                   torch::Dtype dtype) {
  absl::StatusOr<torch::Device> device = ParseDevice(Flags().device);
  if (!device.ok()) {
    Fail(state, device.status().ToString());
    return;
  }
  absl::StatusOr<TextEncoder> encoder = LoadTextEncoder(which, *device, dtype);
  if (!encoder.ok()) {
    Fail(state, encoder.status().ToString());
    return;
  }
  torch::InferenceMode inference_mode;
  const std::vector<std::string> prompts = {kPrompt};
  if (auto warm = EncodePrompts(encoder->tokenizer, encoder->model, prompts); !warm.ok()) {
    Fail(state, warm.status().ToString());
    return;
  }
  Synchronize(*device);
  for (auto _ : state) {
    auto embeds = EncodePrompts(encoder->tokenizer, encoder->model, prompts);
    if (!embeds.ok()) {
      Fail(state, embeds.status().ToString());
      return;
    }
    benchmark::DoNotOptimize(embeds->data_ptr());
    Synchronize(*device);
  }
  state.SetItemsProcessed(state.iterations());
  const CLIPTextConfig& config = encoder->model->config();
  state.SetLabel(absl::StrCat(which, " ", device->str(), " ", dtype_name, ": ",
                              config.num_hidden_layers, " layers x ", config.hidden_size,
                              ", 77 tokens, tokenizer included"));
}

// ---------------------------------------------------------------------------
// Flags and registration.

constexpr char kUsage[] =
    "fd_model_bench flags (besides --benchmark_*), see bench/model_bench.cc:\n"
    "  --fd_preset=tiny|small|sd15  --fd_checkpoint=DIR  --fd_device=cpu|cuda|cuda:N\n"
    "  --fd_dtype=fp32,fp16,bf16  --fd_size=WxH  --fd_steps=N  --fd_batch=1,2,4,8\n"
    "  --fd_threads=N  --fd_lora=merged|live  --fd_cudnn_benchmark=0|1\n"
    "  --fd_previous_latent=encode|reuse\n"
    "  --fd_batch_invariant=0|1  --fd_choose_threads=0|1  --fd_fused_attention=0|1\n"
    "  --fd_controlnet_beside_unet=0|1\n"
    "  --fd_min_time=SECONDS  --fd_iterations=N  --fd_help\n";

absl::StatusOr<std::vector<int64_t>> ParseIntList(const std::string& flag, const std::string& value,
                                                  int64_t min) {
  std::vector<int64_t> out;
  for (absl::string_view part : absl::StrSplit(value, ',')) {
    int64_t x = 0;
    if (!absl::SimpleAtoi(part, &x) || x < min) {
      return absl::InvalidArgumentError(
          absl::StrCat(flag, "=", value, ": expected integers >= ", min, ", comma separated"));
    }
    out.push_back(x);
  }
  return out;
}

absl::Status ParseFlag(const std::string& name, const std::string& value) {
  BenchFlags& f = Flags();
  auto one_int = [&](int64_t min) -> absl::StatusOr<int64_t> {
    FD_ASSIGN_OR_RETURN(std::vector<int64_t> v, ParseIntList(name, value, min));
    if (v.size() != 1) return absl::InvalidArgumentError(absl::StrCat(name, ": one integer"));
    return v[0];
  };
  if (name == "--fd_preset") {
    FD_RETURN_IF_ERROR(fd::model::GetPresetConfigs(value).status());
    f.preset = value;
  } else if (name == "--fd_checkpoint") {
    f.checkpoint = value;
  } else if (name == "--fd_device") {
    FD_RETURN_IF_ERROR(ParseDevice(value).status());
    f.device = value;
  } else if (name == "--fd_dtype") {
    std::vector<std::string> dtypes = absl::StrSplit(value, ',');
    f.dtypes = std::move(dtypes);
    for (const std::string& d : f.dtypes) FD_RETURN_IF_ERROR(ParseDtype(d).status());
  } else if (name == "--fd_size") {
    const std::vector<std::string> wh = absl::StrSplit(value, 'x');
    if (wh.size() != 2 || !absl::SimpleAtoi(wh[0], &f.width) ||
        !absl::SimpleAtoi(wh[1], &f.height) || f.width <= 0 || f.height <= 0 || f.width % 8 != 0 ||
        f.height % 8 != 0) {
      return absl::InvalidArgumentError(
          absl::StrCat(name, "=", value, ": expected WxH, multiples of 8, e.g. 512x512"));
    }
  } else if (name == "--fd_steps") {
    FD_ASSIGN_OR_RETURN(int64_t steps, one_int(1));
    f.steps = static_cast<int>(steps);
  } else if (name == "--fd_batch") {
    FD_ASSIGN_OR_RETURN(f.batches, ParseIntList(name, value, 1));
  } else if (name == "--fd_threads") {
    FD_ASSIGN_OR_RETURN(int64_t threads, one_int(1));
    f.threads = static_cast<int>(threads);
  } else if (name == "--fd_lora") {
    if (value != "merged" && value != "live") {
      return absl::InvalidArgumentError(absl::StrCat(name, "=", value, ": merged or live"));
    }
    f.lora = value;
  } else if (name == "--fd_previous_latent") {
    if (value != "encode" && value != "reuse") {
      return absl::InvalidArgumentError(absl::StrCat(name, "=", value, ": encode or reuse"));
    }
    f.reuse_previous_latent = value == "reuse";
  } else if (name == "--fd_cudnn_benchmark") {
    FD_ASSIGN_OR_RETURN(int64_t on, one_int(0));
    f.cudnn_benchmark = on != 0;
  } else if (name == "--fd_choose_threads") {
    FD_ASSIGN_OR_RETURN(int64_t on, one_int(0));
    f.choose_threads = on != 0;
  } else if (name == "--fd_controlnet_beside_unet") {
    FD_ASSIGN_OR_RETURN(int64_t on, one_int(0));
    f.controlnet_beside_unet = on != 0;
  } else if (name == "--fd_batch_invariant") {
    FD_ASSIGN_OR_RETURN(int64_t on, one_int(0));
    f.batch_invariant = on != 0;
  } else if (name == "--fd_fused_attention") {
    FD_ASSIGN_OR_RETURN(int64_t on, one_int(0));
    SetFusedAttentionEnabled(on != 0);
  } else if (name == "--fd_min_time") {
    if (!absl::SimpleAtod(value, &f.min_time) || !(f.min_time > 0)) {
      return absl::InvalidArgumentError(absl::StrCat(name, "=", value, ": seconds > 0"));
    }
  } else if (name == "--fd_iterations") {
    FD_ASSIGN_OR_RETURN(f.iterations, one_int(1));
  } else {
    return absl::InvalidArgumentError(absl::StrCat("unknown flag ", name));
  }
  return absl::OkStatus();
}

// Parses and removes the --fd_* arguments. Returns -1 to go on, else the
// exit code (0 after --fd_help, 2 after printing the problem).
int ParseBenchFlags(int* argc, char** argv) {
  int kept = 1;
  for (int i = 1; i < *argc; ++i) {
    const std::string arg = argv[i];
    if (arg.rfind("--fd_", 0) != 0) {
      argv[kept++] = argv[i];
      continue;
    }
    if (arg == "--fd_help") {
      std::fputs(kUsage, stdout);
      return 0;
    }
    const size_t eq = arg.find('=');
    const absl::Status status = eq == std::string::npos
                                    ? absl::InvalidArgumentError(arg + ": expected --fd_name=value")
                                    : ParseFlag(arg.substr(0, eq), arg.substr(eq + 1));
    if (!status.ok()) {
      std::fprintf(stderr, "fd_model_bench: %s\n%s", std::string(status.message()).c_str(), kUsage);
      return 2;
    }
  }
  *argc = kept;
  argv[kept] = nullptr;
  return -1;
}

template <typename B>
void ApplyTiming(B* b) {
  b->Unit(benchmark::kMillisecond)->UseRealTime();
  if (Flags().min_time > 0) b->MinTime(Flags().min_time);
  if (Flags().iterations > 0) b->Iterations(Flags().iterations);
}

absl::Status RegisterConfigurable() {
  const BenchFlags& f = Flags();
  int64_t width = f.width, height = f.height;
  if (width == 0) {
    FD_ASSIGN_OR_RETURN(width, DefaultFrameSize());
    height = width;
  }
  const std::string source = f.checkpoint.empty() ? f.preset : "checkpoint";
  for (const std::string& dtype_name : f.dtypes) {
    FD_ASSIGN_OR_RETURN(torch::Dtype dtype, ParseDtype(dtype_name));
    for (int64_t batch : f.batches) {
      const FrameCase c{dtype_name, dtype, width, height, f.steps, batch};
      const std::string name =
          absl::StrCat("BM_PresetFrame/", source, "/", f.device, "/", dtype_name, "/", width, "x",
                       height, "/steps:", f.steps, "/batch:", batch);
      ApplyTiming(benchmark::RegisterBenchmark(
          name.c_str(), [c](benchmark::State& state) { BM_PresetFrame(state, c); }));
    }
  }
  for (const std::string which : {"golden_clip", "sd15_clip"}) {
    for (const std::string& dtype_name : f.dtypes) {
      FD_ASSIGN_OR_RETURN(torch::Dtype dtype, ParseDtype(dtype_name));
      const std::string name =
          absl::StrCat("BM_TextEncode/", which, "/", f.device, "/", dtype_name);
      ApplyTiming(benchmark::RegisterBenchmark(name.c_str(),
                                               [which, dtype_name, dtype](benchmark::State& state) {
                                                 BM_TextEncode(state, which, dtype_name, dtype);
                                               }));
    }
  }
  return absl::OkStatus();
}

}  // namespace
}  // namespace fd::model

int main(int argc, char** argv) {
  // As framediffuser-server: OpenMP threads sleep when idle (may re-execute).
  fd::model::UseBoundedOpenMpSpin(argv);
  if (const int code = fd::model::ParseBenchFlags(&argc, argv); code >= 0) return code;
  if (absl::Status s = fd::model::RegisterConfigurable(); !s.ok()) {
    std::fprintf(stderr, "fd_model_bench: %s\n", s.ToString().c_str());
    return 2;
  }
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 2;
  // As the server does (model/runtime/cpu_runtime.h); recorded in the JSON context.
  benchmark::AddCustomContext("malloc", fd::model::TuneMallocForInference());
  benchmark::AddCustomContext("blas", fd::model::UseSingleThreadedBlas());
  benchmark::AddCustomContext("fused_attention", fd::model::DescribeFusedAttention());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return fd::model::g_failed ? 1 : 0;
}
