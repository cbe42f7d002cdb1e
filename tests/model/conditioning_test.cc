// Tests for model/pipeline/conditioning.h against the goldens of the authors' code
// (fd_pipeline/golden/gbuffer_ops.safetensors and the per-frame conditioning
// tensors of e2e.safetensors), plus the input validation.
#include "model/pipeline/conditioning.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <array>
#include <iostream>
#include <limits>
#include <map>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "model/checkpoint/safetensors.h"
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

// Golden images are HWC ([H, W, 3]) or HW; the API takes [N, C, H, W].
torch::Tensor Nchw(const torch::Tensor& image) {
  if (image.dim() == 2) return image.unsqueeze(0).unsqueeze(0);
  return image.permute({2, 0, 1}).unsqueeze(0).contiguous();
}

void ExpectSameBytes(const std::string& name, const torch::Tensor& actual,
                     const torch::Tensor& expected) {
  ASSERT_TRUE(actual.defined() && expected.defined()) << name;
  ASSERT_EQ(actual.sizes(), expected.sizes()) << name;
  ASSERT_EQ(actual.scalar_type(), expected.scalar_type()) << name;
  const int64_t differing = actual.ne(expected).sum().item<int64_t>();
  EXPECT_EQ(differing, 0) << name << ": " << differing << " values differ";
  std::cout << "[golden] " << name << " values_differing=" << differing << "\n";
}

// irradiance_uint8 may differ by 1 only where irradiance * 255 lies within
// 1e-4 of an integer (truncation boundary; fd_pipeline/README.md).
void ExpectIrradianceU8(const std::string& name, const torch::Tensor& actual,
                        const torch::Tensor& expected, const torch::Tensor& irradiance) {
  ASSERT_EQ(actual.sizes(), expected.sizes()) << name;
  const torch::Tensor diff = (actual.to(torch::kInt32) - expected.to(torch::kInt32)).abs();
  const torch::Tensor scaled = irradiance.to(torch::kFloat64) * 255;
  const torch::Tensor near_boundary = (scaled - scaled.round()).abs() < 1e-4;
  EXPECT_LE(diff.max().item<int>(), 1) << name;
  EXPECT_EQ(diff.gt(0).logical_and(near_boundary.logical_not()).sum().item<int64_t>(), 0)
      << name << ": a value differs away from a truncation boundary";
  std::cout << "[golden] " << name << " values_differing=" << diff.gt(0).sum().item<int64_t>()
            << "\n";
}

// ---------------------------------------------------------------------------
// gbuffer_ops.safetensors

class GBufferOpsTest : public ::testing::Test {
 protected:
  void SetUp() override { g_ = LoadGoldenTensors("fd_pipeline/golden/gbuffer_ops.safetensors"); }
  torch::Tensor In(const std::string& name) {
    return Nchw(GoldenTensor(g_, "in." + name + "_uint8"));
  }
  GBuffer Buffer(const torch::Tensor& basecolor) {
    return {basecolor, In("normals"), In("depth"), In("roughness"), In("metallic")};
  }
  TensorMap g_;
};

TEST_F(GBufferOpsTest, IrradianceIsBitExact) {
  auto irradiance = ComputeIrradiance(In("final"), In("albedo"));
  ASSERT_TRUE(irradiance.ok()) << irradiance.status();
  const torch::Tensor expected = GoldenTensor(g_, "irradiance");
  ExpectGoldenClose("gbuffer_ops/irradiance", irradiance->squeeze(0).squeeze(0), expected, 0, 0);
  ExpectIrradianceU8("gbuffer_ops/irradiance_uint8",
                     QuantizeIrradiance(*irradiance)->squeeze(0).squeeze(0),
                     GoldenTensor(g_, "irradiance_uint8"), expected);
}

TEST_F(GBufferOpsTest, SkyFillIsExact) {
  // The golden uses the albedo image as the basecolor.
  auto filled = FillSky(In("albedo"), In("depth"), In("injection"));
  ASSERT_TRUE(filled.ok()) << filled.status();
  ExpectSameBytes("gbuffer_ops/skyfill.basecolor_uint8", *filled,
                  Nchw(GoldenTensor(g_, "skyfill.basecolor_uint8")));
  // The mask really selects pixels (and not all of them).
  const int64_t sky = GoldenTensor(g_, "debug.sky_mask").sum().item<int64_t>();
  EXPECT_GT(sky, 0);
  EXPECT_LT(sky, GoldenTensor(g_, "debug.sky_mask").numel());
  EXPECT_EQ(filled->ne(In("albedo")).any(1).sum().item<int64_t>(),
            filled->ne(In("albedo"))
                .any(1)
                .logical_and(Nchw(GoldenTensor(g_, "debug.sky_mask")).squeeze(1).to(torch::kBool))
                .sum()
                .item<int64_t>());
}

