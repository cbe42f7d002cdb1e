// FramePipeline options that the end-to-end goldens do not cover, on the tiny
// golden checkpoint (fd_pipeline/model): classifier-free guidance
// (guidance_scale > 1 with negative prompt embeddings) and the DDIM / Euler
// samplers. The references are hand-written loops over the same networks and
// Scheduler::Step (the schedulers' own goldens are in scheduler_test.cc).
// Items use a ready condition and previous latent (the preprocessing is
// covered by frame_pipeline_test.cc), 64x64 frames (8x8 latents).
#include <ATen/CPUGeneratorImpl.h>
#include <ATen/Parallel.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "model/checkpoint/safetensors.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

constexpr int64_t kSize = 64;
constexpr int kSteps = 4;

double MaxAbsDiff(const torch::Tensor& a, const torch::Tensor& b) {
  return (a.to(torch::kFloat64) - b.to(torch::kFloat64)).abs().max().item<double>();
}

// A copy of the golden checkpoint folder made of symlinks, so that files can
// be added next to it.
std::string LinkedCopy(const std::string& name) {
  const fs::path dir =
      fs::temp_directory_path() / ("fd_pipeline_options_" + name + "_" + std::to_string(getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  const fs::path model = fs::absolute(fd::testing::GoldenPath("fd_pipeline/model"));
  for (const auto& entry : fs::directory_iterator(model)) {
    fs::create_symlink(entry.path(), dir / entry.path().filename());
  }
  return dir.string();
}

class FramePipelineOptionsTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    auto plain = LoadEnvironment(fd::testing::GoldenPath("fd_pipeline/model"));
    ASSERT_TRUE(plain.ok()) << plain.status();
    plain_env_ = new std::shared_ptr<Environment>(*plain);
    const torch::Tensor prompt = (*plain)->prompt_embeds;
    ASSERT_TRUE(prompt.defined());

    // The same checkpoint plus negative_prompt_embeds.safetensors.
    cfg_dir_ = new std::string(LinkedCopy("cfg"));
    auto gen = at::make_generator<at::CPUGeneratorImpl>(77);
    const torch::Tensor negative =
        at::randn({1, prompt.size(1), prompt.size(2)}, gen, torch::kFloat32);
    ASSERT_TRUE(SaveSafetensors(*cfg_dir_ + "/negative_prompt_embeds.safetensors",
                                {{"prompt_embeds", negative}})
                    .ok());
    auto cfg = LoadEnvironment(*cfg_dir_);
    ASSERT_TRUE(cfg.ok()) << cfg.status();
    ASSERT_TRUE((*cfg)->negative_prompt_embeds.defined());
    EXPECT_TRUE(fd::testing::TensorsEqual((*cfg)->negative_prompt_embeds, negative));
    cfg_env_ = new std::shared_ptr<Environment>(*cfg);
    plain_ = new FramePipeline(*plain);
    cfg_ = new FramePipeline(*cfg);
  }
  static void TearDownTestSuite() {
    delete plain_;
    delete cfg_;
    delete plain_env_;
    delete cfg_env_;
    fs::remove_all(*cfg_dir_);
    delete cfg_dir_;
  }

  // A request with a ready condition in [-1, 1] and previous latent, all
  // drawn from `seed`.
  static PipelineInput Request(uint64_t seed) {
    auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
    PipelineInput r;
    r.condition = at::rand({1, 10, kSize, kSize}, gen, torch::kFloat32) * 2 - 1;
    r.prev_latent = at::randn({1, 4, kSize / 8, kSize / 8}, gen, torch::kFloat32);
    r.init_noise_seed = seed + 1000;
    r.steps = kSteps;
    r.want_float = true;
    r.keep_intermediates = true;  // the test reads the state's intermediates
    return r;
  }

  static FrameOutput RenderOne(const FramePipeline& pipeline, const PipelineInput& r) {
    auto out = pipeline.Render({r});
    EXPECT_TRUE(out.ok()) << out.status();
    return out.ok() ? (*out)[0] : FrameOutput{};
  }

  // eps of one item as the pipeline's Step computes it, from separate
  // batch-1 network calls: cond only (guidance 1) or eps_u + g (eps_c - eps_u).
  static torch::Tensor HandNoisePred(const Environment& env, const FrameState& s,
                                     const torch::Tensor& model_in, const torch::Tensor& t) {
    ControlNetModel controlnet = env.controlnet;
    UNet2DConditionModel unet = env.unet;
    auto eps_for = [&](const torch::Tensor& embeds) {
      auto residuals = controlnet->Run(model_in, t, embeds, s.condition, s.conditioning_scale);
      EXPECT_TRUE(residuals.ok()) << residuals.status();
      auto eps = unet->Run(torch::cat({model_in, s.prev_latent}, 1), t, embeds, *residuals);
      EXPECT_TRUE(eps.ok()) << eps.status();
      return eps->to(torch::kFloat32);
    };
    const torch::Tensor eps_c = eps_for(s.prompt_embeds);
    if (s.guidance_scale <= 1) return eps_c;
    const torch::Tensor eps_u = eps_for(s.negative_embeds);
    return eps_u + s.guidance_scale * (eps_c - eps_u);
  }

  static std::shared_ptr<Environment>* plain_env_;
  static std::shared_ptr<Environment>* cfg_env_;
  static std::string* cfg_dir_;
  static FramePipeline* plain_;  // no negative prompt embeddings
  static FramePipeline* cfg_;    // with negative_prompt_embeds.safetensors
};
std::shared_ptr<Environment>* FramePipelineOptionsTest::plain_env_ = nullptr;
std::shared_ptr<Environment>* FramePipelineOptionsTest::cfg_env_ = nullptr;
std::string* FramePipelineOptionsTest::cfg_dir_ = nullptr;
FramePipeline* FramePipelineOptionsTest::plain_ = nullptr;
FramePipeline* FramePipelineOptionsTest::cfg_ = nullptr;

