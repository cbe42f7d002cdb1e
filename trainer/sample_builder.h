// One training sample as the authors' GBufferDataset.__getitem__ builds it
// (cgtuebingen/FrameDiffuser GBufferDataset.py @ b39f9af; the line numbers
// are those of ../shared/notes/training-reference.md §2):
//   * the target frame's FinalImage (what the latent diffusion learns);
//   * the previous frame at a temporal offset delta drawn with weights
//     |delta| = 1 -> 4, |delta| = 2 -> 1, delta = 0 -> 0.5 among the offsets
//     that exist in the sequence (positive delta = a future frame; offsets
//     past either end are skipped, never wrapped) (_get_temporal_offset);
//   * noise injection on that previous frame: sigma ~ U(0, 0.2), per pixel
//     and channel N(0, (sigma * 255)^2) added in uint8 space, clipped and
//     TRUNCATED to uint8 (_add_noise_to_rgb_image); the same noisy frame
//     feeds the ControlLoRA (VAE) input and the irradiance;
//   * irradiance = luma(noisy previous) / luma(previous RAW basecolor)
//     (model/pipeline/conditioning.h), or black in stage 1 (--use_black_irradiance:
//     PIL 0, i.e. -1.0 after normalisation: the code, where the paper says
//     "zeros");
//   * sky injection: the target's basecolor pixels with basecolor and depth
//     below 10 take the target's own FinalImage (fill_black_pixels_in_
//     basecolor), unless turned off;
//   * stage 3 (self-conditioning): with probability `generated_ratio`, a
//     generated frame of frame f from the pool is the previous frame, with no
//     noise, and the target is f + delta with delta = 0 (weight 8, a
//     candidate only with probability 0.2), +-1 (4), +-2 (1)
//     (_find_target_frames_for_generated); irradiance from the generated
//     frame and frame f's raw basecolor.
//   * recolouring (this project's, not the authors'; --recolour_probability):
//     with that probability a sample's albedo channels are reordered (one of
//     the five non-identity orders of RGB) and the target and previous frames
//     are relit to match (RecolourFrame), so that a surface's colour can only
//     be learnt from its basecolor, not remembered from its shape and place.
//   * mirroring (this project's; --flip_probability): with that probability
//     a stage 1-3 sample is flipped left to right, every image of it, and
//     its world-space normals are reflected in a plane (MirrorSample): the
//     sample then shows the mirror image of its world, a layout the data
//     does not have, rendered exactly (see MirrorSample for the plane).
//
// Randomness: every draw comes from a SampleRandom seeded by (seed, stage,
// sample index), so a sample depends on nothing but its index: batches can be
// built in any order on any thread, and a resumed run sees the same samples.
//
// Thread-safety: the functions are pure; TrainingData is read-only.
#ifndef FD_TRAINER_SAMPLE_BUILDER_H_
#define FD_TRAINER_SAMPLE_BUILDER_H_

#include <ATen/core/Generator.h>
#include <torch/types.h>

#include <array>
#include <cstdint>
#include <random>
#include <vector>

#include "absl/status/statusor.h"
#include "trainer/training_data.h"

namespace fd::trainer {

// The trainer's stages: stage 0 (a: VAE, b: base UNet) makes the base model
// when no --base is given; stages 1-3 are the paper's. kDecoder (optional,
// --decoder_steps) fine-tunes the VAE's decoder with its encoder frozen: the
// latents every other stage trains on stay bitwise the same, so it can run
// before stage 0b or after stage 3 alike. The values seed the stages' random
// streams (MixSeed), so a new stage takes the next free value; kRunOrder is
// the order `all` runs them in.
enum class Stage {
  kVae = 0,
  kBase = 1,
  kControlNet = 2,
  kControlLora = 3,
  kSelfConditioning = 4,
  kDecoder = 5,
};
inline constexpr int kStageCount = 6;
inline constexpr std::array<Stage, kStageCount> kRunOrder = {
    Stage::kVae,        Stage::kDecoder,     Stage::kBase,
    Stage::kControlNet, Stage::kControlLora, Stage::kSelfConditioning};
// "stage0-vae", "stage0-base", "stage1", "stage2", "stage3", "stage0-decoder".
const char* StageName(Stage stage);

// SplitMix64 of the seed, stage and index: independent streams per sample.
uint64_t MixSeed(uint64_t seed, uint64_t stage, uint64_t index);

// The random source of one sample: a std::mt19937_64 for choices and a torch
// CPU generator for noise tensors, both seeded from MixSeed.
struct SampleRandom {
  explicit SampleRandom(uint64_t seed);
  double Uniform(double lo, double hi);
  std::mt19937_64 engine;
  at::Generator torch_gen;
};

// Offset of the "previous" frame for the frame at `position` of a sequence of
// `length` frames (weights above). Requires length > max_offset >= 1.
int SampleTemporalOffset(int64_t position, int64_t length, int max_offset, SampleRandom& rng);
// Offset of the target from a generated frame at `position` (stage 3).
int SampleGeneratedTargetOffset(int64_t position, int64_t length, int max_offset,
                                SampleRandom& rng);

// Noise injection on a uint8 [3, H, W] image (see the header comment).
torch::Tensor InjectNoise(const torch::Tensor& image_u8, double sigma, at::Generator& gen);

// A Gaussian blur of standard deviation `sigma` pixels on a uint8 [C, H, W]
// image (separable, kernel radius ceil(3 sigma), edges replicated, rounded
// back to uint8); sigma <= 0 returns the image. This project's extension
// (--max_blur_sigma): the authors only add per-pixel noise to the
// ground-truth previous frame, which leaves its shapes sharp and in place,
// while a model's own previous frame on a layout it never saw is smeared; a
// blurred one is meant to make the ControlLoRA take shapes from the G-buffer
// (on street it scored as without it: docs/EVALUATION.md, seventeenth round).
torch::Tensor BlurImage(const torch::Tensor& image_u8, double sigma);

// The six orders of RGB: kChannelOrders[0] is the identity.
inline constexpr int kChannelOrderCount = 6;
inline constexpr std::array<std::array<int64_t, 3>, kChannelOrderCount> kChannelOrders = {
    {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}}};

