// trainer/sample_builder.h: the authors' sampling rules, checked by their
// frequencies and by recomputing what a sample must hold.
#include "trainer/sample_builder.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cmath>
#include <filesystem>
#include <map>

#include "model/checkpoint/checkpoint_writer.h"
#include "model/pipeline/conditioning.h"
#include "model/schedulers/scheduler.h"
#include "tests/trainer/trainer_test_util.h"
#include "trainer/training_data.h"

namespace fd::trainer {
namespace {

namespace fs = std::filesystem;

std::map<int, double> Frequencies(int (*sampler)(int64_t, int64_t, int, SampleRandom&),
                                  int64_t position, int64_t length, int draws) {
  std::map<int, double> counts;
  for (int i = 0; i < draws; ++i) {
    SampleRandom rng(MixSeed(1, 2, static_cast<uint64_t>(i)));
    counts[sampler(position, length, 2, rng)] += 1.0 / draws;
  }
  return counts;
}

TEST(TemporalOffsetTest, InteriorFrameFollowsTheAuthorsWeights) {
  // Weights 4 (|d| = 1), 1 (|d| = 2), 0.5 (d = 0): total 10.5.
  std::map<int, double> f = Frequencies(&SampleTemporalOffset, 5, 10, 40000);
  EXPECT_NEAR(f[-1], 4 / 10.5, 0.01);
  EXPECT_NEAR(f[1], 4 / 10.5, 0.01);
  EXPECT_NEAR(f[-2], 1 / 10.5, 0.006);
  EXPECT_NEAR(f[2], 1 / 10.5, 0.006);
  EXPECT_NEAR(f[0], 0.5 / 10.5, 0.005);
  EXPECT_EQ(f.size(), 5u);
}

TEST(TemporalOffsetTest, OffsetsPastTheEndsAreSkippedNotWrapped) {
  std::map<int, double> first = Frequencies(&SampleTemporalOffset, 0, 10, 20000);
  EXPECT_EQ(first.count(-1) + first.count(-2), 0u);
  EXPECT_NEAR(first[1], 4 / 5.5, 0.012);
  EXPECT_NEAR(first[2], 1 / 5.5, 0.01);
  EXPECT_NEAR(first[0], 0.5 / 5.5, 0.008);
  std::map<int, double> last = Frequencies(&SampleTemporalOffset, 9, 10, 20000);
  EXPECT_EQ(last.count(1) + last.count(2), 0u);
  std::map<int, double> second_last = Frequencies(&SampleTemporalOffset, 8, 10, 20000);
  EXPECT_EQ(second_last.count(2), 0u);
  EXPECT_GT(second_last[1], 0.0);
}

TEST(TemporalOffsetTest, GeneratedTargetsFollowTheAuthorsWeights) {
  // d = 0 is a candidate 20 % of the time with weight 8 (GBufferDataset 487).
  std::map<int, double> f = Frequencies(&SampleGeneratedTargetOffset, 5, 10, 40000);
  EXPECT_NEAR(f[0], 0.2 * 8 / 18, 0.006);
  EXPECT_NEAR(f[1], 0.8 * 0.4 + 0.2 * 4 / 18, 0.01);
  EXPECT_NEAR(f[-2], 0.8 * 0.1 + 0.2 * 1 / 18, 0.006);
}

TEST(SampleTimestepsTest, UniformAndCubicCoverTheRangeWithTheirMeans) {
  constexpr int64_t kT = 1000, kCount = 40000;
  at::Generator gen = SampleRandom(3).torch_gen;
  const torch::Tensor uniform = SampleTimesteps(TimestepSampling::kUniform, kT, kCount, gen);
  const torch::Tensor cubic = SampleTimesteps(TimestepSampling::kCubic, kT, kCount, gen);
  for (const torch::Tensor& t : {uniform, cubic}) {
    EXPECT_EQ(t.scalar_type(), torch::kLong);
    EXPECT_EQ(t.size(0), kCount);
    EXPECT_GE(t.min().item<int64_t>(), 0);
    EXPECT_LE(t.max().item<int64_t>(), kT - 1);
  }
  EXPECT_NEAR(uniform.to(torch::kDouble).mean().item<double>() / kT, 0.5, 0.01);
  // E[1 - u^3] = 3/4; P(t >= 0.87 T) = P(u^3 <= 0.13) = 0.13^(1/3).
  EXPECT_NEAR(cubic.to(torch::kDouble).mean().item<double>() / kT, 0.75, 0.01);
  EXPECT_NEAR((cubic >= 870).to(torch::kDouble).mean().item<double>(), std::cbrt(0.13), 0.01);
  // The same generator state gives the same draws.
  at::Generator a = SampleRandom(5).torch_gen, b = SampleRandom(5).torch_gen;
  EXPECT_TRUE(torch::equal(SampleTimesteps(TimestepSampling::kCubic, kT, 16, a),
                           SampleTimesteps(TimestepSampling::kCubic, kT, 16, b)));
}

// The trainer's regression target is what the server's samplers take the
// model output to be: fed the exact target, every scheduler's x0 estimate
// (pred_original_sample) is the clean latent, at low and high noise.
TEST(DiffusionTargetTest, TheSamplersRecoverTheCleanLatentFromTheExactTarget) {
  at::Generator gen = SampleRandom(11).torch_gen;
  const torch::Tensor latents = torch::randn({1, 4, 8, 8}, gen);  // one state, one item
  const torch::Tensor noise = torch::randn({1, 4, 8, 8}, gen);
  for (const char* prediction_type : {"epsilon", "v_prediction", "sample"}) {
    for (fd::model::SchedulerType type :
         {fd::model::SchedulerType::kDDIM, fd::model::SchedulerType::kUniPCMultistep,
          fd::model::SchedulerType::kDPMSolverMultistep}) {
      absl::StatusOr<fd::model::SchedulerSettings> settings =
          fd::model::SchedulerSettingsFromJson(fd::model::kSd15SchedulerConfigJson, type);
      ASSERT_TRUE(settings.ok()) << settings.status();
      settings->prediction_type = prediction_type;
      absl::StatusOr<fd::model::Scheduler> scheduler = fd::model::Scheduler::Create(*settings);
      ASSERT_TRUE(scheduler.ok()) << scheduler.status();
      absl::StatusOr<fd::model::SchedulerState> state = scheduler->NewState(10);
      ASSERT_TRUE(state.ok()) << state.status();
      for (int step = 0; step < 10; ++step) {
        fd::model::SchedulerState* states[] = {&*state};
        absl::StatusOr<torch::Tensor> t = scheduler->CurrentTimesteps({states[0]});
        ASSERT_TRUE(t.ok()) << t.status();
        const int64_t timestep = t->item<float>();
        const torch::Tensor a = scheduler->alphas_cumprod()[timestep].view({1, 1, 1, 1});
        const torch::Tensor noisy = a.sqrt() * latents + (1 - a).sqrt() * noise;
        const torch::Tensor target = DiffusionTarget(prediction_type, latents, noise, a);
        absl::StatusOr<fd::model::SchedulerStepOutput> out =
            scheduler->Step(absl::MakeSpan(states), target, noisy);
        ASSERT_TRUE(out.ok()) << out.status();
        EXPECT_TRUE(torch::allclose(out->pred_original_sample, latents, 1e-3, 1e-3))
            << prediction_type << " scheduler " << static_cast<int>(type) << " t=" << timestep
            << " max error " << (out->pred_original_sample - latents).abs().max().item<float>();
        // The trainer's pixel loss decodes what an inexact output implies:
        // the schedulers' pred_original_sample.
        if (type == fd::model::SchedulerType::kDDIM) {
          const torch::Tensor output = target + 0.1 * noise.flip(3);
          absl::StatusOr<fd::model::SchedulerState> other = scheduler->NewState(10);
          ASSERT_TRUE(other.ok());
          for (int s = 0; s < step; ++s) {
            fd::model::SchedulerState* o[] = {&*other};
            ASSERT_TRUE(scheduler->Step(absl::MakeSpan(o), target, noisy).ok());
          }
          fd::model::SchedulerState* o[] = {&*other};
          absl::StatusOr<fd::model::SchedulerStepOutput> inexact =
              scheduler->Step(absl::MakeSpan(o), output, noisy);
          ASSERT_TRUE(inexact.ok()) << inexact.status();
          EXPECT_TRUE(torch::allclose(inexact->pred_original_sample,
                                      PredictedCleanLatents(prediction_type, output, noisy, a),
                                      1e-4, 1e-4))
              << prediction_type << " t=" << timestep;
        }
      }
    }
  }
}

TEST(RecolourFrameTest, RelightsADiffuseSurfaceForItsReorderedAlbedo) {
  torch::manual_seed(3);
  const torch::Tensor albedo = torch::randint(64, 256, {3, 16, 16}, torch::kLong).to(torch::kUInt8);
  const torch::Tensor light = torch::rand({3, 16, 16}) * 0.7 + 0.3;  // a coloured light per pixel
  torch::Tensor image = (albedo.to(torch::kFloat32) * light).round().to(torch::kUInt8);
  torch::Tensor basecolor = albedo.clone();
  torch::Tensor depth = torch::full({1, 16, 16}, 200, torch::kUInt8);
  // Row 0 is sky: black basecolor and depth, a blue image.
  basecolor.slice(1, 0, 1).zero_();
  depth.slice(1, 0, 1).zero_();
  image.slice(1, 0, 1).select(0, 2).fill_(230);
  EXPECT_TRUE(torch::equal(RecolourFrame(image, basecolor, depth, 0), image));
  for (int order = 1; order < kChannelOrderCount; ++order) {
    const torch::Tensor recoloured = RecolourFrame(image, basecolor, depth, order);
    ASSERT_EQ(recoloured.scalar_type(), torch::kUInt8);
    EXPECT_TRUE(torch::equal(recoloured.slice(1, 0, 1), image.slice(1, 0, 1))) << order;
    // The new albedo under the same light, up to the input's rounding
    // scaled by the gain, and the output's own.
    const torch::Tensor a = albedo.to(torch::kFloat32).slice(1, 1);
    const torch::Tensor reordered = ReorderChannels(a, order);
    const torch::Tensor exact = reordered * light.slice(1, 1);
    const torch::Tensor bound = 0.5 * reordered / a + 0.5 + 1e-4;
    const torch::Tensor error = (recoloured.slice(1, 1).to(torch::kFloat32) - exact).abs();
    EXPECT_TRUE((error <= bound).all().item<bool>())
        << "order " << order << ": max error " << (error - bound).max().item<float>();
  }
  // kChannelOrders[5] swaps red and blue.
  const torch::Tensor rgb = torch::tensor({1, 2, 3}).view({3, 1, 1});
  EXPECT_TRUE(torch::equal(ReorderChannels(rgb, 5), torch::tensor({3, 2, 1}).view({3, 1, 1})));
}

TEST(RecolourFrameTest, DarkAlbedoChannelsAreFlooredNotDividedByZero) {
  const torch::Tensor basecolor = torch::tensor({0, 4, 200}, torch::kUInt8).view({3, 1, 1});
  const torch::Tensor depth = torch::full({1, 1, 1}, 200, torch::kUInt8);
  const torch::Tensor image = torch::tensor({1, 2, 100}, torch::kUInt8).view({3, 1, 1});
  // Order 5 (blue, green, red): gains 200 / 8, 4 / 8, 0 / 200.
  const torch::Tensor recoloured = RecolourFrame(image, basecolor, depth, 5);
  EXPECT_TRUE(torch::equal(recoloured, torch::tensor({25, 1, 0}, torch::kUInt8).view({3, 1, 1})))
      << recoloured.flatten();
}

TEST(InjectNoiseTest, AddsNoiseOfTheGivenSigmaAndTruncates) {
  torch::Tensor grey = torch::full({3, 64, 64}, 128, torch::kUInt8);
  at::Generator gen = SampleRandom(7).torch_gen;
  EXPECT_TRUE(torch::equal(InjectNoise(grey, 0.0, gen), grey));
  torch::Tensor noisy = InjectNoise(grey, 0.1, gen).to(torch::kFloat32) - 128;
  EXPECT_NEAR(noisy.std().item<double>(), 25.5, 1.0);
  // astype(uint8) truncates: the mean drops by about half a level.
  EXPECT_NEAR(noisy.mean().item<double>(), -0.5, 0.3);
  torch::Tensor white = torch::full({3, 16, 16}, 250, torch::kUInt8);
  torch::Tensor clipped = InjectNoise(white, 0.2, gen);
  EXPECT_EQ(clipped.max().item<int>(), 255);
}

TEST(BlurImageTest, KeepsFlatImagesAndTheMeanAndSpreadsAnEdgeBySigma) {
  torch::Tensor grey = torch::full({3, 16, 16}, 77, torch::kUInt8);
  EXPECT_TRUE(torch::equal(BlurImage(grey, 2.0), grey));
  torch::Tensor random = torch::randint(0, 256, {3, 24, 20}, torch::kLong).to(torch::kUInt8);
  EXPECT_TRUE(torch::equal(BlurImage(random, 0.0), random));
  // A one-pixel checkerboard averages out to mid-grey.
  torch::Tensor checker = (torch::arange(20).view({1, 20}) + torch::arange(20).view({20, 1})) % 2;
  checker = (checker * 255).to(torch::kUInt8).expand({3, 20, 20}).contiguous();
  // (Away from the borders, where the replicated edge breaks the pattern.)
  torch::Tensor smooth =
      BlurImage(checker, 1.5).to(torch::kFloat32).slice(1, 6, 14).slice(2, 6, 14);
  EXPECT_NEAR(smooth.min().item<double>(), 127.5, 1.0);
  EXPECT_NEAR(smooth.max().item<double>(), 127.5, 1.0);
  // A vertical edge (0 | 255 between columns 19 and 20) becomes the normal
  // CDF of the distance to it over sigma; rows and channels alike.
  torch::Tensor edge = torch::zeros({3, 8, 40}, torch::kUInt8);
  edge.slice(2, 20) = 255;
  torch::Tensor ramp = BlurImage(edge, 4.0).to(torch::kFloat32);
  auto normal_cdf = [](double x) { return 0.5 * std::erfc(-x / std::sqrt(2.0)); };
  for (int column : {12, 16, 19, 20, 24, 27}) {
    EXPECT_NEAR(ramp[0][3][column].item<double>(), 255 * normal_cdf((column - 19.5) / 4.0), 1.5)
        << column;
  }
  EXPECT_EQ(ramp[0][3][0].item<double>(), 0.0);  // the replicated edge stays black
  EXPECT_TRUE(torch::equal(ramp[2][7], ramp[0][0]));
}

class SampleTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::MakeTempDir("samples");
    testing::WriteSequence(dir_ + "/seq", {8, 32, 32, 3, true, true});
    TrainingDataOptions options;
    options.width = 32;
    options.height = 32;
    absl::StatusOr<TrainingData> data = LoadTrainingData({dir_ + "/seq"}, options);
    ASSERT_TRUE(data.ok()) << data.status();
    data_ = *std::move(data);
  }
  void TearDown() override { fs::remove_all(dir_); }

