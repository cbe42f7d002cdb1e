// FramePipeline against the end-to-end goldens: the authors' autoregressive
// 3-frame run (fd_pipeline/golden/e2e*.safetensors; UniPC, live and merged
// ControlLoRA, teacher-forced and free-running) and the diffusers-convention
// loops of config B (B/golden/e2e, e2e_lora: DPM-Solver++, ready [0, 1]
// conditions). Plus batch independence, step-level batching and input
// validation. Shapes, seeds and step counts come from the files.
#include "model/pipeline/frame_pipeline.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cstdio>
#include <limits>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "base/status_macros.h"
#include "model/pipeline/conditioning.h"
#include "model/pipeline/environment.h"
#include "tests/model/network_golden.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

using testing::GoldenClose;
using testing::GoldenTensor;
using ::testing::HasSubstr;
using testing::ReadGolden;

using Tensors = std::map<std::string, torch::Tensor>;

// uint8 image check: max diff 1, only where the reference float is within
// 1e-3 (x255 units) of a rounding boundary k + 0.5 (float32 noise of a
// faithful port is ~1e-5 relative, far below that; see the README's
// boundary table).
void ExpectUint8Close(const torch::Tensor& out, const torch::Tensor& ref,
                      const torch::Tensor& ref_float, const std::string& what) {
  ASSERT_EQ(out.sizes(), ref.sizes()) << what;
  const torch::Tensor diff = (out.to(torch::kInt32) - ref.to(torch::kInt32)).abs();
  EXPECT_LE(diff.max().item<int>(), 1) << what;
  const torch::Tensor x255 = ref_float[0].permute({1, 2, 0}).to(torch::kFloat64) * 255;
  const torch::Tensor dist = (x255 - x255.floor() - 0.5).abs();
  const torch::Tensor bad = (diff > 0) & (dist > 1e-3);
  EXPECT_EQ(bad.sum().item<int64_t>(), 0) << what << ": values differ away from a boundary";
  EXPECT_LE(diff.gt(0).sum().item<int64_t>(), out.numel() / 200 + 1) << what;
}

class FramePipelineTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    inputs_ = new Tensors(ReadGolden("fd_pipeline/golden/e2e_inputs.safetensors"));
    e2e_ = new Tensors(ReadGolden("fd_pipeline/golden/e2e.safetensors"));
    auto env = LoadEnvironment(fd::testing::GoldenPath("fd_pipeline/model"));
    ASSERT_TRUE(env.ok()) << env.status();
    live_ = new FramePipeline(*env);
    FramePipelineOptions invariant;
    invariant.batch_invariant = true;
    invariant_ = new FramePipeline(*env, invariant);
  }
  static void TearDownTestSuite() {
    delete inputs_;
    delete e2e_;
    delete live_;
    delete invariant_;
  }

  static int NumFrames() {
    int n = 0;
    while (e2e_->count(absl::StrCat("frame", n, ".timesteps"))) ++n;
    return n;
  }
  static torch::Tensor In(const std::string& key) { return GoldenTensor(*inputs_, key); }
  static torch::Tensor Ref(const std::string& key) { return GoldenTensor(*e2e_, key); }

  // The request of frame f, teacher-forced (previous image and irradiance
  // sources as the reference had them), with the reference's noise.
  static PipelineInput Request(int f, bool inject_noise = true) {
    const std::string p = absl::StrCat("frame", f, ".");
    PipelineInput r;
    r.previous_frame = Ref(p + "lora_image_uint8");
    r.previous_basecolor = Ref(p + "irradiance_albedo_uint8");
    r.basecolor = In(p + "basecolor_uint8");
    r.normals = In(p + "normals_uint8");
    r.depth = In(p + "depth_uint8");
    r.roughness = In(p + "roughness_uint8");
    r.metallic = In(p + "metallic_uint8");
    r.sky_mode = SkyFillMode::kSkyImage;
    r.sky_image = In(p + "injection_final_uint8");
    r.keep_intermediates = true;  // the test reads the state's intermediates
    r.steps = static_cast<int>(Ref(p + "timesteps").numel());
    r.vae_noise_seed = static_cast<uint64_t>(In(p + "global_seed").item<int64_t>());
    r.init_noise_seed = static_cast<uint64_t>(In(p + "generator_seed").item<int64_t>());
    if (inject_noise) {
      r.vae_sample_noise = Ref(p + "vae_sample_noise");
      r.init_noise = Ref(p + "init_noise");
    }
    r.want_float = true;
    return r;
  }

  static Tensors* inputs_;
  static Tensors* e2e_;
  static FramePipeline* live_;
  static FramePipeline* invariant_;  // FramePipelineOptions::batch_invariant
};
Tensors* FramePipelineTest::inputs_ = nullptr;
Tensors* FramePipelineTest::e2e_ = nullptr;
FramePipeline* FramePipelineTest::live_ = nullptr;
FramePipeline* FramePipelineTest::invariant_ = nullptr;

