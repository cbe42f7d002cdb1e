// The step-invariant work FramePipeline hoists out of the denoising loop
// (docs/BENCHMARKS.md, "Step-invariant work"): the ControlNet's condition
// embedding and both networks' time embeddings computed apart give bitwise
// the forward's own result; the time-embedding cache returns exactly the
// batch-1 rows and stays bounded; a pipeline step equals the unhoisted
// network calls bitwise; a state keeps no inspection tensors unless asked.
#include <ATen/CPUGeneratorImpl.h>
#include <ATen/Parallel.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <algorithm>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "model/networks/attention_processor.h"
#include "model/networks/controlnet.h"
#include "model/networks/prompt_kv_cache.h"
#include "model/networks/unet.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"
#include "model/pipeline/thread_choice.h"
#include "model/pipeline/time_embedding_cache.h"
#include "model/runtime/core_budget.h"
#include "tests/model/network_golden.h"
#include "tests/testing/golden.h"

namespace fd::model {
namespace {

using testing::GoldenTensor;
using testing::ReadGolden;
using Tensors = std::map<std::string, torch::Tensor>;

void ExpectAllEqual(const std::vector<torch::Tensor>& got, const std::vector<torch::Tensor>& want) {
  ASSERT_EQ(got.size(), want.size());
  for (size_t i = 0; i < got.size(); ++i) {
    EXPECT_TRUE(torch::equal(got[i], want[i])) << "residual " << i;
  }
}

class StepInvariantsTest : public ::testing::TestWithParam<std::string> {};

// ControlNet (config A and B with diffusers' encoder, config A's
// controlnet_fd with the authors' 9-conv encoder).
TEST_P(StepInvariantsTest, ControlNetEmbeddedForwardIsBitwiseTheForward) {
  const std::string folder = GetParam();
  const std::string config = folder.substr(0, 1);
  auto controlnet = LoadControlNet(fd::testing::GoldenPath(folder), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  const auto in = ReadGolden(config + "/golden/inputs.safetensors");
  const torch::Tensor sample = GoldenTensor(in, "noisy_latent");
  const torch::Tensor t = GoldenTensor(in, "timestep");
  const torch::Tensor ehs = GoldenTensor(in, "encoder_hidden_states");
  const torch::Tensor cond = GoldenTensor(in, "controlnet_cond");
  auto whole = (*controlnet)->Run(sample, t, ehs, cond, 0.5);
  ASSERT_TRUE(whole.ok()) << whole.status();
  auto temb = (*controlnet)->RunTimeEmbedding(t, sample.size(0));
  ASSERT_TRUE(temb.ok()) << temb.status();
  auto cemb = (*controlnet)->RunConditionEmbedding(cond);
  ASSERT_TRUE(cemb.ok()) << cemb.status();
  auto parts = (*controlnet)->RunEmbedded(sample, *temb, ehs, *cemb, 0.5);
  ASSERT_TRUE(parts.ok()) << parts.status();
  ExpectAllEqual(*parts, *whole);

  // The shapes are checked, naming the tensor.
  auto bad_time = (*controlnet)->RunEmbedded(sample, temb->slice(1, 1), ehs, *cemb, 0.5);
  EXPECT_EQ(bad_time.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bad_time.status().message().find("time_emb"), std::string::npos);
  auto bad_cond = (*controlnet)->RunEmbedded(sample, *temb, ehs, cemb->slice(3, 1), 0.5);
  EXPECT_EQ(bad_cond.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bad_cond.status().message().find("cond_emb"), std::string::npos);
  auto odd = (*controlnet)->RunConditionEmbedding(cond.slice(2, 1));
  EXPECT_EQ(odd.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(odd.status().message().find("controlnet_cond"), std::string::npos);
}

INSTANTIATE_TEST_SUITE_P(Goldens, StepInvariantsTest,
                         ::testing::Values("A/controlnet", "A/controlnet_fd", "B/controlnet"),
                         [](const auto& info) {
                           std::string name = info.param;
                           for (char& c : name) {
                             if (c == '/') c = '_';
                           }
                           return name;
                         });

// Config B's UNet with a golden 8-channel sample and the ControlNet's
// residuals for it.
class StepInvariantsUNetTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto loaded = LoadUNet(fd::testing::GoldenPath("B/unet"), torch::kCPU, torch::kFloat32);
    ASSERT_TRUE(loaded.ok()) << loaded.status();
    unet_ = *loaded;
    auto controlnet =
        LoadControlNet(fd::testing::GoldenPath("B/controlnet"), torch::kCPU, torch::kFloat32);
    ASSERT_TRUE(controlnet.ok()) << controlnet.status();
    const auto in = ReadGolden("B/golden/inputs.safetensors");
    latent_ = GoldenTensor(in, "noisy_latent");
    sample_ = torch::cat({latent_, latent_.flip({0})}, 1);
    t_ = GoldenTensor(in, "timestep");
    ehs_ = GoldenTensor(in, "encoder_hidden_states");
    auto control = (*controlnet)->Run(latent_, t_, ehs_, GoldenTensor(in, "controlnet_cond"));
    ASSERT_TRUE(control.ok()) << control.status();
    control_ = *control;
  }
  UNet2DConditionModel unet_{nullptr};
  torch::Tensor latent_, sample_, t_, ehs_;
  std::vector<torch::Tensor> control_;
};

TEST_F(StepInvariantsUNetTest, EmbeddedForwardIsBitwiseTheForward) {
  for (const std::vector<torch::Tensor>& residuals : {std::vector<torch::Tensor>{}, control_}) {
    auto whole = unet_->Run(sample_, t_, ehs_, residuals);
    ASSERT_TRUE(whole.ok()) << whole.status();
    auto temb = unet_->RunTimeEmbedding(t_, sample_.size(0));
    ASSERT_TRUE(temb.ok()) << temb.status();
    auto parts = unet_->RunEmbedded(sample_, *temb, ehs_, residuals);
    ASSERT_TRUE(parts.ok()) << parts.status();
    EXPECT_TRUE(torch::equal(*parts, *whole));
  }
  auto bad = unet_->RunEmbedded(sample_, torch::zeros({1, 3}), ehs_);
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bad.status().message().find("time_emb"), std::string::npos);
}

class TimeEmbeddingCacheTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto unet = LoadUNet(fd::testing::GoldenPath("A/unet"), torch::kCPU, torch::kFloat32);
    ASSERT_TRUE(unet.ok()) << unet.status();
    auto controlnet =
        LoadControlNet(fd::testing::GoldenPath("A/controlnet_fd"), torch::kCPU, torch::kFloat32);
    ASSERT_TRUE(controlnet.ok()) << controlnet.status();
    unet_ = *unet;
    controlnet_ = *controlnet;
  }
  UNet2DConditionModel unet_{nullptr};
  ControlNetModel controlnet_{nullptr};
};