  TrainingSample Sample(SampleOptions options, int64_t index,
                        const std::vector<GeneratedFrame>& pool = {}) {
    absl::StatusOr<TrainingSample> s = BuildSample(data_, options, pool, 11, index);
    EXPECT_TRUE(s.ok()) << s.status();
    return s.ok() ? *s : TrainingSample{};
  }

  // The sample's irradiance is the one its (noisy, blurred) previous frame
  // and that frame's basecolor give.
  void ExpectIrradianceOfThePreviousFrame(const TrainingSample& s) {
    const TrainingSequence& seq = data_.sequences[0];
    absl::StatusOr<torch::Tensor> irradiance = fd::model::ComputeIrradiance(
        s.previous.unsqueeze(0), seq.basecolor[s.previous_position].unsqueeze(0));
    ASSERT_TRUE(irradiance.ok());
    absl::StatusOr<torch::Tensor> u8 = fd::model::QuantizeIrradiance(*irradiance);
    ASSERT_TRUE(u8.ok());
    EXPECT_TRUE(torch::equal(s.irradiance_u8, (*u8)[0]));
  }

  // A stage-3 pool of one random frame standing for frame 4 (its previous
  // frame 3), and options that always take it as the previous frame.
  static std::vector<GeneratedFrame> OneGeneratedFrame() {
    return {{0, 4, torch::randint(0, 255, {3, 32, 32}, torch::kLong).to(torch::kUInt8), 1, 3, 0}};
  }
  static SampleOptions GeneratedOnly() {
    SampleOptions options;
    options.stage = Stage::kSelfConditioning;
    options.generated_ratio = 1.0;
    return options;
  }

