// Model configurations read from diffusers / transformers `config.json`
// files, with the library defaults (diffusers v0.31.0, transformers 4.30) for
// every key a file leaves out:
//
//   UNet2DConditionConfig  diffusers UNet2DConditionModel
//                          (models/unets/unet_2d_condition.py) and the
//                          FrameDiffuser authors' UNet2DConditionModelEx
//                          (model.py: extra condition channels on conv_in)
//   ControlNetConfig       diffusers ControlNetModel
//                          (models/controlnets/controlnet.py) and the authors'
//                          ControlNetModelEx (9-conv G-buffer encoder)
//   AutoencoderKLConfig    diffusers AutoencoderKL
//                          (models/autoencoders/autoencoder_kl.py)
//   CLIPTextConfig         transformers CLIPTextConfig
//                          (models/clip/configuration_clip.py)
//
// The scheduler's scheduler_config.json is parsed by model/schedulers/scheduler_settings.h.
//
// Parsing follows diffusers' ConfigMixin.from_config: unknown keys (e.g.
// `_diffusers_version`, `total_parameters`) are ignored, keys listed in
// `_use_default_values` count as absent, and the non-standard JSON tokens
// `NaN`, `Infinity`, `-Infinity` that Python's json module writes are
// accepted. Configurations that use a diffusers feature this port does not
// implement (class embeddings, other block types, ...) are rejected, so a model
// never silently computes something else than the reference.
//
// Errors of every Load*/Parse* function:
//   NOT_FOUND         the file does not exist (the message names the path);
//   INVALID_ARGUMENT  malformed JSON, a value of the wrong type or out of
//                     range, inconsistent list lengths, an unknown block type
//                     (the message names the file, the key and the value);
//   UNIMPLEMENTED     a valid diffusers setting this port does not support;
//   INTERNAL          I/O errors.
// All functions are thread-safe (no shared state).
#ifndef FD_MODEL_NETWORKS_MODEL_CONFIGS_H_
#define FD_MODEL_NETWORKS_MODEL_CONFIGS_H_

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "model/checkpoint/file_source.h"

namespace fd::model {

// Fields UNet2DConditionModel and ControlNetModel share (same keys, same
// defaults = SD1.5's values except the widths). Per-block settings that
// diffusers accepts either as one value or as a per-down-block list are
// stored expanded to one entry per down block.
struct UNetCommonConfig {
  std::string class_name;  // `_class_name`; empty when absent
  int64_t in_channels = 4;
  bool flip_sin_to_cos = true;
  int64_t freq_shift = 0;
  std::vector<std::string> down_block_types = {"CrossAttnDownBlock2D", "CrossAttnDownBlock2D",
                                               "CrossAttnDownBlock2D", "DownBlock2D"};
  std::string mid_block_type = "UNetMidBlock2DCrossAttn";
  std::vector<int64_t> block_out_channels = {320, 640, 1280, 1280};
  std::vector<int64_t> layers_per_block;              // per down block (default 2)
  std::vector<bool> only_cross_attention;             // per down block (default false)
  std::vector<int64_t> cross_attention_dim;           // per down block (default 1280)
  std::vector<int64_t> transformer_layers_per_block;  // per down block (default 1)
  // As written. SD1.5 quirk: while num_attention_heads is unset this is the
  // NUMBER of heads, not the head width (see UNetLayout). Per down block.
  std::vector<int64_t> attention_head_dim;                  // default 8
  std::optional<std::vector<int64_t>> num_attention_heads;  // per down block
  int64_t downsample_padding = 1;
  double mid_block_scale_factor = 1.0;
  std::string act_fn = "silu";
  int64_t norm_num_groups = 32;
  double norm_eps = 1e-5;
  bool use_linear_projection = false;  // Linear (true) or 1x1 conv proj_in/out
  bool upcast_attention = false;
  std::string resnet_time_scale_shift = "default";

  // Heads per block after the quirk: num_attention_heads when set, else
  // attention_head_dim. One entry per down block.
  std::vector<int64_t> HeadsPerDownBlock() const;
};

// diffusers UNet2DConditionModel, also as the authors' UNet2DConditionModelEx.
struct UNet2DConditionConfig : UNetCommonConfig {
  UNet2DConditionConfig();