TEST_F(TimeEmbeddingCacheTest, RowsAreTheBatchOneEmbeddings) {
  TimeEmbeddingCache cache;
  const torch::Tensor t = torch::tensor({999.0f, 899.0f, 999.0f, 37.5f});
  for (int pass = 0; pass < 2; ++pass) {  // computed, then cached
    auto rows = cache.Get(controlnet_, unet_, t);
    ASSERT_TRUE(rows.ok()) << rows.status();
    ASSERT_EQ(rows->controlnet.size(0), 4);
    for (int64_t i = 0; i < 4; ++i) {
      auto c = controlnet_->RunTimeEmbedding(t.slice(0, i, i + 1), 1);
      auto u = unet_->RunTimeEmbedding(t.slice(0, i, i + 1), 1);
      ASSERT_TRUE(c.ok() && u.ok());
      EXPECT_TRUE(torch::equal(rows->controlnet.slice(0, i, i + 1), *c)) << "pass " << pass;
      EXPECT_TRUE(torch::equal(rows->unet.slice(0, i, i + 1), *u)) << "pass " << pass;
    }
    EXPECT_EQ(cache.size(), 3u);
  }
}

TEST_F(TimeEmbeddingCacheTest, StaysBounded) {
  TimeEmbeddingCache cache;
  const torch::Tensor t =
      torch::arange(0, static_cast<int64_t>(TimeEmbeddingCache::kMaxEntries) + 10, torch::kFloat32);
  auto rows = cache.Get(controlnet_, unet_, t);
  ASSERT_TRUE(rows.ok()) << rows.status();
  EXPECT_EQ(rows->unet.size(0), t.size(0));
  EXPECT_LE(cache.size(), TimeEmbeddingCache::kMaxEntries);
  EXPECT_GT(cache.size(), 0u);
}