  std::string dir_;
  TrainingData data_;
};

TEST_F(SampleTest, NoiseSigmaIsUniformUpToTheMaximum) {
  SampleOptions options;
  options.stage = Stage::kControlLora;
  double lo = 1, hi = 0, sum = 0;
  for (int i = 0; i < 400; ++i) {
    const double sigma = Sample(options, i).sigma;
    lo = std::min(lo, sigma);
    hi = std::max(hi, sigma);
    sum += sigma;
  }
  EXPECT_GE(lo, 0.0);
  EXPECT_LT(hi, 0.2);
  EXPECT_LT(lo, 0.01);
  EXPECT_GT(hi, 0.19);
  EXPECT_NEAR(sum / 400, 0.1, 0.01);
}

TEST_F(SampleTest, IrradianceComesFromTheNoisyPreviousFrame) {
  SampleOptions options;
  options.stage = Stage::kControlLora;
  int checked = 0;
  for (int i = 0; checked < 5 && i < 50; ++i) {
    TrainingSample s = Sample(options, i);
    if (s.sigma < 0.05) continue;
    const TrainingSequence& seq = data_.sequences[0];
    ASSERT_EQ(s.previous_position, s.position + s.delta);
    const torch::Tensor clean = seq.final_image[s.previous_position];
    EXPECT_FALSE(torch::equal(s.previous, clean));  // noise was injected
    EXPECT_LT(
        (s.previous.to(torch::kFloat32) - clean.to(torch::kFloat32)).abs().mean().item<double>(),
        0.8 * 0.2 * 255);
    ExpectIrradianceOfThePreviousFrame(s);
    // Channel 9 of the condition encodes it.
    EXPECT_TRUE(torch::allclose(s.condition[9],
                                s.irradiance_u8[0].to(torch::kFloat32) / 255 * 2 - 1, 1e-6, 1e-6));
    ++checked;
  }
  EXPECT_EQ(checked, 5);
}