  std::optional<int64_t> sample_size;
  int64_t out_channels = 4;
  std::vector<std::string> up_block_types = {"UpBlock2D", "CrossAttnUpBlock2D",
                                             "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"};
  // Per UP block when given (asymmetric UNets); else the reversed down list.
  std::optional<std::vector<int64_t>> reverse_transformer_layers_per_block;
  double dropout = 0.0;
  int64_t conv_in_kernel = 3;
  int64_t conv_out_kernel = 3;
  std::optional<int64_t> time_embedding_dim;  // default 4 * block_out_channels[0]
  double resnet_out_scale_factor = 1.0;

  // UNet2DConditionModelEx: names of the extra conditions; each adds
  // in_channels channels to conv_in. Saved configs hold [] (the base config).
  std::vector<std::string> extra_condition_names;
  // The real number of conv_in input channels. FrameDiffuser's config.json
  // says in_channels 4 while its conv_in weight is [C0, 8, 3, 3] (noisy latent
  // + previous-frame latent, added by add_extra_conditions after the config
  // was saved). 0 = not known yet: the checkpoint loader fills it from the
  // weight shape (InferConvInChannels); until then InputChannels() uses
  // in_channels * (1 + extra_condition_names.size()).
  int64_t conv_in_channels = 0;
  // FrameDiffuser Server's extension (config key "basecolor_patch_channels";
  // not in diffusers or the authors' code): after the previous-frame latent,
  // conv_in also takes the condition's basecolor pixel-unshuffled to the
  // latent grid (BasecolorPatches: 3 * f * f channels for the VAE's
  // downsampling f), a path for the albedo's colours that does not go
  // through the ControlNet. 0 (the authors' layout) = no such input.
  int64_t basecolor_patch_channels = 0;

  int64_t InputChannels() const;
  // The conv_in input channels of a FrameDiffuser UNet: noisy latent +
  // previous-frame latent (2 * out_channels) + basecolor_patch_channels.
  int64_t FrameDiffuserInputChannels() const;
  // time_embedding_dim, or 4 * block_out_channels[0].
  int64_t TimeEmbedDim() const;
};

// Which conditioning encoder a ControlNet checkpoint uses.
enum class ControlNetEmbeddingKind {
  // diffusers ControlNetConditioningEmbedding: conv_in, blocks.{0..}, conv_out.
  kDiffusers,
  // The authors' ControlNetModelEx: nn.Sequential of 9 3x3 convs with SiLU
  // between (keys controlnet_cond_embedding.{0,2,...,16}).
  kFrameDiffuserEx,
};

// diffusers ControlNetModel, also as the authors' ControlNetModelEx.
struct ControlNetConfig : UNetCommonConfig {
  ControlNetConfig();

  int64_t conditioning_channels = 3;
  std::string controlnet_conditioning_channel_order = "rgb";  // rgb | bgr
  // Default (16, 32, 96, 256); ControlNetModelEx's own class default is
  // (64, 96, 256, 512), used when `_class_name` says ControlNetModelEx.
  std::vector<int64_t> conditioning_embedding_out_channels = {16, 32, 96, 256};
  bool global_pool_conditions = false;
  // ControlNetModelEx only: the G-buffer channel count (10).
  std::optional<int64_t> gbuffer_channels;

  // Channels of the condition image the embedding takes: gbuffer_channels
  // when set, else conditioning_channels.
  int64_t ConditionChannels() const;
};

// The embedding kind of a ControlNet: the state-dict keys decide when given
// (`controlnet_cond_embedding.0.weight` -> Ex, `controlnet_cond_embedding.
// conv_in.weight` -> diffusers), else `_class_name` == "ControlNetModelEx".
ControlNetEmbeddingKind DetectControlNetEmbedding(const ControlNetConfig& config,
                                                  const std::vector<std::string>& keys = {});

// diffusers AutoencoderKL.
struct AutoencoderKLConfig {
  std::string class_name;
  int64_t in_channels = 3;
  int64_t out_channels = 3;
  std::vector<std::string> down_block_types = {"DownEncoderBlock2D"};
  std::vector<std::string> up_block_types = {"UpDecoderBlock2D"};
  std::vector<int64_t> block_out_channels = {64};
  int64_t layers_per_block = 1;
  std::string act_fn = "silu";
  int64_t latent_channels = 4;
  int64_t norm_num_groups = 32;
  int64_t sample_size = 32;
  // Applied by the pipeline, never by AutoencoderKL itself:
  // latent = (encode - shift_factor) * scaling_factor; decode(latent /
  // scaling_factor + shift_factor). shift_factor null (SD1.5) means 0.
  double scaling_factor = 0.18215;
  std::optional<double> shift_factor;
  std::optional<std::vector<double>> latents_mean;
  std::optional<std::vector<double>> latents_std;
  bool force_upcast = true;
  bool use_quant_conv = true;
  bool use_post_quant_conv = true;
  bool mid_block_add_attention = true;
};

// transformers CLIPTextConfig (the SD1.5 text encoder).
struct CLIPTextConfig {
  int64_t vocab_size = 49408;
  int64_t hidden_size = 512;
  int64_t intermediate_size = 2048;
  int64_t projection_dim = 512;
  int64_t num_hidden_layers = 12;
  int64_t num_attention_heads = 8;
  int64_t max_position_embeddings = 77;
  std::string hidden_act = "quick_gelu";  // quick_gelu | gelu
  double layer_norm_eps = 1e-5;
  double attention_dropout = 0.0;
  double initializer_range = 0.02;
  double initializer_factor = 1.0;
  // CLIPTextConfig's historic defaults, as in SD1.5's config. With
  // eos_token_id == 2, transformers pools at argmax(input_ids) (the real eos
  // 49407 is the largest id).
  int64_t pad_token_id = 1;
  int64_t bos_token_id = 0;
  int64_t eos_token_id = 2;