// Guidance 1 takes no unconditional pass: with negative embeddings loaded it
// gives bit for bit what an environment without them gives.
TEST_F(FramePipelineOptionsTest, GuidanceOneIsThePlainPath) {
  PipelineInput with_one = Request(1);
  with_one.guidance_scale = 1.0;
  auto states = cfg_->Begin({with_one});
  ASSERT_TRUE(states.ok()) << states.status();
  EXPECT_EQ((*states)[0].guidance_scale, 1.0);
  EXPECT_FALSE((*states)[0].negative_embeds.defined());

  const FrameOutput plain = RenderOne(*plain_, Request(1));
  const FrameOutput cfg_one = RenderOne(*cfg_, with_one);
  const FrameOutput cfg_default = RenderOne(*cfg_, Request(1));
  EXPECT_TRUE(fd::testing::TensorsEqual(cfg_one.decoded, plain.decoded));
  EXPECT_TRUE(fd::testing::TensorsEqual(cfg_default.decoded, plain.decoded));
  EXPECT_TRUE(fd::testing::TensorsEqual(cfg_one.image_uint8, plain.image_uint8));
}

// One step with guidance g: noise_pred = eps_u + g (eps_c - eps_u) from
// separate cond / uncond network calls, and the latents are the scheduler's
// step with that prediction.
TEST_F(FramePipelineOptionsTest, GuidanceCombinesUncondAndCondPredictions) {
  const Environment& env = **cfg_env_;
  for (const double g : {1.0, 3.5}) {
    PipelineInput r = Request(2);
    r.guidance_scale = g;
    r.conditioning_scale = 0.8;
    auto states = cfg_->Begin({r});
    ASSERT_TRUE(states.ok()) << states.status();
    FrameState& s = (*states)[0];
    ASSERT_EQ(s.negative_embeds.defined(), g > 1);
    const torch::Tensor x = s.latents.clone();
    FrameState* one = &s;
    ASSERT_TRUE(cfg_->Step({one}).ok());

    torch::InferenceMode inference_mode;
    auto scheduler = env.GetScheduler(SchedulerType::kUniPCMultistep);
    ASSERT_TRUE(scheduler.ok());
    auto hand = (*scheduler)->NewState(kSteps);
    ASSERT_TRUE(hand.ok());
    const SchedulerState* chand = &*hand;
    auto model_in = (*scheduler)->ScaleModelInput({chand}, x);
    auto t = (*scheduler)->CurrentTimesteps({chand});
    ASSERT_TRUE(model_in.ok() && t.ok());
    const torch::Tensor eps = HandNoisePred(env, s, *model_in, *t);
    // The pipeline's cond/uncond rows run as one batch-2 call and the hand
    // prediction as two batch-1 calls, which differ by float32 noise d per
    // row (BLAS kernels block a batch differently; OpenBLAS's core type
    // changes d). eps_u + g (eps_c - eps_u) scales it by up to |1 - g| + g.
    const double amplification = std::abs(1 - g) + g;
    EXPECT_TRUE(fd::testing::TensorsClose(s.noise_pred, eps, 0, 1e-5 * amplification))
        << "guidance " << g;
    // The latents are the scheduler's step with the pipeline's noise_pred
    // exactly, and with the hand prediction up to its float32 noise (the
    // pipeline's cond/uncond rows run as one batch-2 call), which UniPC's
    // x0 = (x - sigma eps) / alpha scales up.
    SchedulerState copy = *hand;
    SchedulerState* mcopy = &copy;
    auto exact = (*scheduler)->Step({mcopy}, s.noise_pred, x);
    ASSERT_TRUE(exact.ok()) << exact.status();
    EXPECT_TRUE(fd::testing::TensorsEqual(s.latents, exact->prev_sample)) << "guidance " << g;
    SchedulerState* mhand = &*hand;
    auto stepped = (*scheduler)->Step({mhand}, eps, x);
    ASSERT_TRUE(stepped.ok()) << stepped.status();
    EXPECT_TRUE(fd::testing::TensorsClose(s.latents, stepped->prev_sample, 1e-5 * amplification,
                                          1e-6 * amplification))
        << "guidance " << g;
    std::printf("[ cfg     ] guidance %.1f: |noise_pred - hand| max %.3g\n", g,
                MaxAbsDiff(s.noise_pred, eps));
    if (g > 1) {
      // The guidance is not a no-op: the conditional prediction alone differs.
      FrameState cond_only = s;
      cond_only.guidance_scale = 1;
      EXPECT_GT(MaxAbsDiff(HandNoisePred(env, cond_only, *model_in, *t), eps), 1e-3);
    }
  }
}

