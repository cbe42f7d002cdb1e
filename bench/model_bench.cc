// CPU benchmarks of the model/ hot paths on the golden config-B checkpoint
// (../shared/golden/B, or $FD_GOLDEN_DIR/B): one ControlNet + UNet step,
// VAE encode / decode, and whole frames through FramePipeline at several
// batch sizes. LibTorch runs with 2 threads (at::set_num_threads(2)).
//
//   build/<dir>/bench/fd_model_bench --benchmark_repetitions=5
//       --benchmark_report_aggregates_only=true   (one command line)
#include <benchmark/benchmark.h>
#include <torch/torch.h>

#include <cstdio>
#include <cstdlib>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "model/environment.h"
#include "model/frame_pipeline.h"
#include "model/safetensors.h"
#include "tests/testing/golden.h"

namespace fd::model {
namespace {

struct ConfigB {
  std::shared_ptr<Environment> env;
  std::map<std::string, torch::Tensor> inputs;
};

// Loaded once; aborts with a message when the checkpoint is missing.
ConfigB& GetConfigB() {
  static ConfigB* config = [] {
    at::set_num_threads(2);
    // FD_BENCH_MKLDNN=0 runs convolutions on ATen's native kernels instead of
    // oneDNN, to compare the two backends at these small shapes.
    if (const char* mkldnn = std::getenv("FD_BENCH_MKLDNN"); mkldnn && std::string(mkldnn) == "0") {
      at::globalContext().setUserEnabledMkldnn(false);
    }
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

}  // namespace
}  // namespace fd::model

BENCHMARK_MAIN();