TEST_F(GBufferOpsTest, GBufferTensorsMatch) {
  struct Case {
    std::string key;
    SkyFillMode sky_fill;
    std::string irradiance_final;  // input whose luma is divided by the albedo's
  };
  for (const Case& c :
       {Case{"gbuffer.self_irradiance", SkyFillMode::kSkyImage, "injection"},
        Case{"gbuffer.prev_irradiance", SkyFillMode::kSkyImage, "final"},
        Case{"gbuffer.prev_irradiance_no_injection", SkyFillMode::kNone, "final"}}) {
    FrameConditionInputs in;
    in.gbuffer = Buffer(In("albedo"));
    in.sky_fill = c.sky_fill;
    in.sky_image = In("injection");
    in.previous_output = In(c.irradiance_final);
    in.previous_basecolor = In("albedo");
    in.size_multiple = 1;  // the golden's size need not be a latent multiple
    auto out = BuildFrameCondition(in);
    ASSERT_TRUE(out.ok()) << out.status();
    ExpectGoldenClose("gbuffer_ops/" + c.key, out->condition.squeeze(0), GoldenTensor(g_, c.key), 0,
                      0);
  }
  // Channel 9 on its own (irradiance_normalized).
  auto irradiance = ComputeIrradiance(In("final"), In("albedo"));
  ASSERT_TRUE(irradiance.ok());
  auto quantized = QuantizeIrradiance(*irradiance);
  ASSERT_TRUE(quantized.ok()) << quantized.status();
  auto packed = PackCondition(Buffer(In("albedo")), *quantized, /*size_multiple=*/1);
  ASSERT_TRUE(packed.ok()) << packed.status();
  ExpectGoldenClose("gbuffer_ops/irradiance_normalized", packed->select(1, 9),
                    GoldenTensor(g_, "irradiance_normalized"), 0, 0);
}

// ---------------------------------------------------------------------------
// Per-frame conditioning of the autoregressive run (e2e.safetensors).