// Config B's environment (golden condition, golden embeddings).
// The UNet's two halves (the down path beside the ControlNet, then the up
// path with its residuals) are bitwise the whole forward; the up path
// refuses a down path it cannot have come from and residuals that do not fit.
TEST_F(StepInvariantsUNetTest, DownThenUpIsBitwiseTheForward) {
  auto temb = unet_->RunTimeEmbedding(t_, sample_.size(0));
  ASSERT_TRUE(temb.ok()) << temb.status();
  for (const std::vector<torch::Tensor>& residuals : {std::vector<torch::Tensor>{}, control_}) {
    auto whole = unet_->RunEmbedded(sample_, *temb, ehs_, residuals);
    ASSERT_TRUE(whole.ok()) << whole.status();
    auto down = unet_->RunDown(sample_, *temb, ehs_);
    ASSERT_TRUE(down.ok()) << down.status();
    EXPECT_EQ(static_cast<int64_t>(down->res_samples.size()), unet_->num_down_residuals());
    auto up = unet_->RunUp(*std::move(down), *temb, ehs_, residuals);
    ASSERT_TRUE(up.ok()) << up.status();
    EXPECT_TRUE(torch::equal(*up, *whole));
  }
  auto incomplete = unet_->RunUp({}, *temb, ehs_, control_);
  EXPECT_EQ(incomplete.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(incomplete.status().message().find("down path"), std::string::npos);
  auto down = unet_->RunDown(sample_, *temb, ehs_);
  ASSERT_TRUE(down.ok()) << down.status();
  std::vector<torch::Tensor> short_control(control_.begin(), control_.end() - 1);
  auto misfit = unet_->RunUp(*down, *temb, ehs_, short_control);
  EXPECT_EQ(misfit.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(misfit.status().message().find("residuals"), std::string::npos);
  auto bad_sample = unet_->RunDown(latent_, *temb, ehs_);  // 4 channels, conv_in takes 8
  EXPECT_EQ(bad_sample.status().code(), absl::StatusCode::kInvalidArgument);
}

class HoistedStepTest : public ::testing::Test {
 protected:
  void SetUp() override {
    EnvironmentOptions options;
    options.allow_missing_text = true;
    options.lora_policy = LoraPolicy::kSkip;
    auto env = LoadEnvironment(fd::testing::GoldenPath("B"), options);
    ASSERT_TRUE(env.ok()) << env.status();
    env_ = *env;
    in_ = ReadGolden("B/golden/inputs.safetensors");
  }
  PipelineInput Request(int64_t b) const {
    PipelineInput r;
    r.condition = GoldenTensor(in_, "controlnet_cond").slice(0, b, b + 1);
    r.previous_frame = GoldenTensor(in_, "prev_image")[b].permute({1, 2, 0});
    r.prompt_embeds = GoldenTensor(in_, "encoder_hidden_states").slice(0, b, b + 1);
    r.scheduler = SchedulerType::kDPMSolverMultistep;
    r.steps = 4;
    r.vae_noise_seed = 7 + b;
    r.init_noise_seed = 9 + b;
    return r;
  }
  std::shared_ptr<Environment> env_;
  Tensors in_;
};

TEST_F(HoistedStepTest, StepIsBitwiseTheUnhoistedNetworkCalls) {
  FramePipeline pipeline(env_);
  PipelineInput r = Request(0);
  r.keep_intermediates = true;
  auto states = pipeline.Begin({r});
  ASSERT_TRUE(states.ok()) << states.status();
  FrameState& s = (*states)[0];
  for (int step = 0; step < 4; ++step) {
    const torch::Tensor x = s.latents;
    const SchedulerState* st = &s.scheduler_state;
    auto t = s.scheduler->CurrentTimesteps({st});
    ASSERT_TRUE(t.ok());
    // In inference mode, as the pipeline's steps run: the fused attention
    // kernel (model/runtime/attention_kernel.h) applies there only.
    std::optional<torch::InferenceMode> inference(std::in_place);
    auto residuals = env_->controlnet->Run(x, *t, s.prompt_embeds, s.condition, 1.0);
    ASSERT_TRUE(residuals.ok()) << residuals.status();
    auto eps = env_->unet->Run(torch::cat({x, s.prev_latent}, 1), *t, s.prompt_embeds, *residuals);
    ASSERT_TRUE(eps.ok()) << eps.status();
    inference.reset();
    FrameState* p = &s;
    ASSERT_TRUE(pipeline.Step({p}).ok());
    EXPECT_TRUE(torch::equal(s.noise_pred, *eps)) << "step " << step;
  }
}

TEST_F(HoistedStepTest, StatesKeepOnlyWhatTheStepsNeed) {
  FramePipeline pipeline(env_);
  auto states = pipeline.Begin({Request(0), Request(1)});
  ASSERT_TRUE(states.ok()) << states.status();
  for (FrameState& s : *states) {
    EXPECT_FALSE(s.condition.defined());
    EXPECT_FALSE(s.irradiance.defined());
    EXPECT_FALSE(s.irradiance_u8.defined());
    EXPECT_FALSE(s.basecolor.defined());
    ASSERT_TRUE(s.condition_embedding.defined());
    EXPECT_EQ(s.condition_embedding.size(0), 1);
    EXPECT_EQ(s.condition_embedding.size(1), env_->controlnet->config().block_out_channels[0]);
    EXPECT_EQ(s.condition_embedding.size(2), s.latents.size(2));
    EXPECT_EQ(s.condition_embedding.size(3), s.latents.size(3));
  }
  std::vector<FrameState*> all = {&(*states)[0], &(*states)[1]};
  while (!all[0]->finished()) ASSERT_TRUE(pipeline.Step(all).ok());
  for (FrameState* s : all) EXPECT_FALSE(s->noise_pred.defined());
  auto out = pipeline.Finish(all);
  ASSERT_TRUE(out.ok()) << out.status();
}

// The decode's batching choice: a batched decode and per-item decodes of the
// same states give the same frames to float32 rounding (the same pixels but
// for rare off-by-one rounding at .5), whichever kAuto picks.
TEST_F(HoistedStepTest, BatchedAndPerItemDecodesAgree) {
  std::vector<FrameOutput> outputs[2];
  const VaeDecodeBatching modes[2] = {VaeDecodeBatching::kBatched, VaeDecodeBatching::kPerItem};
  for (int m = 0; m < 2; ++m) {
    FramePipelineOptions options;
    options.vae_decode = modes[m];
    FramePipeline pipeline(env_, options);
    PipelineInput a = Request(0), b = Request(1);
    a.want_float = b.want_float = true;
    auto out = pipeline.Render({a, b});
    ASSERT_TRUE(out.ok()) << out.status();
    outputs[m] = *out;
  }
  for (int i = 0; i < 2; ++i) {
    EXPECT_LT((outputs[0][i].image_float - outputs[1][i].image_float).abs().max().item<double>(),
              1e-5);
    EXPECT_LE(
        (outputs[0][i].image_uint8.to(torch::kInt) - outputs[1][i].image_uint8.to(torch::kInt))
            .abs()
            .max()
            .item<int>(),
        1);
  }
}

}  // namespace
}  // namespace fd::model