TEST_F(SampleTest, BlurredPreviousFramesAreTheGroundTruthBlurredBeforeTheNoise) {
  SampleOptions options;
  options.stage = Stage::kControlLora;
  options.max_noise_sigma = 0;  // the blur alone
  options.max_blur_sigma = 3.0;
  const TrainingSequence& seq = data_.sequences[0];
  double lo = 3, hi = 0;
  for (int i = 0; i < 40; ++i) {
    TrainingSample s = Sample(options, i);
    lo = std::min(lo, s.blur_sigma);
    hi = std::max(hi, s.blur_sigma);
    EXPECT_TRUE(
        torch::equal(s.previous, BlurImage(seq.final_image[s.previous_position], s.blur_sigma)));
    // The irradiance follows the blurred frame, as it follows the noisy one.
    ExpectIrradianceOfThePreviousFrame(s);
  }
  EXPECT_GE(lo, 0.0);
  EXPECT_LT(lo, 0.5);
  EXPECT_GT(hi, 2.5);
  EXPECT_LT(hi, 3.0);
  // With noise the blur comes first: the same draws, so the same frame
  // positions and blur.
  options.max_noise_sigma = 0.2;
  TrainingSample noisy = Sample(options, 5);
  options.max_noise_sigma = 0;
  TrainingSample blurred = Sample(options, 5);
  EXPECT_EQ(noisy.previous_position, blurred.previous_position);
  EXPECT_EQ(noisy.blur_sigma, blurred.blur_sigma);
  // Stage 1 draws no blur, so its samples are those of a run without it.
  options.stage = Stage::kControlNet;
  SampleOptions plain = options;
  plain.max_blur_sigma = 0;
  for (int i = 0; i < 8; ++i) {
    TrainingSample a = Sample(options, i), b = Sample(plain, i);
    EXPECT_EQ(a.blur_sigma, 0.0);
    EXPECT_EQ(a.previous_position, b.previous_position);
    EXPECT_TRUE(torch::equal(a.condition, b.condition));
  }
}