// Runs one frame step by step, checking every intermediate (teacher-forced).
void CheckFrame(const FramePipeline& pipeline, const PipelineInput& request, const Tensors& e2e,
                int f, bool check_uint8, const std::string& label) {
  const std::string p = absl::StrCat("frame", f, ".");
  auto ref = [&](const std::string& key) { return GoldenTensor(e2e, p + key); };
  auto begun = pipeline.Begin({request});
  ASSERT_TRUE(begun.ok()) << begun.status();
  FrameState& s = (*begun)[0];
  EXPECT_TRUE(GoldenClose(label + ": " + p, s.condition.cpu(), ref("controlnet_cond"))) << p;
  EXPECT_TRUE(fd::testing::TensorsEqual(s.irradiance_u8[0][0].cpu(), ref("irradiance_uint8"))) << p;
  EXPECT_TRUE(fd::testing::TensorsEqual(s.basecolor[0].permute({1, 2, 0}).cpu(),
                                        ref("basecolor_skyfilled_uint8")))
      << p;
  EXPECT_TRUE(GoldenClose(label + ": " + p, s.prev_latent.cpu(), ref("prev_latent"))) << p;
  EXPECT_TRUE(fd::testing::TensorsEqual(s.scheduler_state.timesteps(), ref("timesteps"))) << p;
  const int steps = static_cast<int>(ref("timesteps").numel());
  for (int i = 0; i < steps; ++i) {
    FrameState* one = &s;
    ASSERT_TRUE(pipeline.Step({one}).ok());
    EXPECT_TRUE(GoldenClose(label + ": " + p, s.noise_pred.cpu(),
                            ref(absl::StrCat("step.", i, ".noise_pred"))))
        << p << "step " << i;
    EXPECT_TRUE(
        GoldenClose(label + ": " + p, s.latents.cpu(), ref(absl::StrCat("step.", i, ".latents"))))
        << p << "step " << i;
    EXPECT_EQ(s.scheduler_state.last_order(),
              ref(absl::StrCat("step.", i, ".order")).item<int64_t>());
  }
  EXPECT_TRUE(s.finished());
  FrameState* one = &s;
  auto out = pipeline.Finish({one});
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_TRUE(GoldenClose(label + ": " + p, (*out)[0].decoded, ref("decoded"))) << p;
  EXPECT_TRUE(GoldenClose(label + ": " + p, (*out)[0].image_float, ref("image_float"))) << p;
  if (check_uint8) {
    ExpectUint8Close((*out)[0].image_uint8, ref("image_uint8"), ref("image_float"),
                     p + "image_uint8");
  }
}

TEST_F(FramePipelineTest, AuthorsPipelineTeacherForcedLiveLora) {
  ASSERT_GT(NumFrames(), 0);
  for (int f = 0; f < NumFrames(); ++f)
    CheckFrame(*live_, Request(f), *e2e_, f, true, "fd_pipeline/e2e live LoRA");
}