namespace fd::model {
namespace {

// FramePipelineOptions::intra_op_threads: the calls run at that count and
// the caller's own count is restored; a pipeline fixed at 1 thread renders
// bitwise what a default pipeline renders on a 1-thread caller.
TEST_F(HoistedStepTest, FixedIntraOpThreadsAreUsedAndRestored) {
  FramePipelineOptions one;
  one.intra_op_threads = 1;
  FramePipeline fixed(env_, one);
  FramePipeline caller_threads(env_);
  at::set_num_threads(2);
  auto got = fixed.Render({Request(0)});
  ASSERT_TRUE(got.ok()) << got.status();
  EXPECT_EQ(at::get_num_threads(), 2);
  at::set_num_threads(1);
  auto want = caller_threads.Render({Request(0)});
  at::set_num_threads(2);
  ASSERT_TRUE(want.ok()) << want.status();
  EXPECT_TRUE(torch::equal((*got)[0].image_uint8, (*want)[0].image_uint8));
}

// The ControlNet beside the UNet's down path on the companion thread:
// every frame (a batch of two, and one alone) bitwise the sequential step's,
// also with batch invariance on (its scope reaches the companion's half),
// and repeatable.
TEST_F(HoistedStepTest, ControlNetBesideTheUNetIsBitwiseTheSequentialStep) {
  at::set_num_threads(1);
  for (const bool batch_invariant : {false, true}) {
    FramePipelineOptions sequential_options;
    sequential_options.batch_invariant = batch_invariant;
    FramePipelineOptions beside_options = sequential_options;
    beside_options.controlnet_beside_unet = ControlNetBeside::kAlways;
    FramePipeline sequential(env_, sequential_options);
    FramePipeline beside(env_, beside_options);
    for (const std::vector<PipelineInput>& items :
         {std::vector<PipelineInput>{Request(0), Request(1)},
          std::vector<PipelineInput>{Request(1)}}) {
      auto want = sequential.Render(items);
      ASSERT_TRUE(want.ok()) << want.status();
      for (int repeat = 0; repeat < 2; ++repeat) {
        auto got = beside.Render(items);
        ASSERT_TRUE(got.ok()) << got.status();
        ASSERT_EQ(got->size(), want->size());
        for (size_t i = 0; i < got->size(); ++i) {
          EXPECT_TRUE(torch::equal((*got)[i].latent, (*want)[i].latent))
              << "item " << i << " of " << items.size() << ", batch invariant " << batch_invariant;
          EXPECT_TRUE(torch::equal((*got)[i].image_uint8, (*want)[i].image_uint8));
        }
      }
    }
  }
}

// kWhenCoreFree takes the companion only while the budget has a core free:
// never with a 1-core budget, at every step with 2 cores and nothing else
// computing; the frames are the same either way, and every claim is
// released afterwards.
TEST_F(HoistedStepTest, ControlNetBesideTheUNetWhenACoreIsFree) {
  at::set_num_threads(1);
  std::vector<FrameOutput> frames;
  for (const int cores : {1, 2}) {
    CoreBudget budget(cores);
    FramePipelineOptions options;
    options.controlnet_beside_unet = ControlNetBeside::kWhenCoreFree;
    options.core_budget = &budget;
    FramePipeline pipeline(env_, options);
    auto out = pipeline.Render({Request(0)});
    ASSERT_TRUE(out.ok()) << out.status();
    EXPECT_EQ((*out)[0].timings.steps_beside, cores == 1 ? 0 : 4) << cores << " cores";
    EXPECT_EQ(budget.in_use(), 0);
    frames.push_back((*out)[0]);
  }
  EXPECT_TRUE(torch::equal(frames[0].image_uint8, frames[1].image_uint8));
  // A core held elsewhere (another worker computing) leaves none free.
  CoreBudget budget(2);
  const CoreBudget::Claim other_worker = budget.Take(1);
  FramePipelineOptions options;
  options.controlnet_beside_unet = ControlNetBeside::kWhenCoreFree;
  options.core_budget = &budget;
  auto out = FramePipeline(env_, options).Render({Request(0)});
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ((*out)[0].timings.steps_beside, 0);
  EXPECT_EQ(budget.in_use(), 1);
}

// vae_on_free_core: a one-thread pipeline's decode takes a second thread
// only while the budget has a core free, never with batch invariance; the
// frames agree to a unit of uint8 rounding, and the claims are released.
TEST_F(HoistedStepTest, VaeTakesASecondThreadWhenACoreIsFree) {
  at::set_num_threads(1);
  std::vector<torch::Tensor> images;
  for (const bool batch_invariant : {false, true}) {
    for (const int cores : {1, 2}) {
      CoreBudget budget(cores);
      FramePipelineOptions options;
      options.intra_op_threads = 1;
      options.vae_on_free_core = true;
      options.batch_invariant = batch_invariant;
      options.core_budget = &budget;
      PipelineInput request = Request(0);
      request.want_float = true;
      auto out = FramePipeline(env_, options).Render({request});
      ASSERT_TRUE(out.ok()) << out.status();
      const int want = cores == 2 && !batch_invariant ? 2 : 1;
      EXPECT_EQ((*out)[0].timings.vae_threads, want)
          << cores << " cores, batch invariant " << batch_invariant;
      EXPECT_EQ(budget.in_use(), 0);
      EXPECT_EQ(at::get_num_threads(), 1);  // the caller's count is back
      images.push_back((*out)[0].image_float);
    }
  }
  // Bitwise, so that the load (a free core or not) and a calibration that
  // chose otherwise never change a frame: the VAE's channels-last GroupNorm
  // is the invariant kernel (model/runtime/group_norm_kernel.h).
  for (size_t i = 1; i < images.size(); ++i) EXPECT_TRUE(images[i].equal(images[0])) << i;
}

// A frame at one intra-op thread is bitwise the frame at two, with or
// without the ControlNet beside the UNet: a server that calibrates to
// another thread count (after a restart, on another replica) renders the
// same frames for the same seed. Golden config B at 128x96: the VAE's outer
// levels are maps of 1024 positions and more, where LibTorch's own
// channels-last GroupNorm depended on the thread count.
TEST_F(HoistedStepTest, FramesAreTheSameAtAnyThreadCount) {
  at::set_num_threads(2);
  std::vector<torch::Tensor> images;
  for (const int threads : {1, 2}) {
    for (const ControlNetBeside beside : {ControlNetBeside::kNever, ControlNetBeside::kAlways}) {
      CoreBudget budget(4);
      FramePipelineOptions options;
      options.intra_op_threads = threads;
      options.controlnet_beside_unet = beside;
      options.vae_decode = VaeDecodeBatching::kPerItem;
      options.core_budget = &budget;
      PipelineInput request = Request(1);
      request.want_float = true;
      auto out = FramePipeline(env_, options).Render({request});
      ASSERT_TRUE(out.ok()) << out.status();
      images.push_back((*out)[0].image_float);
    }
  }
  for (size_t i = 1; i < images.size(); ++i) EXPECT_TRUE(images[i].equal(images[0])) << i;
}

TEST(CoreBudgetTest, TakesAndReleases) {
  CoreBudget budget(2);
  EXPECT_EQ(budget.cores(), 2);
  EXPECT_GE(CoreBudget::Process().cores(), 1);
  {
    const CoreBudget::Claim a = budget.Take(1);
    EXPECT_EQ(budget.in_use(), 1);
    std::optional<CoreBudget::Claim> b = budget.TryTake(1);
    ASSERT_TRUE(b.has_value());
    EXPECT_EQ(budget.in_use(), 2);
    EXPECT_FALSE(budget.TryTake(1).has_value());
    const CoreBudget::Claim over = budget.Take(2);  // counted even when over
    EXPECT_EQ(budget.in_use(), 4);
    CoreBudget::Claim moved = std::move(*b);
    b.reset();
    EXPECT_EQ(budget.in_use(), 4);  // the moved-from claim releases nothing
  }
  EXPECT_EQ(budget.in_use(), 0);
  EXPECT_TRUE(budget.TryTake(2).has_value());
  EXPECT_EQ(budget.in_use(), 0);  // the unnamed claim ended with its statement
  EXPECT_EQ(CoreBudget(0).cores(), 1);
}

TEST_F(HoistedStepTest, ChoosesAThreadCountByMeasuring) {
  at::set_num_threads(2);
  ThreadChoiceOptions no_companion;
  no_companion.companion = false;
  auto single = ChooseIntraOpThreads(env_, 1, no_companion);
  ASSERT_TRUE(single.ok()) << single.status();
  EXPECT_EQ(single->threads, 1);
  EXPECT_FALSE(single->controlnet_beside_unet);
  EXPECT_EQ(single->step_ms_one, 0);  // nothing to choose, nothing timed
  ThreadChoiceOptions options;
  options.rounds = 1;
  options.width = 128;  // the golden frame size, not the settings' default
  options.height = 96;
  const bool two_cores = CoreBudget::Process().cores() >= 2;
  if (two_cores) {
    // One thread per worker: 1 thread against 1 thread with the companion.
    auto one = ChooseIntraOpThreads(env_, 1, options);
    ASSERT_TRUE(one.ok()) << one.status();
    EXPECT_EQ(one->threads, 1);
    EXPECT_GT(one->step_ms_one, 0);
    EXPECT_EQ(one->step_ms_many, 0);
    EXPECT_GT(one->step_ms_beside, 0);
    EXPECT_EQ(one->controlnet_beside_unet, one->step_ms_beside < one->step_ms_one);
  }

  auto choice = ChooseIntraOpThreads(env_, 2, options);
  ASSERT_TRUE(choice.ok()) << choice.status();
  EXPECT_GT(choice->step_ms_one, 0);
  EXPECT_GT(choice->step_ms_many, 0);
  EXPECT_EQ(choice->step_ms_beside > 0, two_cores);  // timed only with a core to spare
  // The fastest of those timed: 1 thread, 2 threads, 1 thread beside.
  const double best =
      two_cores ? std::min({choice->step_ms_one, choice->step_ms_many, choice->step_ms_beside})
                : std::min(choice->step_ms_one, choice->step_ms_many);
  if (choice->threads == 1 && two_cores) {
    EXPECT_GT(choice->frame_ms_vae_one, 0);
    EXPECT_GT(choice->frame_ms_vae_two, 0);
    EXPECT_EQ(choice->vae_on_free_core, choice->frame_ms_vae_two < choice->frame_ms_vae_one);
  } else {
    EXPECT_FALSE(choice->vae_on_free_core);
  }
  if (choice->controlnet_beside_unet) {
    EXPECT_EQ(choice->threads, 1);
    EXPECT_EQ(choice->step_ms_beside, best);
  } else {
    EXPECT_EQ(choice->threads, choice->step_ms_many == best ? 2 : 1);
    EXPECT_EQ(choice->threads == 2 ? choice->step_ms_many : choice->step_ms_one, best);
  }
  EXPECT_EQ(at::get_num_threads(), 2);  // the caller's count is back
}

}  // namespace
}  // namespace fd::model