TEST_F(SampleTest, StageOneIrradianceIsBlackAndHasNoPreviousFrame) {
  SampleOptions options;
  options.stage = Stage::kControlNet;
  TrainingSample s = Sample(options, 3);
  EXPECT_FALSE(s.previous.defined());
  // PIL 0 -> -1 after Normalize(0.5, 0.5): the code, not the paper's "zeros".
  EXPECT_EQ(s.condition[9].max().item<float>(), -1.0f);
  EXPECT_EQ(s.condition[9].min().item<float>(), -1.0f);
}

TEST_F(SampleTest, SkyPixelsTakeTheTargetsGroundTruth) {
  SampleOptions options;
  options.stage = Stage::kControlNet;
  TrainingSample on = Sample(options, 0);
  options.sky_injection = false;
  TrainingSample off = Sample(options, 0);
  ASSERT_EQ(on.position, off.position);
  const TrainingSequence& seq = data_.sequences[0];
  // Row 0 is sky (basecolor and depth 0) in the synthetic scene.
  const torch::Tensor gt =
      seq.final_image[on.position].slice(1, 0, 1).to(torch::kFloat32) / 255 * 2 - 1;
  EXPECT_TRUE(torch::allclose(on.condition.slice(0, 0, 3).slice(1, 0, 1), gt, 1e-6, 1e-6));
  EXPECT_EQ(off.condition.slice(0, 0, 3).slice(1, 0, 1).max().item<float>(), -1.0f);
  // Elsewhere both keep the basecolor.
  EXPECT_TRUE(torch::equal(on.condition.slice(1, 16), off.condition.slice(1, 16)));
}

