// CPU benchmarks of the model/ hot paths on the golden config-B checkpoint
// (../shared/golden/B, or $FD_GOLDEN_DIR/B): one ControlNet + UNet step,
// VAE encode / decode, and whole frames through FramePipeline at several
// batch sizes; plus whole frames on the `small` preset of
// tools/make_checkpoint (random weights, written to a temporary folder on
// first use). LibTorch runs with 2 threads (at::set_num_threads(2)).
//
//   build/<dir>/bench/fd_model_bench --benchmark_repetitions=5
//       --benchmark_report_aggregates_only=true   (one command line)
#include <ATen/CPUGeneratorImpl.h>
#include <benchmark/benchmark.h>
#include <torch/torch.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "model/environment.h"
#include "model/frame_pipeline.h"
#include "model/safetensors.h"
#include "tests/testing/golden.h"
#include "tools/make_checkpoint/checkpoint_maker.h"

namespace fd::model {
namespace {

struct ConfigB {
  std::shared_ptr<Environment> env;
  std::map<std::string, torch::Tensor> inputs;
};

void SetUpTorch() {
  at::set_num_threads(2);
  // FD_BENCH_MKLDNN=0 runs convolutions on ATen's native kernels instead of
  // oneDNN, to compare the two backends at these small shapes.
  if (const char* mkldnn = std::getenv("FD_BENCH_MKLDNN"); mkldnn && std::string(mkldnn) == "0") {
    at::globalContext().setUserEnabledMkldnn(false);
  }
}

// Loaded once; aborts with a message when the checkpoint is missing.
ConfigB& GetConfigB() {
  static ConfigB* config = [] {
    SetUpTorch();
    auto* c = new ConfigB;
    EnvironmentOptions options;
    options.allow_missing_text = true;  // the goldens carry embeddings, no text encoder
    options.lora_policy = LoraPolicy::kIfPresent;
    options.lora_mode = LoraMode::kMerged;  // merged LoRA costs nothing per step
    auto env = LoadEnvironment(fd::testing::GoldenPath("B"), options);
    auto inputs = LoadSafetensors(fd::testing::GoldenPath("B/golden/inputs.safetensors"));
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
  for (auto _ : state) {
    auto residuals = controlnet->Run(latent, t, ehs, cond);
    auto eps = unet->Run(torch::cat({latent, prev}, 1), t, ehs, *residuals);
    benchmark::DoNotOptimize(eps->data_ptr());
  }
  state.SetLabel("batch " + std::to_string(latent.size(0)) + ", latent " +
                 std::to_string(latent.size(2)) + "x" + std::to_string(latent.size(3)));
}
BENCHMARK(BM_UNetControlNetStep)->Unit(benchmark::kMillisecond)->MinTime(2.0);

// VAE encode of one previous frame (golden prev_image item 0, 96x128).
void BM_VaeEncode(benchmark::State& state) {
  ConfigB& b = GetConfigB();
  torch::InferenceMode inference_mode;
  const torch::Tensor image = b.inputs.at("prev_image").slice(0, 0, 1) * 2 - 1;
  AutoencoderKL vae = b.env->vae;
  for (auto _ : state) {
    auto posterior = vae->Encode(image);
    benchmark::DoNotOptimize(posterior->mean.data_ptr());
  }
}
BENCHMARK(BM_VaeEncode)->Unit(benchmark::kMillisecond)->MinTime(2.0);

// VAE decode of one latent (12x16 -> 96x128).
void BM_VaeDecode(benchmark::State& state) {
  ConfigB& b = GetConfigB();
  torch::InferenceMode inference_mode;
  const torch::Tensor z = b.inputs.at("vae_decode_latents_scaled").slice(0, 0, 1) / 0.18215;
  AutoencoderKL vae = b.env->vae;
  for (auto _ : state) {
    auto image = vae->Decode(z);
    benchmark::DoNotOptimize(image->data_ptr());
  }
}
BENCHMARK(BM_VaeDecode)->Unit(benchmark::kMillisecond)->MinTime(2.0);

// Whole frames: encode + 10 UniPC steps + decode, state.range(0) sessions
// in one batch (ready golden condition, float previous frame, golden
// embeddings; noise from per-item seeds).
void BM_FullFrame(benchmark::State& state) {
  ConfigB& b = GetConfigB();
  FramePipeline pipeline(b.env);
  std::vector<FrameRequest> requests;
  for (int64_t i = 0; i < state.range(0); ++i) {
    const int64_t k = i % b.inputs.at("controlnet_cond").size(0);
    FrameRequest r;
    r.condition = b.inputs.at("controlnet_cond").slice(0, k, k + 1);
    r.previous_frame = b.inputs.at("prev_image")[k].permute({1, 2, 0});
    r.prompt_embeds = b.inputs.at("encoder_hidden_states").slice(0, k, k + 1);
    r.vae_noise_seed = 1000 + i;
    r.init_noise_seed = 2000 + i;
    r.steps = 10;
    requests.push_back(r);
  }
  for (auto _ : state) {
    auto out = pipeline.Render(requests);
    if (!out.ok()) {
      state.SkipWithError(out.status().ToString().c_str());
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
    static const std::string dir = (std::filesystem::temp_directory_path() /
                                    ("fd_model_bench_small_" + std::to_string(getpid())))
                                       .string();
    fd::tools::MakeCheckpointOptions make;
    make.preset = "small";
    make.out_dir = dir;
    std::atexit([] {
      std::error_code ignored;
      std::filesystem::remove_all(dir, ignored);
    });
    const absl::Status made = fd::tools::MakeCheckpoint(make);
    if (!made.ok()) {
      std::fprintf(stderr, "cannot make the small checkpoint: %s\n", made.ToString().c_str());
      std::exit(1);
    }
    EnvironmentOptions options;
    options.lora_mode = LoraMode::kMerged;
    absl::StatusOr<std::shared_ptr<Environment>> loaded = LoadEnvironment(dir, options);
    if (!loaded.ok()) {
      std::fprintf(stderr, "cannot load the small checkpoint: %s\n",
                   loaded.status().ToString().c_str());
      std::exit(1);
    }
    return new std::shared_ptr<Environment>(*loaded);
  }();
  return *env;
}

// Whole frames on the small preset through the G-buffer path: random uint8
// G-buffer, previous frame and previous basecolor (per-item seed), 256x256
// images (32x32 latents, the preset's sample_size), sky mode
// previous_output, the environment's prompt embeddings (77 tokens), 10
// UniPC steps; state.range(0) sessions in one batch. Includes conditioning
// (irradiance), VAE encode of the previous frame, noise, the steps, decode.
void BM_FullFrameSmall(benchmark::State& state) {
  constexpr int64_t kSize = 256;
  FramePipeline pipeline(GetSmallEnvironment());
  std::vector<FrameRequest> requests;
  for (int64_t i = 0; i < state.range(0); ++i) {
    auto gen = at::make_generator<at::CPUGeneratorImpl>(100 + i);
    auto image = [&](int64_t channels) {
      return at::randint(0, 256, {kSize, kSize, channels}, gen, torch::kUInt8);
    };
    FrameRequest r;
    r.previous_frame = image(3);
    r.previous_basecolor = image(3);
    r.basecolor = image(3);
    r.normals = image(3);
    r.depth = image(1);
    r.roughness = image(1);
    r.metallic = image(1);
    r.sky_mode = SkyFillMode::kPreviousOutput;
    r.vae_noise_seed = 1000 + i;
    r.init_noise_seed = 2000 + i;
    r.steps = 10;
    r.scheduler = SchedulerType::kUniPCMultistep;
    requests.push_back(r);
  }
  // Warm-up outside the timing (one step): oneDNN creates its kernels per
  // shape on first use, which a single timed iteration would include.
  std::vector<FrameRequest> warm_up = requests;
  for (FrameRequest& r : warm_up) r.steps = 1;
  if (auto out = pipeline.Render(warm_up); !out.ok()) {
    state.SkipWithError(out.status().ToString().c_str());
    return;
  }
  StageTimings stages;  // summed over the batch's items, last iteration
  for (auto _ : state) {
    auto out = pipeline.Render(requests);
    if (!out.ok()) {
      state.SkipWithError(out.status().ToString().c_str());
      break;
    }
    benchmark::DoNotOptimize((*out)[0].image_uint8.data_ptr());
    stages = StageTimings{};
    for (const FrameOutput& o : *out) {
      stages.encode_ms += o.timings.encode_ms;
      stages.decode_ms += o.timings.decode_ms;
    }
    // The steps are batched: every item reports the same denoise time.
    stages.denoise_ms = (*out)[0].timings.denoise_ms;
  }
  state.SetItemsProcessed(state.iterations() * state.range(0));
  state.counters["encode_ms"] = stages.encode_ms;
  state.counters["denoise_ms"] = stages.denoise_ms;
  state.counters["decode_ms"] = stages.decode_ms;
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

}  // namespace
}  // namespace fd::model

BENCHMARK_MAIN();