// `image` ([3, H, W], any dtype) with its channels in kChannelOrders[order].
torch::Tensor ReorderChannels(const torch::Tensor& image, int order);

// A frame relit for its albedo's channels reordered by kChannelOrders[order]:
// each geometry pixel's channel c is scaled by reordered albedo_c / albedo_c
// (the albedo floored at kRecolourAlbedoFloor), rounded and clamped to uint8.
// A diffuse surface's radiance is its albedo times the light, channel by
// channel, and a power-law display encoding keeps that product, so the
// scaled frame shows the same light on the new albedo (exact for diffuse
// surfaces under a pure power law; ACES's shoulder and specular highlights
// are approximated). Sky pixels (the sky fill's mask: basecolor all < 10 and
// depth < 10) stay as they are: the sky's colour is not an albedo's.
// image_u8, basecolor_u8: uint8 [3, H, W] of one frame; depth_u8 uint8
// [1, H, W]. Returns uint8 [3, H, W]; order 0 returns `image_u8`.
inline constexpr double kRecolourAlbedoFloor = 8.0;
torch::Tensor RecolourFrame(const torch::Tensor& image_u8, const torch::Tensor& basecolor_u8,
                            const torch::Tensor& depth_u8, int order);

// The unit normal of the plane a mirrored sample's world is reflected in.
using PlaneNormal = std::array<double, 3>;

// Normals images reflected in the plane through the origin with unit normal
// `plane` (n - 2 (n . plane) plane) and encoded again as the dataset encodes
// them: normals_u8 uint8 [..., 3, H, W] holds round((n * 0.5 + 0.5) * 255)
// per channel; sky pixels (0, 0, 0) stay (0, 0, 0). Returns uint8 of the same
// shape.
torch::Tensor ReflectNormals(const torch::Tensor& normals_u8, const PlaneNormal& plane);

// How the diffusion stages (base, 1-3) draw their timesteps: uniform over
// 0..T-1 (train.py 2751), or cubic (T2I-Adapter), t = (1 - u^3) T, about
// half of them above 0.87 T. A frame's layout is decided at those
// high-noise steps, where the noise-prediction loss barely sees an error in
// the clean image (its weight there is the SNR, < 0.01); a small model
// trained for minutes learns to follow its condition there only when it
// sees them often.
enum class TimestepSampling { kUniform, kCubic };

// `count` timesteps in [0, num_timesteps), int64 [count], from `gen`.
torch::Tensor SampleTimesteps(TimestepSampling sampling, int64_t num_timesteps, int64_t count,
                              at::Generator& gen);

// What the denoiser's output is regressed on for noisy latents
// sqrt(a) * latents + sqrt(1 - a) * noise, by the scheduler config's
// prediction_type (train.py's target): "epsilon" the noise, "v_prediction"
// DDPMScheduler.get_velocity's sqrt(a) * noise - sqrt(1 - a) * latents,
// "sample" the latents. `alphas_cumprod` broadcasts against the latents
// ([B, 1, 1, 1]).
torch::Tensor DiffusionTarget(const std::string& prediction_type, const torch::Tensor& latents,
                              const torch::Tensor& noise, const torch::Tensor& alphas_cumprod);

// The clean latents a denoiser output implies at noisy latents
// sqrt(a) * x0 + sqrt(1 - a) * noise (the schedulers' pred_original_sample):
// "v_prediction" sqrt(a) * noisy - sqrt(1 - a) * output, "sample" the output,
// "epsilon" (noisy - sqrt(1 - a) * output) / sqrt(a).
torch::Tensor PredictedCleanLatents(const std::string& prediction_type, const torch::Tensor& output,
                                    const torch::Tensor& noisy,
                                    const torch::Tensor& alphas_cumprod);