TEST_F(FramePipelineTest, AuthorsPipelineTeacherForcedMergedLora) {
  EnvironmentOptions options;
  options.lora_mode = LoraMode::kMerged;
  auto env = LoadEnvironment(fd::testing::GoldenPath("fd_pipeline/model"), options);
  ASSERT_TRUE(env.ok()) << env.status();
  FramePipeline merged(*env);
  for (int f = 0; f < NumFrames(); ++f)
    CheckFrame(merged, Request(f), *e2e_, f, true, "fd_pipeline/e2e merged LoRA");
}

TEST_F(FramePipelineTest, NextIrradianceFromStoredOutput) {
  for (int f = 0; f < NumFrames(); ++f) {
    const std::string p = absl::StrCat("frame", f, ".");
    auto nchw = [](const torch::Tensor& hwc) { return hwc.permute({2, 0, 1}).unsqueeze(0); };
    auto irr = ComputeIrradiance(nchw(Ref(p + "image_uint8")), nchw(In(p + "basecolor_uint8")));
    ASSERT_TRUE(irr.ok()) << irr.status();
    EXPECT_TRUE(fd::testing::TensorsClose((*irr)[0][0], Ref(p + "next_irradiance"))) << p;
    auto u8 = QuantizeIrradiance(*irr);
    ASSERT_TRUE(u8.ok());
    EXPECT_TRUE(fd::testing::TensorsEqual((*u8)[0][0], Ref(p + "next_irradiance_uint8"))) << p;
  }
}

// True autoregression: frame f > 0 is fed this port's own uint8 output of
// frame f-1 (and the irradiance from it). Tolerances of the README's chain
// mode (frame 0 is per-frame exact).
TEST_F(FramePipelineTest, AuthorsPipelineFreeRunning) {
  torch::Tensor previous;
  for (int f = 0; f < NumFrames(); ++f) {
    const std::string p = absl::StrCat("frame", f, ".");
    PipelineInput r = Request(f);
    if (f > 0) r.previous_frame = previous;
    auto out = live_->Render({r});
    ASSERT_TRUE(out.ok()) << out.status();
    const FrameOutput& o = (*out)[0];
    if (f == 0) {
      EXPECT_TRUE(fd::testing::TensorsClose(o.image_float, Ref(p + "image_float")));
      ExpectUint8Close(o.image_uint8, Ref(p + "image_uint8"), Ref(p + "image_float"), p);
    } else {
      EXPECT_TRUE(fd::testing::TensorsClose(o.decoded, Ref(p + "decoded"), 3e-2)) << p;
      EXPECT_LE((o.image_float - Ref(p + "image_float")).abs().max().item<double>(), 1e-3) << p;
      const torch::Tensor diff =
          (o.image_uint8.to(torch::kInt32) - Ref(p + "image_uint8").to(torch::kInt32)).abs();
      EXPECT_LE(diff.max().item<int>(), 1) << p;
      EXPECT_LE(diff.gt(0).sum().item<int64_t>(), diff.numel() * 95 / 1000) << p;
    }
    const torch::Tensor flips = o.image_uint8.ne(Ref(p + "image_uint8"));
    std::printf(
        "[ chain   ] %s image_float max abs %.2e, image_uint8 values differing %lld of %lld\n",
        p.c_str(), (o.image_float - Ref(p + "image_float")).abs().max().item<double>(),
        static_cast<long long>(flips.sum().item<int64_t>()), static_cast<long long>(flips.numel()));
    previous = o.image_uint8;
  }
}

// Generated noise (per-item CPU generators seeded like the reference's
// global / pipeline generators) reproduces the reference's draws.
TEST_F(FramePipelineTest, SeededNoiseMatchesReferenceDraws) {
  auto begun = live_->Begin({Request(0, /*inject_noise=*/false)});
  ASSERT_TRUE(begun.ok()) << begun.status();
  EXPECT_TRUE(
      fd::testing::TensorsClose((*begun)[0].latents.cpu(), Ref("frame0.init_noise"), 0, 1e-6));
  EXPECT_TRUE(fd::testing::TensorsClose((*begun)[0].prev_latent.cpu(), Ref("frame0.prev_latent")));
}