TEST_F(FramePipelineOptionsTest, GuidanceWithoutNegativeEmbeddingsIsRefused) {
  PipelineInput r = Request(3);
  r.guidance_scale = 2.0;
  auto states = plain_->Begin({Request(4), r});
  ASSERT_FALSE(states.ok());
  EXPECT_EQ(states.status().code(), absl::StatusCode::kFailedPrecondition) << states.status();
  const std::string message(states.status().message());
  EXPECT_THAT(message, HasSubstr("item 1"));
  EXPECT_THAT(message, HasSubstr("guidance_scale > 1 needs negative prompt embeddings"));
  EXPECT_THAT(message, HasSubstr("negative_prompt_embeds.safetensors"));

  // Per-item prompt embeddings whose length the negative ones do not have
  // (half the environment's prompt length, whatever the golden set's).
  const torch::Tensor prompt = (*cfg_env_)->prompt_embeds;
  ASSERT_GE(prompt.size(1), 2);
  const int64_t half = prompt.size(1) / 2;
  r.prompt_embeds = prompt.slice(1, 0, half);
  states = cfg_->Begin({r});
  ASSERT_FALSE(states.ok());
  EXPECT_EQ(states.status().code(), absl::StatusCode::kFailedPrecondition) << states.status();
  EXPECT_THAT(std::string(states.status().message()), HasSubstr(absl::StrCat("of length ", half)));

  r = Request(3);
  r.guidance_scale = 0.5;
  states = cfg_->Begin({r});
  EXPECT_EQ(states.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(states.status().message()), HasSubstr("item 0: guidance_scale"));
}