// --colour_latent_scale: how many of a latent's channels (its last ones) are
// tied to the block colour, and the two sides of the tie.
inline constexpr int64_t kColourLatentChannels = 3;
// The last kColourLatentChannels channels of latents [B, C, h, w].
torch::Tensor ColourLatents(const torch::Tensor& latents);
// Each factor x factor block's mean colour of frames [B, 3, H, W]:
// [B, 3, H / factor, W / factor], the latent grid of a VAE that downsamples
// by `factor`.
torch::Tensor BlockColour(const torch::Tensor& frames, int64_t factor);

// A frame the current weights generated (stage 3's pool).
struct GeneratedFrame {
  int sequence = 0;
  int64_t position = 0;  // the frame it renders
  torch::Tensor image;   // uint8 [3, H, W]
  int chain_depth = 1;   // 1 = generated from a ground-truth previous frame
  // How it was made (tests re-render it): the frame its previous frame
  // showed and the request's noise seed (validation.h MakeFrameRequest).
  int64_t previous_position = 0;
  uint64_t seed = 0;
};

struct SampleOptions {
  Stage stage = Stage::kControlNet;
  int max_offset = 2;
  double max_noise_sigma = 0.2;  // noise injection: sigma ~ U(0, max)
  // Stages 2-3: the ground-truth previous frame is blurred (BlurImage) with
  // sigma ~ U(0, max) pixels before the noise; 0: off (draws nothing, so the
  // samples of runs without it stay as they were). Generated frames are not.
  double max_blur_sigma = 0.0;
  bool sky_injection = true;
  bool irradiance = true;        // false: black irradiance in every stage
  double generated_ratio = 0.5;  // stage 3, when the pool is not empty
  // Stages 1-3: the probability that a sample is recoloured (header comment).
  double recolour_probability = 0.0;
  // Stages 1-3: the probability that a sample is mirrored (MirrorSample) in
  // the plane with unit normal flip_plane_normal.
  double flip_probability = 0.0;
  PlaneNormal flip_plane_normal = {1, 0, 0};
};

struct TrainingSample {
  int sequence = 0;
  int64_t position = 0;           // target frame
  int64_t previous_position = 0;  // the previous frame's position (generated: its frame)
  int delta = 0;                  // previous_position - position
  double sigma = 0;               // noise injection (0 for generated previous frames)
  double blur_sigma = 0;          // previous-frame blur in pixels (0: none)
  bool generated = false;
  int channel_order = 0;        // kChannelOrders index of the recolouring (0: none)
  bool mirrored = false;        // flipped left to right (MirrorSample)
  torch::Tensor target;         // uint8 [3, H, W] FinalImage of the target (recoloured)
  torch::Tensor previous;       // uint8 [3, H, W] as the ControlLoRA sees it (undefined: stage 0-1)
  torch::Tensor irradiance_u8;  // uint8 [1, H, W] (channel 9 before normalisation)
  torch::Tensor condition;      // float32 [10, H, W] in [-1, 1] (undefined: stage 0)
};

// Flips `sample` left to right: its target, previous frame, irradiance and
// condition (the last dimension), the condition's normals channels (3-5)
// replaced by the flipped `target_normals_u8` (uint8 [3, H, W], the target
// frame's raw normals) reflected in `plane`. An image flipped left to right
// is what a camera mirrored in a vertical plane sees of the world mirrored in
// that plane; the G-buffer's world-space normals follow the world, so they
// are reflected in any plane the world is mirrored in, and choosing a
// vertical plane that contains the sun's direction leaves the sun (and the
// sky around it) where it was: the mirrored world is lit as the data is, and
// every shadow and highlight of the flipped frame is the one it would cast.
// Camera-space normals: plane (1, 0, 0), the image's x axis.
void MirrorSample(TrainingSample& sample, const torch::Tensor& target_normals_u8,
                  const PlaneNormal& plane);

// Builds the sample at `index` of the stage's stream: the target is
// frames[order[index % N]] where `order` is a seeded permutation per epoch
// (index / N), as a shuffled DataLoader visits them. `pool` may be empty.
absl::StatusOr<TrainingSample> BuildSample(const TrainingData& data, const SampleOptions& options,
                                           const std::vector<GeneratedFrame>& pool, uint64_t seed,
                                           int64_t index);

// A batch of samples stacked for the networks.
struct TrainingBatch {
  std::vector<TrainingSample> samples;
  torch::Tensor target;     // float32 [B, 3, H, W] in [-1, 1]
  torch::Tensor previous;   // float32 [B, 3, H, W] in [-1, 1] (undefined: stage 0-1)
  torch::Tensor condition;  // float32 [B, 10, H, W] (undefined: stage 0)
  int64_t first_index = 0;
};

// Samples first_index .. first_index + batch_size - 1, stacked.
absl::StatusOr<TrainingBatch> BuildBatch(const TrainingData& data, const SampleOptions& options,
                                         const std::vector<GeneratedFrame>& pool, uint64_t seed,
                                         int64_t first_index, int batch_size);

// uint8 [.., 3, H, W] -> float32 in [-1, 1] (ToTensor + Normalize(0.5, 0.5)).
torch::Tensor ToSigned(const torch::Tensor& image_u8);

}  // namespace fd::trainer

#endif  // FD_TRAINER_SAMPLE_BUILDER_H_