TEST_F(FramePipelineTest, BatchEqualsAlone) {
  std::vector<PipelineInput> requests;
  for (int f = 0; f < NumFrames(); ++f) requests.push_back(Request(f, /*inject_noise=*/false));
  auto together = live_->Render(requests);
  ASSERT_TRUE(together.ok()) << together.status();
  for (size_t i = 0; i < requests.size(); ++i) {
    auto alone = live_->Render({requests[i]});
    ASSERT_TRUE(alone.ok()) << alone.status();
    EXPECT_LE(((*together)[i].image_float - (*alone)[0].image_float).abs().max().item<double>(),
              1e-5)
        << "item " << i;
  }
}

// Renders `a` and `b` through step-level batching: `a` takes `head_start`
// steps alone, then both step together until each has finished (b alone at
// the end), then both are decoded in one Finish. `states` keeps the states
// (for checks after the run).
absl::StatusOr<std::vector<FrameOutput>> RenderStaggered(const FramePipeline& pipeline,
                                                         const PipelineInput& a,
                                                         const PipelineInput& b, int head_start,
                                                         std::vector<FrameState>& states) {
  FD_ASSIGN_OR_RETURN(states, pipeline.Begin({a, b}));
  FrameState* first = &states[0];
  FrameState* second = &states[1];
  for (int i = 0; i < head_start; ++i) FD_RETURN_IF_ERROR(pipeline.Step({first}));
  while (!first->finished() || !second->finished()) {
    std::vector<FrameState*> active;
    if (!first->finished()) active.push_back(first);
    if (!second->finished()) active.push_back(second);
    FD_RETURN_IF_ERROR(pipeline.Step(active));
  }
  return pipeline.Finish({first, second});
}

TEST_F(FramePipelineTest, ItemsAtDifferentSteps) {
  ASSERT_GE(NumFrames(), 2);
  const std::vector<PipelineInput> requests = {Request(0, false), Request(1, false)};
  std::vector<FrameState> states;
  auto out = RenderStaggered(*live_, requests[0], requests[1], /*head_start=*/3, states);
  ASSERT_TRUE(out.ok()) << out.status();
  for (size_t i = 0; i < requests.size(); ++i) {
    auto alone = live_->Render({requests[i]});
    ASSERT_TRUE(alone.ok());
    EXPECT_LE(((*out)[i].image_float - (*alone)[0].image_float).abs().max().item<double>(), 1e-5)
        << "item " << i;
  }
  FrameState* finished = &states[0];
  EXPECT_EQ(live_->Step({finished}).code(), absl::StatusCode::kFailedPrecondition);
}

// batch_invariant: every item of a batch is bitwise the item rendered alone,
// whether the items run all steps together or join at different steps; and
// alone, the option changes nothing (batch 1 is the same calls).
TEST_F(FramePipelineTest, BatchInvariantItemsAreBitwiseAlone) {
  ASSERT_GE(NumFrames(), 2);
  std::vector<PipelineInput> requests;
  for (int f = 0; f < NumFrames(); ++f) requests.push_back(Request(f, /*inject_noise=*/false));
  auto together = invariant_->Render(requests);
  ASSERT_TRUE(together.ok()) << together.status();

  std::vector<FrameState> states;
  auto staggered = RenderStaggered(*invariant_, requests[0], requests[1], /*head_start=*/2, states);
  ASSERT_TRUE(staggered.ok()) << staggered.status();

  for (size_t i = 0; i < requests.size(); ++i) {
    auto alone = live_->Render({requests[i]});
    ASSERT_TRUE(alone.ok()) << alone.status();
    const FrameOutput& want = (*alone)[0];
    EXPECT_TRUE(torch::equal((*together)[i].image_float, want.image_float)) << "item " << i;
    EXPECT_TRUE(torch::equal((*together)[i].image_uint8, want.image_uint8)) << "item " << i;
    if (i < 2) {
      EXPECT_TRUE(torch::equal((*staggered)[i].image_float, want.image_float)) << "item " << i;
    }
  }
}