// Items with different guidance (and two sharing one) rendered in one batch
// equal each rendered alone; different guidance gives different frames.
TEST_F(FramePipelineOptionsTest, MixedGuidanceBatchEqualsAlone) {
  std::vector<PipelineInput> requests;
  const std::vector<double> guidance = {1.0, 2.5, 2.5, 6.0, 0.0 /* default */};
  for (size_t i = 0; i < guidance.size(); ++i) {
    PipelineInput r = Request(10 + i);
    if (guidance[i] > 0) r.guidance_scale = guidance[i];
    requests.push_back(r);
  }
  auto together = cfg_->Render(requests);
  ASSERT_TRUE(together.ok()) << together.status();
  for (size_t i = 0; i < requests.size(); ++i) {
    const FrameOutput alone = RenderOne(*cfg_, requests[i]);
    const double diff = MaxAbsDiff((*together)[i].image_float, alone.image_float);
    EXPECT_LE(diff, 1e-5) << "item " << i;
    std::printf("[ cfg     ] item %zu guidance %.1f: |batch - alone| max %.3g\n", i, guidance[i],
                diff);
  }
  PipelineInput g1 = Request(11);
  g1.guidance_scale = 1.0;
  EXPECT_GT(MaxAbsDiff(RenderOne(*cfg_, g1).image_float, (*together)[1].image_float), 1e-3);
}

// VaeDecodeBatching::kBatched decodes each frame size in one VAE call (the
// GPU default); per item is the CPU default. Both give the same frames: two
// sizes, three items, in an order that interleaves the sizes.
TEST_F(FramePipelineOptionsTest, BatchedVaeDecodeEqualsPerItem) {
  FramePipelineOptions batched_options;
  batched_options.vae_decode = VaeDecodeBatching::kBatched;
  const FramePipeline batched(*plain_env_, batched_options);
  FramePipelineOptions per_item_options;
  per_item_options.vae_decode = VaeDecodeBatching::kPerItem;
  const FramePipeline per_item(*plain_env_, per_item_options);

  std::vector<PipelineInput> requests = {Request(60), Request(61), Request(62)};
  {  // item 1 is twice as wide
    auto gen = at::make_generator<at::CPUGeneratorImpl>(63);
    requests[1].condition = at::rand({1, 10, kSize, 2 * kSize}, gen, torch::kFloat32) * 2 - 1;
    requests[1].prev_latent = at::randn({1, 4, kSize / 8, kSize / 4}, gen, torch::kFloat32);
  }
  requests[2].want_float = false;
  auto a = batched.Render(requests);
  auto b = per_item.Render(requests);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  for (size_t i = 0; i < requests.size(); ++i) {
    const FrameOutput& x = (*a)[i];
    const FrameOutput& y = (*b)[i];
    ASSERT_EQ(x.image_uint8.sizes(), y.image_uint8.sizes()) << "item " << i;
    EXPECT_EQ(x.image_uint8.size(1), i == 1 ? 2 * kSize : kSize);
    // uint8 may differ by one step where a float lands on a rounding edge.
    EXPECT_LE(MaxAbsDiff(x.image_uint8.to(torch::kFloat32), y.image_uint8.to(torch::kFloat32)), 1)
        << "item " << i;
    EXPECT_EQ(x.image_float.defined(), requests[i].want_float);
    if (requests[i].want_float) {
      EXPECT_EQ(x.image_float.sizes(), y.image_float.sizes());
      EXPECT_LE(MaxAbsDiff(x.image_float, y.image_float), 1e-5) << "item " << i;
      EXPECT_LE(MaxAbsDiff(x.decoded, y.decoded), 1e-5) << "item " << i;
    }
  }
  // The CPU default at one thread is per item: bit for bit the per-item
  // pipeline. (At two threads it batches, which is not bitwise; whether it
  // happened to match depended on the process's history.)
  const int caller_threads = at::get_num_threads();
  at::set_num_threads(1);
  auto c = plain_->Render(requests);
  auto d = per_item.Render(requests);
  at::set_num_threads(caller_threads);
  ASSERT_TRUE(c.ok()) << c.status();
  ASSERT_TRUE(d.ok()) << d.status();
  for (size_t i = 0; i < requests.size(); ++i) {
    EXPECT_TRUE(fd::testing::TensorsEqual((*c)[i].image_uint8, (*d)[i].image_uint8));
  }
}