namespace fd::model {
namespace {

// Cross-attention with a PromptKvScope: each row's K/V projected alone and
// cached; at batch 1 bitwise the unscoped layer, at batch 2 each row is the
// row it has alone, and the second call reads the cache.
TEST(PromptKvCacheTest, ScopedCrossAttentionMatchesAndCaches) {
  AttentionOptions options;
  options.query_dim = 16;
  options.cross_attention_dim = 12;
  options.heads = 2;
  options.dim_head = 8;
  Attention attention(options);
  auto gen = at::make_generator<at::CPUGeneratorImpl>(3);
  torch::NoGradGuard no_grad;
  for (auto& p : attention->parameters()) p.normal_(0, 0.3, gen);
  const torch::Tensor x = at::randn({2, 5, 16}, gen);
  const torch::Tensor p0 = at::randn({1, 7, 12}, gen);
  const torch::Tensor p1 = at::randn({1, 7, 12}, gen);

  const torch::Tensor alone0 = attention(x.slice(0, 0, 1), p0);
  const torch::Tensor alone1 = attention(x.slice(0, 1, 2), p1);
  PromptKvCache cache;
  for (int pass = 0; pass < 2; ++pass) {
    {
      PromptKvScope scope(&cache, {p0});
      EXPECT_TRUE(torch::equal(attention(x.slice(0, 0, 1), p0), alone0)) << "pass " << pass;
    }
    PromptKvScope scope(&cache, {p0, p1});
    const torch::Tensor both = attention(x, torch::cat({p0, p1}, 0));
    EXPECT_TRUE(torch::allclose(both.slice(0, 0, 1), alone0, 0, 1e-6)) << "pass " << pass;
    EXPECT_TRUE(torch::allclose(both.slice(0, 1, 2), alone1, 0, 1e-6)) << "pass " << pass;
  }
  // Two prompts x (K + V) of [1, 7, 16] floats.
  EXPECT_EQ(cache.bytes(), size_t{2 * 2 * 7 * 16 * 4});
  EXPECT_EQ(PromptKvScope::Current(), nullptr);
  // Self-attention (no encoder states) ignores the scope.
  AttentionOptions self_options = options;
  self_options.cross_attention_dim = 0;
  Attention self_attention(self_options);
  for (auto& p : self_attention->parameters()) p.normal_(0, 0.3, gen);
  const torch::Tensor plain = self_attention(x.slice(0, 0, 1));
  PromptKvScope scope(&cache, {p0});
  EXPECT_TRUE(torch::equal(self_attention(x.slice(0, 0, 1)), plain));
}

}  // namespace
}  // namespace fd::model