TEST_F(FramePipelineTest, GBufferOnlyStart) {
  PipelineInput r = Request(0, false);
  r.previous_frame = torch::Tensor();
  r.previous_basecolor = torch::Tensor();
  auto states = live_->Begin({r});
  ASSERT_TRUE(states.ok()) << states.status();
  EXPECT_EQ((*states)[0].prev_latent.abs().max().item<double>(), 0.0);
  EXPECT_EQ((*states)[0].irradiance_u8.max().item<int>(), 0);
  auto out = live_->Render({r});
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ((*out)[0].image_uint8.sizes(), Ref("frame0.image_uint8").sizes());
}

// An environment's "previous_latent": "reuse": the previous frame's own
// denoised latent (FrameOutput::latent) stands in for the VAE encode of its
// image, which still gives the irradiance and the sky fill.
TEST_F(FramePipelineTest, ReusedPreviousLatentReplacesOnlyTheEncode) {
  auto first = live_->Render({Request(0, false)});
  ASSERT_TRUE(first.ok()) << first.status();
  const FrameOutput& out0 = (*first)[0];
  ASSERT_TRUE(out0.latent.defined());
  EXPECT_EQ(out0.latent.sizes(), Ref("frame0.init_noise").sizes());
  {  // The image is the decode of exactly that latent.
    torch::InferenceMode inference_mode;
    AutoencoderKL vae = live_->environment().vae;  // holders share the module
    auto decoded = vae->Decode(out0.latent / vae->config().scaling_factor);
    ASSERT_TRUE(decoded.ok()) << decoded.status();
    EXPECT_TRUE(fd::testing::TensorsEqual((*decoded / 2 + 0.5).clamp(0, 1), out0.image_float));
  }

  PipelineInput encoded = Request(1, false);
  encoded.previous_frame = out0.image_uint8;
  PipelineInput reused = encoded;
  reused.prev_latent = out0.latent;
  auto a = live_->Begin({encoded});
  auto b = live_->Begin({reused});
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_TRUE(fd::testing::TensorsEqual((*b)[0].prev_latent, out0.latent));
  EXPECT_FALSE(fd::testing::TensorsEqual((*a)[0].prev_latent, out0.latent));
  // Irradiance, sky fill and condition still come from the previous image.
  EXPECT_TRUE(fd::testing::TensorsEqual((*a)[0].irradiance_u8, (*b)[0].irradiance_u8));
  EXPECT_TRUE(fd::testing::TensorsEqual((*a)[0].basecolor, (*b)[0].basecolor));
  EXPECT_TRUE(fd::testing::TensorsEqual((*a)[0].condition_embedding, (*b)[0].condition_embedding));
  EXPECT_GT((*b)[0].irradiance_u8.max().item<int>(), 0);
}

TEST_F(FramePipelineTest, BadInputs) {
  auto expect_error = [&](PipelineInput r, const std::string& text) {
    auto s = live_->Begin({Request(0), r});
    ASSERT_FALSE(s.ok()) << text;
    EXPECT_EQ(s.status().code(), absl::StatusCode::kInvalidArgument) << s.status();
    EXPECT_THAT(std::string(s.status().message()), HasSubstr(text));
  };
  PipelineInput r = Request(0);
  r.normals = r.normals.slice(2, 0, 2);
  expect_error(r, "item 1: normals");
  r = Request(0);
  r.depth = r.depth.slice(0, 0, 8);
  expect_error(r, "item 1: depth");
  r = Request(0);
  r.basecolor = r.basecolor.to(torch::kFloat32) / 255;
  r.basecolor[0][0][0] = std::nan("");
  expect_error(r, "item 1: basecolor contains NaN");
  r = Request(0);
  for (torch::Tensor* t : {&r.previous_frame, &r.previous_basecolor, &r.basecolor, &r.normals,
                           &r.depth, &r.roughness, &r.metallic, &r.sky_image}) {
    *t = t->slice(0, 0, t->size(0) - 4);
  }
  expect_error(r, "not a multiple of 8");
  r = Request(0);
  r.init_noise = r.init_noise.slice(1, 0, 3);
  expect_error(r, "item 1: init_noise");
  r = Request(0);
  r.vae_sample_noise = r.vae_sample_noise * std::numeric_limits<float>::infinity();
  expect_error(r, "item 1: vae_sample_noise contains NaN or Inf");
  r = Request(0);
  r.sky_image = torch::Tensor();
  expect_error(r, "item 1: sky_image is missing");
}