TEST(E2EConditioningTest, EveryFrameMatches) {
  const TensorMap e2e = LoadGoldenTensors("fd_pipeline/golden/e2e.safetensors");
  const TensorMap in = LoadGoldenTensors("fd_pipeline/golden/e2e_inputs.safetensors");
  int frames = 0;
  for (int f = 0;; ++f) {
    const std::string p = "frame" + std::to_string(f) + ".";
    if (!e2e.count(p + "controlnet_cond")) break;
    ++frames;
    auto input = [&](const std::string& name) {
      return Nchw(GoldenTensor(in, p + name + "_uint8"));
    };
    const torch::Tensor final_rgb = Nchw(GoldenTensor(e2e, p + "irradiance_final_uint8"));
    const torch::Tensor albedo_rgb = Nchw(GoldenTensor(e2e, p + "irradiance_albedo_uint8"));
    // The pipeline's sources: frame 0 uses the keyframe and its own basecolor,
    // frame f > 0 the output and the RAW basecolor of frame f - 1.
    const std::string prev = "frame" + std::to_string(f == 0 ? 0 : f - 1) + ".";
    ExpectSameBytes(p + "irradiance_final source", final_rgb,
                    Nchw(f == 0 ? GoldenTensor(in, "keyframe_uint8")
                                : GoldenTensor(e2e, prev + "image_uint8")));
    ExpectSameBytes(p + "irradiance_albedo source", albedo_rgb,
                    Nchw(GoldenTensor(in, prev + "basecolor_uint8")));

    FrameConditionInputs ci;
    ci.gbuffer = {input("basecolor"), input("normals"), input("depth"), input("roughness"),
                  input("metallic")};
    ci.sky_fill = SkyFillMode::kSkyImage;
    ci.sky_image = input("injection_final");
    ci.previous_output = final_rgb;
    ci.previous_basecolor = albedo_rgb;
    auto out = BuildFrameCondition(ci);
    ASSERT_TRUE(out.ok()) << out.status();
    const torch::Tensor irradiance = GoldenTensor(e2e, p + "irradiance");
    ExpectGoldenClose("e2e/" + p + "irradiance", out->irradiance.squeeze(0).squeeze(0), irradiance,
                      0, 0);
    ExpectIrradianceU8("e2e/" + p + "irradiance_uint8", out->irradiance_u8.squeeze(0).squeeze(0),
                       GoldenTensor(e2e, p + "irradiance_uint8"), irradiance);
    ExpectSameBytes("e2e/" + p + "basecolor_skyfilled_uint8", out->basecolor,
                    Nchw(GoldenTensor(e2e, p + "basecolor_skyfilled_uint8")));
    ExpectGoldenClose("e2e/" + p + "controlnet_cond", out->condition,
                      GoldenTensor(e2e, p + "controlnet_cond"), 0, 0);

    // What frame f + 1 will use, from this frame's uint8 output.
    const torch::Tensor output_u8 = Nchw(GoldenTensor(e2e, p + "image_uint8"));
    auto next = ComputeIrradiance(output_u8, input("basecolor"));
    ASSERT_TRUE(next.ok());
    ExpectGoldenClose("e2e/" + p + "next_irradiance", next->squeeze(0).squeeze(0),
                      GoldenTensor(e2e, p + "next_irradiance"), 0, 0);
    ExpectSameBytes("e2e/" + p + "next_irradiance_uint8",
                    QuantizeIrradiance(*next)->squeeze(0).squeeze(0),
                    GoldenTensor(e2e, p + "next_irradiance_uint8"));

    // A float output image is quantised as the pipeline does (round half even).
    auto quantised = ToUint8Image(GoldenTensor(e2e, p + "image_float"), "image_float", 3);
    ASSERT_TRUE(quantised.ok()) << quantised.status();
    ExpectSameBytes("e2e/" + p + "image_uint8 from image_float", *quantised, output_u8);
  }
  EXPECT_GT(frames, 0);
}

// ---------------------------------------------------------------------------
// Modes, dtypes and batching.

GBuffer RandomGBuffer(int64_t n, int64_t h, int64_t w, uint64_t seed) {
  torch::manual_seed(seed);
  auto img = [&](int64_t c) { return torch::randint(0, 256, {n, c, h, w}).to(torch::kUInt8); };
  GBuffer g{img(3), img(3), img(1), img(1), img(1)};
  // Make a sky region: black basecolor and depth in the top rows.
  g.basecolor.narrow(2, 0, 4).fill_(3);
  g.depth.narrow(2, 0, 4).fill_(2);
  return g;
}

TEST(ConditioningModesTest, PreviousOutputSkyBlackIrradianceAndMissingMetallic) {
  GBuffer g = RandomGBuffer(1, 16, 24, 5);
  g.metallic = torch::Tensor();
  const torch::Tensor prev = torch::randint(0, 256, {1, 3, 16, 24}).to(torch::kUInt8);
  FrameConditionInputs in;
  in.gbuffer = g;
  in.sky_fill = SkyFillMode::kPreviousOutput;
  in.previous_output = prev;
  in.previous_basecolor = g.basecolor;
  auto out = BuildFrameCondition(in);
  ASSERT_TRUE(out.ok()) << out.status();
  // Sky rows come from the previous output.
  EXPECT_TRUE(torch::equal(out->basecolor.narrow(2, 0, 4), prev.narrow(2, 0, 4)));
  // Absent metallic is an all-zero image: -1 after normalisation.
  EXPECT_TRUE(torch::equal(out->condition.select(1, 8), torch::full({1, 16, 24}, -1.0f)));

  // black_irradiance (models trained without it): channel 9 black, while the
  // previous output still fills the sky.
  FrameConditionInputs black = in;
  black.black_irradiance = true;
  auto dark = BuildFrameCondition(black);
  ASSERT_TRUE(dark.ok()) << dark.status();
  EXPECT_TRUE(torch::equal(dark->condition.select(1, 9), torch::full({1, 16, 24}, -1.0f)));
  EXPECT_TRUE(torch::equal(dark->basecolor, out->basecolor));
  EXPECT_FALSE(torch::equal(out->condition.select(1, 9), dark->condition.select(1, 9)));

  // G-buffer-only start: no previous frame -> black irradiance (-1), no sky fill.
  FrameConditionInputs start;
  start.gbuffer = g;
  auto first = BuildFrameCondition(start);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_TRUE(torch::equal(first->condition.select(1, 9), torch::full({1, 16, 24}, -1.0f)));
  EXPECT_TRUE(torch::equal(first->basecolor, g.basecolor));
  // Channel layout: basecolor 0-2, normals 3-5, depth 6, roughness 7.
  EXPECT_TRUE(torch::equal(first->condition.narrow(1, 3, 3),
                           (g.normals.to(torch::kFloat32) / 255.0 - 0.5) / 0.5));
  EXPECT_TRUE(torch::equal(first->condition.select(1, 7),
                           (g.roughness.select(1, 0).to(torch::kFloat32) / 255.0 - 0.5) / 0.5));
}