  int64_t HeadDim() const { return hidden_size / num_attention_heads; }
};

// Parsing from text; `source` names the origin in error messages (a path).
absl::StatusOr<UNet2DConditionConfig> ParseUNet2DConditionConfig(const std::string& json_text,
                                                                 const std::string& source);
absl::StatusOr<ControlNetConfig> ParseControlNetConfig(const std::string& json_text,
                                                       const std::string& source);
absl::StatusOr<AutoencoderKLConfig> ParseAutoencoderKLConfig(const std::string& json_text,
                                                             const std::string& source);
absl::StatusOr<CLIPTextConfig> ParseCLIPTextConfig(const std::string& json_text,
                                                   const std::string& source);

// Reading `path` (a config.json, from `files`) and parsing it as above.
absl::StatusOr<UNet2DConditionConfig> LoadUNet2DConditionConfig(
    const std::string& path, const FileSource& files = DiskFiles());
absl::StatusOr<ControlNetConfig> LoadControlNetConfig(const std::string& path,
                                                      const FileSource& files = DiskFiles());
absl::StatusOr<AutoencoderKLConfig> LoadAutoencoderKLConfig(const std::string& path,
                                                            const FileSource& files = DiskFiles());
absl::StatusOr<CLIPTextConfig> LoadCLIPTextConfig(const std::string& path,
                                                  const FileSource& files = DiskFiles());

// The real conv_in input channels of a UNet checkpoint from the shape of
// `conv_in.weight` ([block_out_channels[0], C, k, k]). C must be a multiple of
// config.in_channels (C = in_channels: a base SD UNet; 2 * in_channels:
// FrameDiffuser's noisy + previous-frame latent). INVALID_ARGUMENT naming the
// shape otherwise.
absl::StatusOr<int64_t> InferConvInChannels(const UNet2DConditionConfig& config,
                                            const std::vector<int64_t>& conv_in_weight_shape);

// One UNet/ControlNet block as diffusers' get_down_block / get_up_block /
// get_mid_block build it from the config.
struct UNetBlockLayout {
  std::string type;  // e.g. "CrossAttnDownBlock2D", "UNetMidBlock2DCrossAttn"
  bool has_cross_attention = false;
  int64_t in_channels = 0;
  int64_t out_channels = 0;
  int64_t prev_output_channel = 0;  // up blocks only
  int64_t num_layers = 0;           // resnets (mid block: transformer layers)
  bool add_sampler = false;         // down blocks: downsampler; up blocks: upsampler
  // Cross-attention blocks: transformer depth, heads and their width
  // (head_dim = channels / heads), and the encoder hidden size.
  int64_t transformer_layers = 1;
  int64_t num_attention_heads = 0;
  int64_t attention_head_dim = 0;
  int64_t cross_attention_dim = 0;
};

struct UNetLayout {
  int64_t time_embed_dim = 0;  // TimestepEmbedding output (4 * C0)
  std::vector<UNetBlockLayout> down_blocks;
  UNetBlockLayout mid_block;
  std::vector<UNetBlockLayout> up_blocks;  // empty for a ControlNet
};

// The block structure of a UNet / ControlNet. INVALID_ARGUMENT when the
// channel counts do not divide into the heads.
absl::StatusOr<UNetLayout> ComputeUNetLayout(const UNet2DConditionConfig& config);
absl::StatusOr<UNetLayout> ComputeControlNetLayout(const ControlNetConfig& config);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_MODEL_CONFIGS_H_