TEST_F(SampleTest, SamplesDependOnlyOnTheirIndex) {
  SampleOptions options;
  options.stage = Stage::kControlLora;
  TrainingSample a = Sample(options, 17), b = Sample(options, 17), c = Sample(options, 18);
  EXPECT_TRUE(torch::equal(a.previous, b.previous));
  EXPECT_TRUE(torch::equal(a.condition, b.condition));
  EXPECT_FALSE(a.position == c.position && torch::equal(a.previous, c.previous));
  // One epoch visits every frame once.
  std::vector<int> visits(8, 0);
  for (int i = 0; i < 8; ++i) ++visits[static_cast<size_t>(Sample(options, i).position)];
  for (int v : visits) EXPECT_EQ(v, 1);
}

TEST_F(SampleTest, RecolouredSamplesReorderTheAlbedoAndRelightTheirFrames) {
  SampleOptions options;
  options.stage = Stage::kControlLora;
  options.recolour_probability = 0.5;
  const TrainingSequence& seq = data_.sequences[0];
  std::map<int, int> orders;
  const int draws = 300;
  for (int i = 0; i < draws; ++i) {
    TrainingSample s = Sample(options, i);
    ++orders[s.channel_order];
    if (i >= 20 || s.channel_order == 0) continue;
    const int order = s.channel_order;
    EXPECT_TRUE(
        torch::equal(s.target, RecolourFrame(seq.final_image[s.position], seq.basecolor[s.position],
                                             seq.depth[s.position], order)));
    // The condition's basecolor is the reordered albedo (its sky pixels,
    // row 0, take the recoloured target, which keeps the sky as it is).
    const torch::Tensor basecolor = ReorderChannels(seq.basecolor[s.position], order);
    EXPECT_TRUE(torch::allclose(s.condition.slice(0, 0, 3).slice(1, 16),
                                ToSigned(basecolor).slice(1, 16), 1e-6, 1e-6));
    EXPECT_TRUE(torch::equal(s.target.slice(1, 0, 1), seq.final_image[s.position].slice(1, 0, 1)));
    // The previous frame is recoloured, then noised; its irradiance divides
    // by its reordered albedo.
    const torch::Tensor clean =
        RecolourFrame(seq.final_image[s.previous_position], seq.basecolor[s.previous_position],
                      seq.depth[s.previous_position], order);
    EXPECT_LT(
        (s.previous.to(torch::kFloat32) - clean.to(torch::kFloat32)).abs().mean().item<double>(),
        0.8 * 0.2 * 255 + 1e-6);
    absl::StatusOr<torch::Tensor> irradiance = fd::model::ComputeIrradiance(
        s.previous.unsqueeze(0),
        ReorderChannels(seq.basecolor[s.previous_position], order).unsqueeze(0));
    ASSERT_TRUE(irradiance.ok());
    absl::StatusOr<torch::Tensor> u8 = fd::model::QuantizeIrradiance(*irradiance);
    ASSERT_TRUE(u8.ok());
    EXPECT_TRUE(torch::equal(s.irradiance_u8, (*u8)[0]));
  }
  // Half the samples, spread over the five non-identity orders.
  EXPECT_NEAR(orders[0], draws / 2, 30);
  for (int order = 1; order < kChannelOrderCount; ++order) {
    EXPECT_NEAR(orders[order], draws / 10, 18) << order;
  }
  // Without recolouring the samples are those drawn before it existed.
  options.recolour_probability = 0.0;
  SampleOptions plain;
  plain.stage = Stage::kControlLora;
  for (int i = 0; i < 4; ++i) {
    TrainingSample a = Sample(options, i), b = Sample(plain, i);
    EXPECT_EQ(a.channel_order, 0);
    EXPECT_TRUE(torch::equal(a.previous, b.previous));
    EXPECT_TRUE(torch::equal(a.target, seq.final_image[a.position]));
  }
}