// diffusers-convention loops of config B (top-level golden README, e2e /
// e2e_lora): DPM-Solver++ from B's scheduler config, the condition given
// directly in [0, 1], a float previous image, per-item text embeddings.
void CheckConfigBLoop(const std::string& golden, bool lora) {
  const Tensors in = ReadGolden("B/golden/inputs.safetensors");
  const Tensors ref = ReadGolden("B/golden/" + golden + ".safetensors");
  EnvironmentOptions options;
  options.allow_missing_text = true;
  options.lora_policy = lora ? LoraPolicy::kRequire : LoraPolicy::kSkip;
  options.lora_mode = LoraMode::kMerged;
  auto env = LoadEnvironment(fd::testing::GoldenPath("B"), options);
  ASSERT_TRUE(env.ok()) << env.status();
  FramePipeline pipeline(*env);
  const int64_t batch = GoldenTensor(in, "latents_init").size(0);
  const int steps = static_cast<int>(GoldenTensor(ref, "timesteps").numel());
  std::vector<PipelineInput> requests;
  for (int64_t b = 0; b < batch; ++b) {
    PipelineInput r;
    r.condition = GoldenTensor(in, "controlnet_cond").slice(0, b, b + 1);
    r.previous_frame = GoldenTensor(in, "prev_image")[b].permute({1, 2, 0});
    r.vae_sample_noise = GoldenTensor(in, "prev_image_noise").slice(0, b, b + 1);
    r.init_noise = GoldenTensor(in, "latents_init").slice(0, b, b + 1);
    r.prompt_embeds = GoldenTensor(in, "encoder_hidden_states").slice(0, b, b + 1);
    r.scheduler = SchedulerType::kDPMSolverMultistep;
    r.steps = steps;
    r.keep_intermediates = true;  // the test reads the state's intermediates
    r.want_float = true;
    requests.push_back(r);
  }
  auto states = pipeline.Begin(requests);
  ASSERT_TRUE(states.ok()) << states.status();
  std::vector<FrameState*> all;
  for (FrameState& s : *states) all.push_back(&s);
  auto batched = [&](auto get) {
    std::vector<torch::Tensor> parts;
    for (FrameState* s : all) parts.push_back(get(*s).cpu());
    return torch::cat(parts, 0);
  };
  EXPECT_TRUE(GoldenClose("B/" + golden, batched([](FrameState& s) { return s.prev_latent; }),
                          GoldenTensor(ref, "prev_latent")))
      << golden;
  for (int i = 0; i < steps; ++i) {
    ASSERT_TRUE(pipeline.Step(all).ok());
    EXPECT_TRUE(GoldenClose("B/" + golden, batched([](FrameState& s) { return s.noise_pred; }),
                            GoldenTensor(ref, absl::StrCat("step.", i, ".noise_pred"))))
        << golden << " step " << i;
    EXPECT_TRUE(GoldenClose("B/" + golden, batched([](FrameState& s) { return s.latents; }),
                            GoldenTensor(ref, absl::StrCat("step.", i, ".latents"))))
        << golden << " step " << i;
  }
  auto out = pipeline.Finish(all);
  ASSERT_TRUE(out.ok()) << out.status();
  if (ref.count("image_decoded")) {
    std::vector<torch::Tensor> decoded;
    for (const FrameOutput& o : *out) decoded.push_back(o.decoded);
    EXPECT_TRUE(GoldenClose("B/" + golden, torch::cat(decoded, 0), ref.at("image_decoded")));
  }
}

TEST(FramePipelineConfigBTest, E2e) { CheckConfigBLoop("e2e", /*lora=*/false); }

TEST(FramePipelineConfigBTest, E2eLora) { CheckConfigBLoop("e2e_lora", /*lora=*/true); }

}  // namespace
}  // namespace fd::model