TEST(ConditioningModesTest, FloatInputsEqualTheirUint8Quantisation) {
  const GBuffer g = RandomGBuffer(2, 16, 16, 9);
  auto as_float = [](const torch::Tensor& t) { return t.to(torch::kFloat32) / 255.0; };
  FrameConditionInputs u8;
  u8.gbuffer = g;
  u8.sky_fill = SkyFillMode::kSkyImage;
  u8.sky_image = torch::full({2, 3, 16, 16}, 200).to(torch::kUInt8);
  u8.previous_output = torch::randint(0, 256, {2, 3, 16, 16}).to(torch::kUInt8);
  u8.previous_basecolor = g.basecolor;
  FrameConditionInputs fl = u8;
  fl.gbuffer = {as_float(g.basecolor), as_float(g.normals), as_float(g.depth),
                as_float(g.roughness), as_float(g.metallic)};
  fl.sky_image = as_float(u8.sky_image);
  fl.previous_output = as_float(u8.previous_output).to(torch::kFloat64);
  fl.previous_basecolor = as_float(g.basecolor);
  auto a = BuildFrameCondition(u8);
  auto b = BuildFrameCondition(fl);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_TRUE(torch::equal(a->condition, b->condition));

  // Batching: item 1 alone equals item 1 of the batch.
  FrameConditionInputs one = u8;
  one.gbuffer = {g.basecolor.narrow(0, 1, 1), g.normals.narrow(0, 1, 1), g.depth.narrow(0, 1, 1),
                 g.roughness.narrow(0, 1, 1), g.metallic.narrow(0, 1, 1)};
  one.sky_image = u8.sky_image.narrow(0, 1, 1);
  one.previous_output = u8.previous_output.narrow(0, 1, 1);
  one.previous_basecolor = g.basecolor.narrow(0, 1, 1);
  auto c = BuildFrameCondition(one);
  ASSERT_TRUE(c.ok());
  EXPECT_TRUE(torch::equal(c->condition, a->condition.narrow(0, 1, 1)));
}

// ---------------------------------------------------------------------------
// Validation: every bad input is refused with a message naming it.

void ExpectInvalid(const FrameConditionInputs& in, const std::string& named) {
  auto out = BuildFrameCondition(in);
  ASSERT_FALSE(out.ok()) << "accepted bad input (" << named << ")";
  EXPECT_EQ(out.status().code(), absl::StatusCode::kInvalidArgument) << out.status();
  EXPECT_THAT(out.status().message(), HasSubstr(named));
}

// The UNet's basecolor patches: cell (y, x) of channel c * f * f + i * f + j
// holds basecolor channel c at pixel (f * y + i, f * x + j), as
// torch.nn.PixelUnshuffle orders them.
TEST(BasecolorPatchesTest, UnshufflesTheBasecolorChannelsOnly) {
  FrameConditionInputs in;
  in.gbuffer = RandomGBuffer(2, 16, 24, 5);
  absl::StatusOr<FrameCondition> cond = BuildFrameCondition(in);
  ASSERT_TRUE(cond.ok()) << cond.status();
  absl::StatusOr<torch::Tensor> patches = BasecolorPatches(cond->condition, 8);
  ASSERT_TRUE(patches.ok()) << patches.status();
  ASSERT_EQ(patches->sizes(), torch::IntArrayRef({2, 192, 2, 3}));
  const torch::Tensor& c = cond->condition;
  for (const auto& [n, ch, i, j, y, x] : std::vector<std::array<int64_t, 6>>{
           {0, 0, 0, 0, 0, 0}, {1, 2, 7, 5, 1, 2}, {0, 1, 3, 6, 1, 0}}) {
    EXPECT_EQ((*patches)[n][ch * 64 + i * 8 + j][y][x].item<float>(),
              c[n][ch][8 * y + i][8 * x + j].item<float>())
        << n << " " << ch << " " << i << " " << j;
  }
  // The values stay the condition's [-1, 1] basecolor; nothing else enters.
  EXPECT_TRUE(torch::equal(torch::pixel_shuffle(*patches, 8), c.slice(1, 0, 3)));

  EXPECT_FALSE(BasecolorPatches(c.slice(3, 0, 20), 8).ok());  // 20 is no multiple of 8
  EXPECT_FALSE(BasecolorPatches(c.slice(1, 0, 2), 8).ok());   // no basecolor
  EXPECT_FALSE(BasecolorPatches(c, 0).ok());
  EXPECT_FALSE(BasecolorPatches(torch::Tensor(), 8).ok());
}