TEST(ReflectNormalsTest, ReflectsInThePlaneAndKeepsTheSky) {
  // Three pixels: +X, a normal in the plane x = 0, and sky (0, 0, 0).
  auto encode = [](double x, double y, double z) {
    return std::vector<double>{std::round((x * 0.5 + 0.5) * 255), std::round((y * 0.5 + 0.5) * 255),
                               std::round((z * 0.5 + 0.5) * 255)};
  };
  const std::vector<double> px = encode(1, 0, 0), in_plane = encode(0, 0.6, 0.8);
  torch::Tensor normals = torch::zeros({3, 1, 3}, torch::kUInt8);
  for (int c = 0; c < 3; ++c) {
    normals[c][0][0] = static_cast<int>(px[c]);
    normals[c][0][1] = static_cast<int>(in_plane[c]);
  }
  const torch::Tensor reflected = ReflectNormals(normals, {1, 0, 0});
  ASSERT_EQ(reflected.scalar_type(), torch::kUInt8);
  const std::vector<double> minus_x = encode(-1, 0, 0);
  for (int c = 0; c < 3; ++c) {
    // 127.5 +- 127.5 * n rounds the encoded 0 (128) to 127 or 128.
    EXPECT_NEAR(reflected[c][0][0].item<int>(), minus_x[c], 1) << c;
    EXPECT_NEAR(reflected[c][0][1].item<int>(), in_plane[c], 1) << c;
    EXPECT_EQ(reflected[c][0][2].item<int>(), 0) << c;
  }
  // Unit normals as the dataset stores them, reflected in a vertical plane
  // through (1, 1, z): x and y swap, z stays; batched [2, 3, 4, 4].
  torch::manual_seed(5);
  const torch::Tensor unit =
      torch::nn::functional::normalize(torch::randn({2, 3, 4, 4}, torch::kFloat64),
                                       torch::nn::functional::NormalizeFuncOptions().dim(1));
  const torch::Tensor batch = unit.mul(0.5).add(0.5).mul(255).round().to(torch::kUInt8);
  const double h = 1 / std::sqrt(2.0);
  const torch::Tensor swapped = ReflectNormals(batch, {h, -h, 0});
  const torch::Tensor diff =
      swapped.to(torch::kInt32) - batch.index_select(1, torch::tensor({1, 0, 2})).to(torch::kInt32);
  EXPECT_LE(diff.abs().max().item<int>(), 1);
  // Twice is the identity, within the encoding's rounding.
  const PlaneNormal tilted = {0.3, 0.4, std::sqrt(0.75)};
  const torch::Tensor twice = ReflectNormals(ReflectNormals(batch, tilted), tilted);
  EXPECT_LE((twice.to(torch::kInt32) - batch.to(torch::kInt32)).abs().max().item<int>(), 2);
}