// environment.json's guidance_scale is the default of every request.
TEST_F(FramePipelineOptionsTest, EnvironmentDefaultGuidance) {
  const std::string dir = LinkedCopy("cfg_default");
  fs::create_symlink(fs::path(*cfg_dir_) / "negative_prompt_embeds.safetensors",
                     fs::path(dir) / "negative_prompt_embeds.safetensors");
  std::ofstream(dir + "/environment.json") << R"({"guidance_scale": 2.5})";
  auto env = LoadEnvironment(dir);
  ASSERT_TRUE(env.ok()) << env.status();
  FramePipeline pipeline(*env);
  auto states = pipeline.Begin({Request(5)});
  ASSERT_TRUE(states.ok()) << states.status();
  EXPECT_EQ((*states)[0].guidance_scale, 2.5);
  PipelineInput explicit_g = Request(5);
  explicit_g.guidance_scale = 2.5;
  EXPECT_TRUE(fd::testing::TensorsEqual(RenderOne(pipeline, Request(5)).decoded,
                                        RenderOne(*cfg_, explicit_g).decoded));
  fs::remove_all(dir);
}

// --- Samplers -------------------------------------------------------------

class FramePipelineSchedulerTest : public FramePipelineOptionsTest,
                                   public ::testing::WithParamInterface<SchedulerType> {};

std::string SchedulerParamName(const ::testing::TestParamInfo<SchedulerType>& info) {
  switch (info.param) {
    case SchedulerType::kUniPCMultistep:
      return "UniPC";
    case SchedulerType::kDPMSolverMultistep:
      return "DPMSolver";
    case SchedulerType::kDDIM:
      return "DDIM";
    case SchedulerType::kEulerDiscrete:
      return "Euler";
  }
  return "Unknown";
}

// The pipeline's Begin + Step loop equals a hand loop over the networks and
// Scheduler::Step with the same noise (x_T = noise * init_noise_sigma).
TEST_P(FramePipelineSchedulerTest, MatchesAHandLoop) {
  const Environment& env = **plain_env_;
  auto scheduler = env.GetScheduler(GetParam());
  ASSERT_TRUE(scheduler.ok()) << scheduler.status();
  PipelineInput r = Request(20);
  r.scheduler = GetParam();
  r.init_noise = torch::randn({1, 4, kSize / 8, kSize / 8},
                              at::make_generator<at::CPUGeneratorImpl>(21), torch::kFloat32);
  auto states = plain_->Begin({r});
  ASSERT_TRUE(states.ok()) << states.status();
  FrameState& s = (*states)[0];
  EXPECT_EQ(s.scheduler_type, GetParam());

  torch::InferenceMode inference_mode;
  auto hand = (*scheduler)->NewState(kSteps);
  ASSERT_TRUE(hand.ok());
  torch::Tensor x = r.init_noise * (*scheduler)->InitNoiseSigma(*hand);
  EXPECT_TRUE(fd::testing::TensorsEqual(s.latents, x));
  EXPECT_TRUE(fd::testing::TensorsEqual(s.scheduler_state.timesteps(), hand->timesteps()));
  double worst = 0;
  for (int i = 0; i < kSteps; ++i) {
    FrameState* one = &s;
    ASSERT_TRUE(plain_->Step({one}).ok());
    const SchedulerState* chand = &*hand;
    auto model_in = (*scheduler)->ScaleModelInput({chand}, x);
    auto t = (*scheduler)->CurrentTimesteps({chand});
    ASSERT_TRUE(model_in.ok() && t.ok());
    const torch::Tensor eps = HandNoisePred(env, s, *model_in, *t);
    SchedulerState* mhand = &*hand;
    auto stepped = (*scheduler)->Step({mhand}, eps, x);
    ASSERT_TRUE(stepped.ok()) << stepped.status();
    x = stepped->prev_sample;
    EXPECT_TRUE(fd::testing::TensorsClose(s.latents, x, 0, 1e-5)) << "step " << i;
    worst = std::max(worst, MaxAbsDiff(s.latents, x));
  }
  EXPECT_TRUE(s.finished());
  EXPECT_TRUE(hand->finished());
  std::printf("[ sampler ] %s: |pipeline - hand loop| latents max %.3g over %d steps\n",
              SchedulerParamName({GetParam(), 0}).c_str(), worst, kSteps);
}