TEST(ConditioningValidationTest, RejectsBadInputs) {
  FrameConditionInputs good;
  good.gbuffer = RandomGBuffer(1, 16, 24, 3);
  good.previous_output = good.gbuffer.basecolor;
  good.previous_basecolor = good.gbuffer.basecolor;
  ASSERT_TRUE(BuildFrameCondition(good).ok());

  FrameConditionInputs in = good;
  in.gbuffer.normals = torch::zeros({1, 4, 16, 24}, torch::kUInt8);
  ExpectInvalid(in, "normals");  // channel count
  in = good;
  in.gbuffer.depth = torch::zeros({1, 3, 16, 24}, torch::kUInt8);
  ExpectInvalid(in, "depth");
  in = good;
  in.gbuffer.roughness = torch::zeros({1, 1, 16, 32}, torch::kUInt8);
  ExpectInvalid(in, "roughness");  // mismatched size
  in = good;
  in.gbuffer.metallic = torch::zeros({2, 1, 16, 24}, torch::kUInt8);
  ExpectInvalid(in, "metallic");  // mismatched batch
  in = good;
  in.gbuffer.basecolor = torch::zeros({1, 3, 12, 24}, torch::kUInt8);
  ExpectInvalid(in, "multiples of 8");
  in = good;
  in.gbuffer.basecolor = torch::zeros({3, 16, 24}, torch::kUInt8);
  ExpectInvalid(in, "basecolor");  // rank
  in = good;
  in.gbuffer.normals = torch::zeros({1, 3, 16, 24}, torch::kInt32);
  ExpectInvalid(in, "normals");  // dtype
  in = good;
  in.gbuffer.normals = torch::full({1, 3, 16, 24}, 0.5f);
  in.gbuffer.normals[0][1][2][3] = std::numeric_limits<float>::quiet_NaN();
  ExpectInvalid(in, "NaN");
  in = good;
  in.gbuffer.depth = torch::full({1, 1, 16, 24}, 0.5f);
  in.gbuffer.depth[0][0][0][0] = std::numeric_limits<float>::infinity();
  ExpectInvalid(in, "depth");
  in = good;
  in.previous_output = torch::full({1, 3, 16, 24}, 1.5f);
  ExpectInvalid(in, "previous_output");  // out of [0, 1]
  in = good;
  in.previous_basecolor = torch::Tensor();
  ExpectInvalid(in, "previous_basecolor");
  in = good;
  in.sky_fill = SkyFillMode::kSkyImage;
  ExpectInvalid(in, "sky_image");
  in = good;
  in.sky_fill = SkyFillMode::kPreviousOutput;
  in.previous_output = torch::Tensor();
  in.previous_basecolor = torch::Tensor();
  ExpectInvalid(in, "previous_output");

  auto packed = PackCondition(good.gbuffer, torch::zeros({1, 1, 16, 24}, torch::kFloat32));
  EXPECT_THAT(packed.status().message(), HasSubstr("irradiance"));
  auto irr = ComputeIrradiance(good.gbuffer.basecolor, torch::zeros({1, 3, 8, 24}, torch::kUInt8));
  EXPECT_THAT(irr.status().message(), HasSubstr("albedo"));
  auto sky = FillSky(good.gbuffer.basecolor, good.gbuffer.depth, torch::zeros({1, 1, 16, 24}));
  EXPECT_THAT(sky.status().message(), HasSubstr("sky image"));
}

}  // namespace
}  // namespace fd::model
