// Training samples; see sample_builder.h.
#include "trainer/sample_builder.h"

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <utility>

#include "absl/strings/str_cat.h"
#include "model/pipeline/conditioning.h"

namespace fd::trainer {
namespace {

uint64_t SplitMix64(uint64_t x) {
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

// Weighted choice among (offset, weight) pairs (Python's random.choices).
int Choose(const std::vector<std::pair<int, double>>& candidates, SampleRandom& rng) {
  double total = 0;
  for (const auto& c : candidates) total += c.second;
  double r = rng.Uniform(0.0, total);
  for (const auto& c : candidates) {
    if (r < c.second) return c.first;
    r -= c.second;
  }
  return candidates.back().first;
}

bool UsesPrevious(Stage stage) {
  return stage == Stage::kControlLora || stage == Stage::kSelfConditioning;
}

// [3, H, W] -> [1, 3, H, W] views for the conditioning functions.
torch::Tensor One(const torch::Tensor& t) { return t.unsqueeze(0); }

// The 10-channel condition of the target frame from its (possibly
// recoloured) basecolor and ground truth, with irradiance from `previous`
// (undefined: black irradiance).
absl::Status Condition(const TrainingSequence& seq, int64_t target,
                       const torch::Tensor& target_basecolor, const torch::Tensor& target_image,
                       const torch::Tensor& previous, const torch::Tensor& previous_basecolor,
                       const SampleOptions& options, TrainingSample& sample) {
  const bool sky_injection = options.sky_injection;
  fd::model::FrameConditionInputs in;
  in.gbuffer.basecolor = One(target_basecolor);
  in.gbuffer.normals = One(seq.normals[target]);
  in.gbuffer.depth = One(seq.depth[target]);
  in.gbuffer.roughness = One(seq.roughness[target]);
  in.gbuffer.metallic = One(seq.metallic[target]);
  // GBufferDataset fills the sky from the same frame's ground truth.
  in.sky_fill = sky_injection ? fd::model::SkyFillMode::kSkyImage : fd::model::SkyFillMode::kNone;
  if (sky_injection) in.sky_image = One(target_image);
  if (previous.defined() && options.irradiance) {
    in.previous_output = One(previous);
    in.previous_basecolor = One(previous_basecolor);
  }
  absl::StatusOr<fd::model::FrameCondition> cond = fd::model::BuildFrameCondition(in);
  if (!cond.ok()) return cond.status();
  sample.condition = cond->condition[0];
  sample.irradiance_u8 = cond->irradiance_u8[0];
  return absl::OkStatus();
}

// The sample's recolouring: 0 (none) unless drawn with the options'
// probability. Draws nothing when the probability is 0, so that samples
// without recolouring stay those of runs made before it existed.
int DrawChannelOrder(const SampleOptions& options, SampleRandom& rng) {
  if (options.recolour_probability <= 0) return 0;
  if (rng.Uniform(0.0, 1.0) >= options.recolour_probability) return 0;
  return 1 + static_cast<int>(rng.engine() % (kChannelOrderCount - 1));
}

// Frame `position` of `seq` (or `image` in its place) relit for the
// sample's recolouring.
torch::Tensor Recoloured(const TrainingSequence& seq, int64_t position, const torch::Tensor& image,
                         int order) {
  return RecolourFrame(image, seq.basecolor[position], seq.depth[position], order);
}

// Whether the sample is mirrored: false unless drawn with the options'
// probability; draws nothing when it is 0 (as DrawChannelOrder).
bool DrawMirror(const SampleOptions& options, SampleRandom& rng) {
  if (options.flip_probability <= 0) return false;
  return rng.Uniform(0.0, 1.0) < options.flip_probability;
}

torch::Tensor FlipWidth(const torch::Tensor& t) { return t.flip({-1}); }

}  // namespace

const char* StageName(Stage stage) {
  switch (stage) {
    case Stage::kVae:
      return "stage0-vae";
    case Stage::kBase:
      return "stage0-base";
    case Stage::kControlNet:
      return "stage1";
    case Stage::kControlLora:
      return "stage2";
    case Stage::kSelfConditioning:
      return "stage3";
    case Stage::kDecoder:
      return "stage0-decoder";
  }
  return "?";
}

uint64_t MixSeed(uint64_t seed, uint64_t stage, uint64_t index) {
  return SplitMix64(SplitMix64(SplitMix64(seed) ^ stage) ^ index);
}

SampleRandom::SampleRandom(uint64_t seed)
    : engine(seed), torch_gen(at::make_generator<at::CPUGeneratorImpl>(SplitMix64(seed))) {}

double SampleRandom::Uniform(double lo, double hi) {
  // 53 random bits -> [0, 1), independent of the standard library's
  // distribution implementations.
  const double u = static_cast<double>(engine() >> 11) * 0x1.0p-53;
  return lo + (hi - lo) * u;
}

int SampleTemporalOffset(int64_t position, int64_t length, int max_offset, SampleRandom& rng) {
  std::vector<std::pair<int, double>> candidates;
  for (int d = -max_offset; d <= max_offset; ++d) {
    if (d == 0 || position + d < 0 || position + d >= length) continue;
    candidates.push_back({d, std::abs(d) == 1 ? 4.0 : 1.0});
  }
  candidates.push_back({0, 0.5});
  return Choose(candidates, rng);
}

int SampleGeneratedTargetOffset(int64_t position, int64_t length, int max_offset,
                                SampleRandom& rng) {
  std::vector<std::pair<int, double>> candidates;
  for (int d = -max_offset; d <= max_offset; ++d) {
    if (d == 0 || position + d < 0 || position + d >= length) continue;
    candidates.push_back({d, std::abs(d) == 1 ? 4.0 : 1.0});
  }
  // GBufferDataset.py 487: the frame itself is a candidate 20 % of the time.
  if (rng.Uniform(0.0, 1.0) < 0.2 || candidates.empty()) candidates.push_back({0, 8.0});
  return Choose(candidates, rng);
}

torch::Tensor InjectNoise(const torch::Tensor& image_u8, double sigma, at::Generator& gen) {
  torch::Tensor noise = torch::randn(image_u8.sizes(), gen) * (sigma * 255.0);
  // np.clip(img + noise, 0, 255).astype(np.uint8): truncation toward zero.
  return (image_u8.to(torch::kFloat32) + noise).clamp(0.0, 255.0).to(torch::kUInt8);
}

torch::Tensor BlurImage(const torch::Tensor& image_u8, double sigma) {
  if (sigma <= 0) return image_u8;
  namespace F = torch::nn::functional;
  const int64_t radius = static_cast<int64_t>(std::ceil(3.0 * sigma));
  torch::Tensor offsets = torch::arange(-radius, radius + 1, torch::kFloat32);
  torch::Tensor kernel = torch::exp(-offsets * offsets / (2.0 * sigma * sigma));
  kernel = kernel / kernel.sum();
  const int64_t channels = image_u8.size(0);
  torch::Tensor x = image_u8.to(torch::kFloat32).unsqueeze(0);  // [1, C, H, W]
  // Rows, then columns; each channel alone (groups = C).
  x = F::pad(x, F::PadFuncOptions({radius, radius, 0, 0}).mode(torch::kReplicate));
  x = F::conv2d(x, kernel.view({1, 1, 1, -1}).expand({channels, 1, 1, 2 * radius + 1}),
                F::Conv2dFuncOptions().groups(channels));
  x = F::pad(x, F::PadFuncOptions({0, 0, radius, radius}).mode(torch::kReplicate));
  x = F::conv2d(x, kernel.view({1, 1, -1, 1}).expand({channels, 1, 2 * radius + 1, 1}),
                F::Conv2dFuncOptions().groups(channels));
  return x[0].round().clamp(0.0, 255.0).to(torch::kUInt8);
}

torch::Tensor ReorderChannels(const torch::Tensor& image, int order) {
  if (order == 0) return image;
  const auto& o = kChannelOrders.at(static_cast<size_t>(order));
  return image.index_select(0, torch::tensor({o[0], o[1], o[2]}, torch::kLong));
}

torch::Tensor RecolourFrame(const torch::Tensor& image_u8, const torch::Tensor& basecolor_u8,
                            const torch::Tensor& depth_u8, int order) {
  if (order == 0) return image_u8;
  torch::NoGradGuard no_grad;
  const torch::Tensor albedo = basecolor_u8.to(torch::kFloat32);
  const torch::Tensor gain =
      ReorderChannels(albedo, order).div(albedo.clamp_min(kRecolourAlbedoFloor));
  const torch::Tensor relit =
      image_u8.to(torch::kFloat32).mul(gain).round().clamp(0.0, 255.0).to(torch::kUInt8);
  // The sky fill's mask (model/pipeline/conditioning.cc): [1, H, W].
  const torch::Tensor sky = (basecolor_u8 < 10).all(0, /*keepdim=*/true).logical_and(depth_u8 < 10);
  return torch::where(sky, image_u8, relit);
}

torch::Tensor SampleTimesteps(TimestepSampling sampling, int64_t num_timesteps, int64_t count,
                              at::Generator& gen) {
  if (sampling == TimestepSampling::kUniform) {
    return torch::randint(0, num_timesteps, {count}, gen, torch::kLong);
  }
  const torch::Tensor u = torch::rand({count}, gen);
  return ((1.0 - u.pow(3)) * static_cast<double>(num_timesteps))
      .floor()
      .clamp(0, num_timesteps - 1)
      .to(torch::kLong);
}

torch::Tensor DiffusionTarget(const std::string& prediction_type, const torch::Tensor& latents,
                              const torch::Tensor& noise, const torch::Tensor& alphas_cumprod) {
  if (prediction_type == "v_prediction") {
    return alphas_cumprod.sqrt() * noise - (1.0 - alphas_cumprod).sqrt() * latents;
  }
  if (prediction_type == "sample") return latents;
  return noise;
}

torch::Tensor PredictedCleanLatents(const std::string& prediction_type, const torch::Tensor& output,
                                    const torch::Tensor& noisy,
                                    const torch::Tensor& alphas_cumprod) {
  if (prediction_type == "v_prediction") {
    return alphas_cumprod.sqrt() * noisy - (1.0 - alphas_cumprod).sqrt() * output;
  }
  if (prediction_type == "sample") return output;
  return (noisy - (1.0 - alphas_cumprod).sqrt() * output) / alphas_cumprod.sqrt();
}

torch::Tensor ColourLatents(const torch::Tensor& latents) {
  return latents.slice(1, latents.size(1) - kColourLatentChannels);
}

torch::Tensor BlockColour(const torch::Tensor& frames, int64_t factor) {
  return torch::avg_pool2d(frames, {factor, factor});
}

torch::Tensor ToSigned(const torch::Tensor& image_u8) {
  return image_u8.to(torch::kFloat32).div(255.0).sub(0.5).div(0.5);
}

torch::Tensor ReflectNormals(const torch::Tensor& normals_u8, const PlaneNormal& plane) {
  const int64_t c = normals_u8.dim() - 3;  // the channel dimension
  const torch::Tensor n = normals_u8.to(torch::kFloat64).div(255.0).mul(2.0).sub(1.0);
  const torch::Tensor p =
      torch::tensor({plane[0], plane[1], plane[2]}, torch::kFloat64).view({3, 1, 1});
  const torch::Tensor reflected = n - 2.0 * (n * p).sum(c, /*keepdim=*/true) * p;
  const torch::Tensor encoded =
      reflected.mul(0.5).add(0.5).mul(255.0).round().clamp(0, 255).to(torch::kUInt8);
  const torch::Tensor sky = (normals_u8 == 0).all(c, /*keepdim=*/true);
  return torch::where(sky, normals_u8, encoded);
}

void MirrorSample(TrainingSample& sample, const torch::Tensor& target_normals_u8,
                  const PlaneNormal& plane) {
  sample.mirrored = true;
  sample.target = FlipWidth(sample.target).contiguous();
  if (sample.previous.defined()) sample.previous = FlipWidth(sample.previous).contiguous();
  if (sample.irradiance_u8.defined()) {
    sample.irradiance_u8 = FlipWidth(sample.irradiance_u8).contiguous();
  }
  if (!sample.condition.defined()) return;
  torch::Tensor condition = FlipWidth(sample.condition).contiguous();
  condition.slice(0, 3, 6).copy_(ToSigned(ReflectNormals(FlipWidth(target_normals_u8), plane)));
  sample.condition = condition;
}

absl::StatusOr<TrainingSample> BuildSample(const TrainingData& data, const SampleOptions& options,
                                           const std::vector<GeneratedFrame>& pool, uint64_t seed,
                                           int64_t index) {
  torch::NoGradGuard no_grad;
  const int64_t n = data.frame_count();
  if (n == 0) return absl::InvalidArgumentError("the dataset is empty");
  const uint64_t stage = static_cast<uint64_t>(options.stage);
  SampleRandom rng(MixSeed(seed, stage, static_cast<uint64_t>(index)));
  TrainingSample sample;

  const bool use_generated = options.stage == Stage::kSelfConditioning && !pool.empty() &&
                             rng.Uniform(0.0, 1.0) < options.generated_ratio;
  if (use_generated) {
    const GeneratedFrame& g =
        pool[static_cast<size_t>(rng.engine() % static_cast<uint64_t>(pool.size()))];
    const TrainingSequence& seq = data.sequences.at(static_cast<size_t>(g.sequence));
    const int delta = SampleGeneratedTargetOffset(g.position, seq.size(), options.max_offset, rng);
    sample.sequence = g.sequence;
    sample.position = g.position + delta;
    sample.previous_position = g.position;
    sample.delta = -delta;
    sample.generated = true;
    const int order = sample.channel_order = DrawChannelOrder(options, rng);
    sample.target = Recoloured(seq, sample.position, seq.final_image[sample.position], order);
    sample.previous = Recoloured(seq, g.position, g.image, order);
    absl::Status made = Condition(
        seq, sample.position, ReorderChannels(seq.basecolor[sample.position], order), sample.target,
        sample.previous, ReorderChannels(seq.basecolor[g.position], order), options, sample);
    if (!made.ok()) return made;
    if (DrawMirror(options, rng)) {
      MirrorSample(sample, seq.normals[sample.position], options.flip_plane_normal);
    }
    return sample;
  }

  // The epoch's shuffled order of all frames.
  const int64_t epoch = index / n;
  std::vector<int64_t> epoch_order(static_cast<size_t>(n));
  std::iota(epoch_order.begin(), epoch_order.end(), 0);
  std::mt19937_64 shuffle_engine(MixSeed(seed, stage, (1ULL << 62) + static_cast<uint64_t>(epoch)));
  std::shuffle(epoch_order.begin(), epoch_order.end(), shuffle_engine);
  int64_t flat = epoch_order[static_cast<size_t>(index % n)];
  size_t s = 0;
  while (flat >= data.sequences[s].size()) flat -= data.sequences[s++].size();
  const TrainingSequence& seq = data.sequences[s];
  sample.sequence = static_cast<int>(s);
  sample.position = flat;
  sample.previous_position = flat;
  sample.target = seq.final_image[flat];
  if (options.stage == Stage::kVae || options.stage == Stage::kDecoder ||
      options.stage == Stage::kBase) {
    return sample;
  }

  // The previous frame is drawn (and noised) in every stage, as the
  // authors' dataset does; stage 1 then ignores it (black irradiance).
  sample.delta = SampleTemporalOffset(flat, seq.size(), options.max_offset, rng);
  sample.previous_position = flat + sample.delta;
  sample.sigma = rng.Uniform(0.0, options.max_noise_sigma);
  const bool black = !UsesPrevious(options.stage);
  // Stage 1 draws no blur: its samples stay those of a run without it.
  if (!black && options.max_blur_sigma > 0) {
    sample.blur_sigma = rng.Uniform(0.0, options.max_blur_sigma);
  }
  const int order = sample.channel_order = DrawChannelOrder(options, rng);
  // Recoloured and blurred before the noise, which stays the authors' uint8
  // noise.
  torch::Tensor noisy =
      InjectNoise(BlurImage(Recoloured(seq, sample.previous_position,
                                       seq.final_image[sample.previous_position], order),
                            sample.blur_sigma),
                  sample.sigma, rng.torch_gen);
  sample.target = Recoloured(seq, flat, sample.target, order);
  if (!black) sample.previous = noisy;
  absl::Status made = Condition(
      seq, flat, ReorderChannels(seq.basecolor[flat], order), sample.target,
      black ? torch::Tensor() : noisy,
      black ? torch::Tensor() : ReorderChannels(seq.basecolor[sample.previous_position], order),
      options, sample);
  if (!made.ok()) return made;
  if (DrawMirror(options, rng)) MirrorSample(sample, seq.normals[flat], options.flip_plane_normal);
  return sample;
}

absl::StatusOr<TrainingBatch> BuildBatch(const TrainingData& data, const SampleOptions& options,
                                         const std::vector<GeneratedFrame>& pool, uint64_t seed,
                                         int64_t first_index, int batch_size) {
  TrainingBatch batch;
  batch.first_index = first_index;
  std::vector<torch::Tensor> targets, previous, conditions;
  for (int i = 0; i < batch_size; ++i) {
    absl::StatusOr<TrainingSample> sample = BuildSample(data, options, pool, seed, first_index + i);
    if (!sample.ok()) return sample.status();
    targets.push_back(sample->target);
    if (sample->previous.defined()) previous.push_back(sample->previous);
    if (sample->condition.defined()) conditions.push_back(sample->condition);
    batch.samples.push_back(*std::move(sample));
  }
  torch::NoGradGuard no_grad;
  batch.target = ToSigned(torch::stack(targets));
  if (!previous.empty()) batch.previous = ToSigned(torch::stack(previous));
  if (!conditions.empty()) batch.condition = torch::stack(conditions);
  return batch;
}

}  // namespace fd::trainer