TEST_F(SampleTest, MirroredSamplesAreTheSameSampleFlippedWithReflectedNormals) {
  SampleOptions plain;
  plain.stage = Stage::kControlLora;
  SampleOptions mirrored = plain;
  mirrored.flip_probability = 1.0;
  const double h = 1 / std::sqrt(2.0);
  mirrored.flip_plane_normal = {h, h, 0};
  const TrainingSequence& seq = data_.sequences[0];
  auto flip = [](const torch::Tensor& t) { return t.flip({-1}); };
  for (int i = 0; i < 6; ++i) {
    const TrainingSample a = Sample(plain, i), m = Sample(mirrored, i);
    EXPECT_FALSE(a.mirrored);
    ASSERT_TRUE(m.mirrored);
    ASSERT_EQ(m.position, a.position);
    ASSERT_EQ(m.previous_position, a.previous_position);
    EXPECT_TRUE(torch::equal(m.target, flip(a.target)));
    EXPECT_TRUE(torch::equal(m.previous, flip(a.previous)));  // the same injected noise
    EXPECT_TRUE(torch::equal(m.irradiance_u8, flip(a.irradiance_u8)));
    EXPECT_TRUE(torch::equal(m.condition.slice(0, 0, 3), flip(a.condition.slice(0, 0, 3))));
    EXPECT_TRUE(torch::equal(m.condition.slice(0, 6), flip(a.condition.slice(0, 6))));
    EXPECT_TRUE(torch::equal(
        m.condition.slice(0, 3, 6),
        ToSigned(ReflectNormals(flip(seq.normals[m.position]), mirrored.flip_plane_normal))));
    EXPECT_FALSE(torch::equal(m.condition.slice(0, 3, 6), flip(a.condition.slice(0, 3, 6))));
  }
  // Half of the samples at probability 0.5; stage 1 too, never stage 0.
  mirrored.flip_probability = 0.5;
  mirrored.stage = Stage::kControlNet;
  int count = 0;
  const int draws = 200;
  for (int i = 0; i < draws; ++i) count += Sample(mirrored, i).mirrored ? 1 : 0;
  EXPECT_NEAR(count, draws / 2, 25);
  mirrored.stage = Stage::kBase;
  mirrored.flip_probability = 1.0;
  for (int i = 0; i < 4; ++i) {
    const TrainingSample base = Sample(mirrored, i);
    EXPECT_FALSE(base.mirrored);
    EXPECT_TRUE(torch::equal(base.target, seq.final_image[base.position]));
  }
}

TEST_F(SampleTest, GeneratedFramesAreMirroredWithTheirTarget) {
  const std::vector<GeneratedFrame> pool = OneGeneratedFrame();
  SampleOptions options = GeneratedOnly();
  options.flip_probability = 1.0;
  options.flip_plane_normal = {0, 1, 0};
  const TrainingSequence& seq = data_.sequences[0];
  for (int i = 0; i < 6; ++i) {
    TrainingSample s = Sample(options, i, pool);
    ASSERT_TRUE(s.generated);
    ASSERT_TRUE(s.mirrored);
    EXPECT_TRUE(torch::equal(s.previous, pool[0].image.flip({-1})));
    EXPECT_TRUE(torch::equal(s.target, seq.final_image[s.position].flip({-1})));
  }
}

TEST_F(SampleTest, GeneratedFramesAreRecolouredLikeTheGroundTruth) {
  const std::vector<GeneratedFrame> pool = OneGeneratedFrame();
  SampleOptions options = GeneratedOnly();
  options.recolour_probability = 1.0;
  const TrainingSequence& seq = data_.sequences[0];
  for (int i = 0; i < 10; ++i) {
    TrainingSample s = Sample(options, i, pool);
    ASSERT_TRUE(s.generated);
    ASSERT_NE(s.channel_order, 0);
    EXPECT_TRUE(torch::equal(
        s.previous, RecolourFrame(pool[0].image, seq.basecolor[4], seq.depth[4], s.channel_order)));
    EXPECT_TRUE(
        torch::equal(s.target, RecolourFrame(seq.final_image[s.position], seq.basecolor[s.position],
                                             seq.depth[s.position], s.channel_order)));
  }
}

TEST_F(SampleTest, GeneratedFramesBecomeThePreviousFrameUnchanged) {
  const std::vector<GeneratedFrame> pool = OneGeneratedFrame();
  SampleOptions options = GeneratedOnly();
  options.max_blur_sigma = 3.0;  // the model's own frames are not blurred
  for (int i = 0; i < 20; ++i) {
    TrainingSample s = Sample(options, i, pool);
    EXPECT_TRUE(s.generated);
    EXPECT_EQ(s.sigma, 0.0);
    EXPECT_EQ(s.blur_sigma, 0.0);
    EXPECT_TRUE(torch::equal(s.previous, pool[0].image));
    EXPECT_EQ(s.previous_position, 4);
    EXPECT_LE(std::abs(s.position - 4), 2);
    EXPECT_TRUE(torch::equal(s.target, data_.sequences[0].final_image[s.position]));
  }
  options.generated_ratio = 0.0;
  EXPECT_FALSE(Sample(options, 0, pool).generated);
}

}  // namespace
}  // namespace fd::trainer