// A frame renders, is finite and differs from UniPC's with the same noise.
TEST_P(FramePipelineSchedulerTest, RendersFiniteFramesUnlikeUniPC) {
  PipelineInput r = Request(30);
  r.scheduler = GetParam();
  const FrameOutput out = RenderOne(*plain_, r);
  ASSERT_TRUE(out.decoded.defined());
  EXPECT_TRUE(torch::isfinite(out.decoded).all().item<bool>());
  EXPECT_EQ(out.image_uint8.sizes(), (std::vector<int64_t>{kSize, kSize, 3}));
  if (GetParam() != SchedulerType::kUniPCMultistep) {
    r.scheduler = SchedulerType::kUniPCMultistep;
    const double diff = MaxAbsDiff(out.image_float, RenderOne(*plain_, r).image_float);
    EXPECT_GT(diff, 1e-3);
    std::printf("[ sampler ] %s vs UniPC: image_float max abs diff %.3g\n",
                SchedulerParamName({GetParam(), 0}).c_str(), diff);
  }
}

// Items of this sampler at different steps, batched with each other and
// with items of other samplers, equal each rendered alone.
TEST_P(FramePipelineSchedulerTest, BatchAtDifferentStepsEqualsAlone) {
  std::vector<PipelineInput> requests;
  for (uint64_t i = 0; i < 3; ++i) {
    PipelineInput r = Request(40 + i);
    r.scheduler = GetParam();
    requests.push_back(r);
  }
  PipelineInput other = Request(43);
  other.scheduler = GetParam() == SchedulerType::kUniPCMultistep ? SchedulerType::kDDIM
                                                                 : SchedulerType::kUniPCMultistep;
  requests.push_back(other);
  requests[2].steps = kSteps + 2;
  auto states = plain_->Begin(requests);
  ASSERT_TRUE(states.ok()) << states.status();
  std::vector<FrameState*> all;
  for (FrameState& s : *states) all.push_back(&s);
  ASSERT_TRUE(plain_->Step({all[0]}).ok());
  ASSERT_TRUE(plain_->Step({all[0], all[1]}).ok());
  while (true) {
    std::vector<FrameState*> active;
    for (FrameState* s : all) {
      if (!s->finished()) active.push_back(s);
    }
    if (active.empty()) break;
    ASSERT_TRUE(plain_->Step(active).ok());
  }
  auto out = plain_->Finish(all);
  ASSERT_TRUE(out.ok()) << out.status();
  for (size_t i = 0; i < requests.size(); ++i) {
    const double diff =
        MaxAbsDiff((*out)[i].image_float, RenderOne(*plain_, requests[i]).image_float);
    EXPECT_LE(diff, 1e-5) << "item " << i;
  }
}

INSTANTIATE_TEST_SUITE_P(Samplers, FramePipelineSchedulerTest,
                         ::testing::Values(SchedulerType::kUniPCMultistep,
                                           SchedulerType::kDPMSolverMultistep, SchedulerType::kDDIM,
                                           SchedulerType::kEulerDiscrete),
                         SchedulerParamName);

}  // namespace
}  // namespace fd::model
