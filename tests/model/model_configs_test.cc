// Tests for model/model_configs.{h,cc}: every config.json of the golden sets
// parses to the values the golden READMEs state, and the computed block
// layout agrees with the weight shapes in the checkpoint beside it; defaults
// when keys are absent; error cases.
#include "model/networks/model_configs.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "model/checkpoint/safetensors.h"
#include "tests/testing/golden.h"

namespace fd::model {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

std::unique_ptr<SafetensorsFile> OpenWeights(const std::string& relative) {
  auto file = SafetensorsFile::Open(fd::testing::GoldenPath(relative));
  EXPECT_TRUE(file.ok()) << file.status();
  return file.ok() ? std::move(*file) : nullptr;
}

std::vector<int64_t> ShapeOf(const SafetensorsFile& file, const std::string& key) {
  auto info = file.Info(key);
  EXPECT_TRUE(info.ok()) << info.status();
  return info.ok() ? info->shape : std::vector<int64_t>{};
}

// Dimension `dim` of a tensor's shape; -1 when the tensor or dim is missing
// (a failure is already recorded by ShapeOf).
int64_t DimOf(const SafetensorsFile& file, const std::string& key, size_t dim) {
  const std::vector<int64_t> shape = ShapeOf(file, key);
  return dim < shape.size() ? shape[dim] : -1;
}

// Number of `<prefix>.<i>.` entries (i = 0, 1, ...) that have `suffix`.
int64_t CountIndexed(const SafetensorsFile& file, const std::string& prefix,
                     const std::string& suffix) {
  int64_t count = 0;
  while (file.Contains(prefix + "." + std::to_string(count) + "." + suffix)) ++count;
  return count;
}

// Checks a block layout (heads aside, which the weights cannot show) against
// the checkpoint: resnet counts and widths, attention widths, samplers.
void ExpectBlockMatchesWeights(const SafetensorsFile& weights, const std::string& prefix,
                               const UNetBlockLayout& block, bool is_mid) {
  SCOPED_TRACE(prefix);
  const int64_t resnets = is_mid ? block.num_layers + 1 : block.num_layers;
  EXPECT_EQ(CountIndexed(weights, prefix + ".resnets", "conv1.weight"), resnets);
  EXPECT_EQ(DimOf(weights, prefix + ".resnets.0.conv2.weight", 0), block.out_channels);
  const int64_t attentions = CountIndexed(weights, prefix + ".attentions", "proj_in.weight");
  EXPECT_EQ(attentions, block.has_cross_attention ? block.num_layers : 0);
  if (block.has_cross_attention) {
    const std::string attention = prefix + ".attentions.0.";
    EXPECT_EQ(CountIndexed(weights, attention + "transformer_blocks", "attn1.to_q.weight"),
              block.transformer_layers);
    EXPECT_EQ(ShapeOf(weights, attention + "transformer_blocks.0.attn2.to_k.weight"),
              (std::vector<int64_t>{block.out_channels, block.cross_attention_dim}));
    EXPECT_EQ(block.num_attention_heads * block.attention_head_dim, block.out_channels);
  }
  // Input width of every resnet's conv1 (diffusers' block constructors).
  const bool down = prefix.rfind("down_blocks", 0) == 0;
  for (int64_t j = 0; j < resnets; ++j) {
    int64_t expected_in = block.out_channels;
    if (is_mid) {
      expected_in = block.in_channels;
    } else if (down) {
      expected_in = j == 0 ? block.in_channels : block.out_channels;
    } else {  // up: previous output (or block input) + the skip tensor
      const int64_t skip = j == resnets - 1 ? block.in_channels : block.out_channels;
      expected_in = (j == 0 ? block.prev_output_channel : block.out_channels) + skip;
    }
    EXPECT_EQ(DimOf(weights, prefix + ".resnets." + std::to_string(j) + ".conv1.weight", 1),
              expected_in)
        << "resnet " << j;
  }
  if (!is_mid) {
    const std::string sampler =
        prefix + (down ? ".downsamplers.0.conv.weight" : ".upsamplers.0.conv.weight");
    EXPECT_EQ(weights.Contains(sampler), block.add_sampler);
  }
}

void ExpectLayoutMatchesWeights(const SafetensorsFile& weights, const UNetLayout& layout) {
  EXPECT_EQ(DimOf(weights, "time_embedding.linear_1.weight", 0), layout.time_embed_dim);
  for (size_t i = 0; i < layout.down_blocks.size(); ++i) {
    ExpectBlockMatchesWeights(weights, "down_blocks." + std::to_string(i), layout.down_blocks[i],
                              /*is_mid=*/false);
  }
  EXPECT_FALSE(weights.Contains("down_blocks." + std::to_string(layout.down_blocks.size()) +
                                ".resnets.0.conv1.weight"));
  ExpectBlockMatchesWeights(weights, "mid_block", layout.mid_block, /*is_mid=*/true);
  for (size_t i = 0; i < layout.up_blocks.size(); ++i) {
    ExpectBlockMatchesWeights(weights, "up_blocks." + std::to_string(i), layout.up_blocks[i],
                              /*is_mid=*/false);
  }
}

// ---------------------------------------------------------------------------
// Golden configs (values from ../shared/golden/README.md and
// fd_pipeline/README.md; the held-out sets share these structures).

TEST(ModelConfigsGoldenTest, ConfigAUNet) {
  auto config = LoadUNet2DConditionConfig(fd::testing::GoldenPath("A/unet/config.json"));
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->class_name, "UNet2DConditionModel");
  EXPECT_EQ(config->in_channels, 8);
  EXPECT_EQ(config->out_channels, 4);
  EXPECT_THAT(config->down_block_types, ElementsAre("CrossAttnDownBlock2D", "DownBlock2D"));
  EXPECT_THAT(config->up_block_types, ElementsAre("UpBlock2D", "CrossAttnUpBlock2D"));
  EXPECT_THAT(config->block_out_channels, ElementsAre(16, 32));
  EXPECT_THAT(config->layers_per_block, ElementsAre(1, 1));
  EXPECT_THAT(config->cross_attention_dim, ElementsAre(24, 24));
  EXPECT_THAT(config->attention_head_dim, ElementsAre(4, 4));
  EXPECT_FALSE(config->num_attention_heads.has_value());
  EXPECT_EQ(config->norm_num_groups, 8);
  EXPECT_TRUE(config->use_linear_projection);
  EXPECT_TRUE(config->flip_sin_to_cos);
  EXPECT_EQ(config->freq_shift, 0);
  EXPECT_EQ(config->act_fn, "silu");
  EXPECT_DOUBLE_EQ(config->norm_eps, 1e-5);
  EXPECT_EQ(config->mid_block_type, "UNetMidBlock2DCrossAttn");
  EXPECT_THAT(config->transformer_layers_per_block, ElementsAre(1, 1));
  EXPECT_EQ(config->InputChannels(), 8);

  auto layout = ComputeUNetLayout(*config);
  ASSERT_TRUE(layout.ok()) << layout.status();
  // SD1.5 quirk: attention_head_dim 4 = 4 heads; head width = channels / 4.
  ASSERT_EQ(layout->down_blocks.size(), 2u);
  EXPECT_EQ(layout->down_blocks[0].num_attention_heads, 4);
  EXPECT_EQ(layout->down_blocks[0].attention_head_dim, 4);
  EXPECT_EQ(layout->mid_block.num_attention_heads, 4);
  EXPECT_EQ(layout->mid_block.attention_head_dim, 8);
  EXPECT_EQ(layout->up_blocks[1].num_attention_heads, 4);
  EXPECT_EQ(layout->up_blocks[1].attention_head_dim, 4);
  EXPECT_EQ(layout->up_blocks[0].num_layers, 2);  // layers_per_block + 1
  EXPECT_EQ(layout->time_embed_dim, 64);

  auto weights = OpenWeights("A/unet/diffusion_pytorch_model.safetensors");
  ASSERT_NE(weights, nullptr);
  ExpectLayoutMatchesWeights(*weights, *layout);
  auto conv_in = InferConvInChannels(*config, ShapeOf(*weights, "conv_in.weight"));
  ASSERT_TRUE(conv_in.ok()) << conv_in.status();
  EXPECT_EQ(*conv_in, 8);
  // Linear projection: proj_in is a 2-D Linear weight.
  EXPECT_EQ(ShapeOf(*weights, "down_blocks.0.attentions.0.proj_in.weight").size(), 2u);
}

TEST(ModelConfigsGoldenTest, ConfigBUNet) {
  auto config = LoadUNet2DConditionConfig(fd::testing::GoldenPath("B/unet/config.json"));
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->in_channels, 8);
  EXPECT_EQ(config->out_channels, 4);
  EXPECT_THAT(config->down_block_types, ElementsAre("CrossAttnDownBlock2D", "CrossAttnDownBlock2D",
                                                    "CrossAttnDownBlock2D", "DownBlock2D"));
  EXPECT_THAT(config->up_block_types, ElementsAre("UpBlock2D", "CrossAttnUpBlock2D",
                                                  "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"));
  EXPECT_THAT(config->block_out_channels, ElementsAre(16, 32, 32, 32));
  EXPECT_THAT(config->layers_per_block, ElementsAre(2, 2, 2, 2));
  EXPECT_THAT(config->cross_attention_dim, ElementsAre(40, 40, 40, 40));
  EXPECT_EQ(config->norm_num_groups, 16);
  EXPECT_FALSE(config->use_linear_projection);

  auto layout = ComputeUNetLayout(*config);
  ASSERT_TRUE(layout.ok()) << layout.status();
  // attention_head_dim 8 = 8 heads: widths 16/8 = 2 and 32/8 = 4.
  EXPECT_EQ(layout->down_blocks[0].num_attention_heads, 8);
  EXPECT_EQ(layout->down_blocks[0].attention_head_dim, 2);
  EXPECT_EQ(layout->down_blocks[1].attention_head_dim, 4);
  EXPECT_FALSE(layout->down_blocks[3].has_cross_attention);
  EXPECT_FALSE(layout->down_blocks[3].add_sampler);
  EXPECT_EQ(layout->mid_block.attention_head_dim, 4);
  EXPECT_FALSE(layout->up_blocks[0].has_cross_attention);
  EXPECT_EQ(layout->up_blocks[3].out_channels, 16);
  EXPECT_EQ(layout->up_blocks[3].prev_output_channel, 32);
  EXPECT_FALSE(layout->up_blocks[3].add_sampler);

  auto weights = OpenWeights("B/unet/diffusion_pytorch_model.safetensors");
  ASSERT_NE(weights, nullptr);
  ExpectLayoutMatchesWeights(*weights, *layout);
  // 1x1 conv projection.
  EXPECT_EQ(ShapeOf(*weights, "down_blocks.0.attentions.0.proj_in.weight").size(), 4u);
}

TEST(ModelConfigsGoldenTest, FrameDiffuserUNetExHasEightChannelConvInDespiteConfig) {
  auto config =
      LoadUNet2DConditionConfig(fd::testing::GoldenPath("fd_pipeline/model/unet/config.json"));
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->class_name, "UNet2DConditionModelEx");
  EXPECT_EQ(config->in_channels, 4);  // the base config
  EXPECT_TRUE(config->extra_condition_names.empty());
  EXPECT_EQ(config->InputChannels(), 4);
  EXPECT_THAT(config->block_out_channels, ElementsAre(16, 32, 32, 32));
  EXPECT_THAT(config->cross_attention_dim, ElementsAre(32, 32, 32, 32));
  EXPECT_THAT(config->attention_head_dim, ElementsAre(8, 8, 8, 8));
  EXPECT_EQ(config->norm_num_groups, 8);
  EXPECT_FALSE(config->use_linear_projection);

  auto weights = OpenWeights("fd_pipeline/model/unet/diffusion_pytorch_model.safetensors");
  ASSERT_NE(weights, nullptr);
  auto conv_in = InferConvInChannels(*config, ShapeOf(*weights, "conv_in.weight"));
  ASSERT_TRUE(conv_in.ok()) << conv_in.status();
  EXPECT_EQ(*conv_in, 8);  // noisy latent + previous-frame latent
  config->conv_in_channels = *conv_in;
  EXPECT_EQ(config->InputChannels(), 8);

  auto layout = ComputeUNetLayout(*config);
  ASSERT_TRUE(layout.ok()) << layout.status();
  ExpectLayoutMatchesWeights(*weights, *layout);
}

TEST(ModelConfigsGoldenTest, ControlNetConfigs) {
  struct Case {
    std::string dir;
    bool is_ex;
    std::vector<int64_t> embedding_channels;
  };
  const Case cases[] = {
      {"A/controlnet", false, {8, 16, 16, 32}},
      {"A/controlnet_fd", true, {8, 16, 16, 32}},
      {"B/controlnet", false, {16, 16, 32, 32}},
      {"fd_pipeline/model/controlnet", true, {16, 32, 96, 128}},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.dir);
    auto config = LoadControlNetConfig(fd::testing::GoldenPath(c.dir + "/config.json"));
    ASSERT_TRUE(config.ok()) << config.status();
    EXPECT_EQ(config->in_channels, 4);
    EXPECT_EQ(config->conditioning_channels, 10);
    EXPECT_EQ(config->ConditionChannels(), 10);
    EXPECT_EQ(config->controlnet_conditioning_channel_order, "rgb");
    EXPECT_FALSE(config->global_pool_conditions);
    EXPECT_EQ(config->conditioning_embedding_out_channels, c.embedding_channels);
    EXPECT_EQ(config->class_name, c.is_ex ? "ControlNetModelEx" : "ControlNetModel");
    EXPECT_EQ(config->gbuffer_channels.has_value(), c.is_ex);
    const ControlNetEmbeddingKind expected_kind =
        c.is_ex ? ControlNetEmbeddingKind::kFrameDiffuserEx : ControlNetEmbeddingKind::kDiffusers;
    EXPECT_EQ(DetectControlNetEmbedding(*config), expected_kind);

    auto weights = OpenWeights(c.dir + "/diffusion_pytorch_model.safetensors");
    ASSERT_NE(weights, nullptr);
    const std::vector<std::string> keys = weights->Keys();
    EXPECT_EQ(DetectControlNetEmbedding(*config, keys), expected_kind);
    // The keys decide even when the class name is missing.
    ControlNetConfig unnamed = *config;
    unnamed.class_name.clear();
    EXPECT_EQ(DetectControlNetEmbedding(unnamed, keys), expected_kind);

    auto layout = ComputeControlNetLayout(*config);
    ASSERT_TRUE(layout.ok()) << layout.status();
    EXPECT_TRUE(layout->up_blocks.empty());
    ExpectLayoutMatchesWeights(*weights, *layout);
    // The embedding's first conv takes the condition channels.
    const std::string first_conv =
        c.is_ex ? "controlnet_cond_embedding.0.weight" : "controlnet_cond_embedding.conv_in.weight";
    EXPECT_EQ(DimOf(*weights, first_conv, 1), config->ConditionChannels());
    EXPECT_EQ(DimOf(*weights, first_conv, 0), config->conditioning_embedding_out_channels[0]);
  }
}

TEST(ModelConfigsGoldenTest, ControlNetConfigsMatchTheirUNets) {
  // FrameDiffuser's ControlNet is ControlNetModelEx.from_unet(unet): same
  // down/mid topology as the UNet of its set.
  for (const auto& [unet_dir, controlnet_dir] :
       {std::pair{"A/unet", "A/controlnet_fd"}, std::pair{"B/unet", "B/controlnet"},
        std::pair{"fd_pipeline/model/unet", "fd_pipeline/model/controlnet"}}) {
    SCOPED_TRACE(controlnet_dir);
    auto unet =
        LoadUNet2DConditionConfig(fd::testing::GoldenPath(std::string(unet_dir) + "/config.json"));
    auto controlnet =
        LoadControlNetConfig(fd::testing::GoldenPath(std::string(controlnet_dir) + "/config.json"));
    ASSERT_TRUE(unet.ok()) << unet.status();
    ASSERT_TRUE(controlnet.ok()) << controlnet.status();
    EXPECT_EQ(controlnet->down_block_types, unet->down_block_types);
    EXPECT_EQ(controlnet->block_out_channels, unet->block_out_channels);
    EXPECT_EQ(controlnet->layers_per_block, unet->layers_per_block);
    EXPECT_EQ(controlnet->cross_attention_dim, unet->cross_attention_dim);
    EXPECT_EQ(controlnet->HeadsPerDownBlock(), unet->HeadsPerDownBlock());
    EXPECT_EQ(controlnet->use_linear_projection, unet->use_linear_projection);
    EXPECT_EQ(controlnet->norm_num_groups, unet->norm_num_groups);
  }
}

TEST(ModelConfigsGoldenTest, VaeConfigs) {
  struct Case {
    std::string dir;
    std::vector<int64_t> block_out_channels;
    int64_t layers_per_block;
    int64_t norm_num_groups;
  };
  const Case cases[] = {
      {"A/vae", {8, 16, 16, 16}, 1, 4},
      {"B/vae", {16, 16, 32, 32}, 2, 8},
      {"fd_pipeline/model/vae", {8, 16, 32, 32}, 1, 4},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.dir);
    auto config = LoadAutoencoderKLConfig(fd::testing::GoldenPath(c.dir + "/config.json"));
    ASSERT_TRUE(config.ok()) << config.status();
    EXPECT_EQ(config->class_name, "AutoencoderKL");
    EXPECT_EQ(config->block_out_channels, c.block_out_channels);
    EXPECT_EQ(config->layers_per_block, c.layers_per_block);
    EXPECT_EQ(config->norm_num_groups, c.norm_num_groups);
    EXPECT_EQ(config->latent_channels, 4);
    EXPECT_EQ(config->in_channels, 3);
    EXPECT_EQ(config->out_channels, 3);
    EXPECT_DOUBLE_EQ(config->scaling_factor, 0.18215);
    EXPECT_FALSE(config->shift_factor.has_value());
    EXPECT_FALSE(config->latents_mean.has_value());
    EXPECT_TRUE(config->use_quant_conv);
    EXPECT_TRUE(config->use_post_quant_conv);
    EXPECT_TRUE(config->mid_block_add_attention);
    EXPECT_EQ(config->down_block_types.size(), config->block_out_channels.size());

    auto weights = OpenWeights(c.dir + "/diffusion_pytorch_model.safetensors");
    ASSERT_NE(weights, nullptr);
    EXPECT_EQ(ShapeOf(*weights, "encoder.conv_in.weight"),
              (std::vector<int64_t>{config->block_out_channels[0], config->in_channels, 3, 3}));
    EXPECT_EQ(
        ShapeOf(*weights, "quant_conv.weight"),
        (std::vector<int64_t>{2 * config->latent_channels, 2 * config->latent_channels, 1, 1}));
    EXPECT_EQ(CountIndexed(*weights, "encoder.down_blocks.0.resnets", "conv1.weight"),
              config->layers_per_block);
    EXPECT_EQ(CountIndexed(*weights, "decoder.up_blocks.0.resnets", "conv1.weight"),
              config->layers_per_block + 1);
  }
}

TEST(ModelConfigsGoldenTest, ClipTextConfig) {
  auto config = LoadCLIPTextConfig(fd::testing::GoldenPath("clip/text_encoder/config.json"));
  ASSERT_TRUE(config.ok()) << config.status();
  // Set-independent values (clip/README.md).
  EXPECT_EQ(config->vocab_size, 49408);
  EXPECT_EQ(config->max_position_embeddings, 77);
  EXPECT_EQ(config->hidden_act, "quick_gelu");
  EXPECT_DOUBLE_EQ(config->layer_norm_eps, 1e-5);
  EXPECT_EQ(config->bos_token_id, 0);
  EXPECT_EQ(config->eos_token_id, 2);
  EXPECT_EQ(config->pad_token_id, 1);
  // Sizes against the weights.
  auto weights = OpenWeights("clip/text_encoder/model.safetensors");
  ASSERT_NE(weights, nullptr);
  EXPECT_EQ(ShapeOf(*weights, "text_model.embeddings.token_embedding.weight"),
            (std::vector<int64_t>{config->vocab_size, config->hidden_size}));
  EXPECT_EQ(ShapeOf(*weights, "text_model.embeddings.position_embedding.weight"),
            (std::vector<int64_t>{config->max_position_embeddings, config->hidden_size}));
  EXPECT_EQ(CountIndexed(*weights, "text_model.encoder.layers", "mlp.fc1.weight"),
            config->num_hidden_layers);
  EXPECT_EQ(ShapeOf(*weights, "text_model.encoder.layers.0.mlp.fc1.weight"),
            (std::vector<int64_t>{config->intermediate_size, config->hidden_size}));
  EXPECT_EQ(config->HeadDim() * config->num_attention_heads, config->hidden_size);
}

// ---------------------------------------------------------------------------
// Defaults when keys are absent.

TEST(ModelConfigsDefaultsTest, EmptyUNetConfigGetsDiffusersDefaults) {
  auto config = ParseUNet2DConditionConfig("{}", "empty.json");
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->in_channels, 4);
  EXPECT_EQ(config->out_channels, 4);
  EXPECT_THAT(config->block_out_channels, ElementsAre(320, 640, 1280, 1280));
  EXPECT_THAT(config->layers_per_block, ElementsAre(2, 2, 2, 2));
  EXPECT_THAT(config->cross_attention_dim, ElementsAre(1280, 1280, 1280, 1280));
  EXPECT_THAT(config->attention_head_dim, ElementsAre(8, 8, 8, 8));
  EXPECT_EQ(config->norm_num_groups, 32);
  EXPECT_DOUBLE_EQ(config->norm_eps, 1e-5);
  EXPECT_TRUE(config->flip_sin_to_cos);
  EXPECT_EQ(config->freq_shift, 0);
  EXPECT_FALSE(config->use_linear_projection);
  EXPECT_EQ(config->conv_in_kernel, 3);
  EXPECT_FALSE(config->sample_size.has_value());
  EXPECT_EQ(config->TimeEmbedDim(), 1280);
  EXPECT_EQ(config->mid_block_type, "UNetMidBlock2DCrossAttn");
}

TEST(ModelConfigsDefaultsTest, Sd15UNetLayout) {
  // SD1.5's unet/config.json (the keys that differ from the defaults).
  auto config = ParseUNet2DConditionConfig(
      R"({"_class_name": "UNet2DConditionModel", "attention_head_dim": 8,
          "cross_attention_dim": 768, "sample_size": 64})",
      "sd15.json");
  ASSERT_TRUE(config.ok()) << config.status();
  auto layout = ComputeUNetLayout(*config);
  ASSERT_TRUE(layout.ok()) << layout.status();
  ASSERT_EQ(layout->down_blocks.size(), 4u);
  EXPECT_EQ(layout->down_blocks[0].num_attention_heads, 8);
  EXPECT_EQ(layout->down_blocks[0].attention_head_dim, 40);
  EXPECT_EQ(layout->down_blocks[2].attention_head_dim, 160);
  EXPECT_EQ(layout->down_blocks[0].cross_attention_dim, 768);
  EXPECT_EQ(layout->down_blocks[1].in_channels, 320);
  EXPECT_EQ(layout->down_blocks[1].out_channels, 640);
  EXPECT_EQ(layout->mid_block.attention_head_dim, 160);
  EXPECT_EQ(layout->up_blocks[1].prev_output_channel, 1280);
  EXPECT_EQ(layout->up_blocks[1].out_channels, 1280);
  EXPECT_EQ(layout->up_blocks[1].in_channels, 640);
  EXPECT_EQ(layout->up_blocks[3].in_channels, 320);
  EXPECT_EQ(layout->up_blocks[3].num_layers, 3);
  EXPECT_EQ(layout->time_embed_dim, 1280);
}

TEST(ModelConfigsDefaultsTest, PerBlockListsAndNumAttentionHeads) {
  auto config = ParseUNet2DConditionConfig(
      R"({"block_out_channels": [32, 64], "down_block_types": ["CrossAttnDownBlock2D",
          "CrossAttnDownBlock2D"], "up_block_types": ["CrossAttnUpBlock2D", "CrossAttnUpBlock2D"],
          "attention_head_dim": [2, 4], "layers_per_block": [1, 2],
          "cross_attention_dim": [16, 24], "transformer_layers_per_block": [1, 2],
          "norm_num_groups": 8})",
      "lists.json");
  ASSERT_TRUE(config.ok()) << config.status();
  auto layout = ComputeUNetLayout(*config);
  ASSERT_TRUE(layout.ok()) << layout.status();
  EXPECT_EQ(layout->down_blocks[0].num_attention_heads, 2);
  EXPECT_EQ(layout->down_blocks[1].num_attention_heads, 4);
  EXPECT_EQ(layout->down_blocks[1].attention_head_dim, 16);
  EXPECT_EQ(layout->down_blocks[1].transformer_layers, 2);
  EXPECT_EQ(layout->mid_block.transformer_layers, 2);
  EXPECT_EQ(layout->mid_block.cross_attention_dim, 24);
  // The up path mirrors the lists.
  EXPECT_EQ(layout->up_blocks[0].num_layers, 3);
  EXPECT_EQ(layout->up_blocks[0].num_attention_heads, 4);
  EXPECT_EQ(layout->up_blocks[0].cross_attention_dim, 24);
  EXPECT_EQ(layout->up_blocks[0].transformer_layers, 2);
  EXPECT_EQ(layout->up_blocks[1].num_layers, 2);
  EXPECT_EQ(layout->up_blocks[1].attention_head_dim, 16);

  // A ControlNet may set num_attention_heads, which then wins.
  auto controlnet = ParseControlNetConfig(
      R"({"block_out_channels": [32, 64], "down_block_types": ["CrossAttnDownBlock2D",
          "DownBlock2D"], "attention_head_dim": 8, "num_attention_heads": [2, 4],
          "norm_num_groups": 8})",
      "heads.json");
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  auto controlnet_layout = ComputeControlNetLayout(*controlnet);
  ASSERT_TRUE(controlnet_layout.ok()) << controlnet_layout.status();
  EXPECT_EQ(controlnet_layout->down_blocks[0].num_attention_heads, 2);
  EXPECT_EQ(controlnet_layout->down_blocks[0].attention_head_dim, 16);
  EXPECT_EQ(controlnet_layout->mid_block.num_attention_heads, 4);
}

TEST(ModelConfigsDefaultsTest, ControlNetVaeAndClipDefaults) {
  auto controlnet = ParseControlNetConfig("{}", "c.json");
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  EXPECT_EQ(controlnet->conditioning_channels, 3);
  EXPECT_THAT(controlnet->conditioning_embedding_out_channels, ElementsAre(16, 32, 96, 256));
  EXPECT_EQ(controlnet->controlnet_conditioning_channel_order, "rgb");
  EXPECT_EQ(DetectControlNetEmbedding(*controlnet), ControlNetEmbeddingKind::kDiffusers);
  EXPECT_THAT(controlnet->layers_per_block, ElementsAre(2, 2, 2, 2));

  auto controlnet_ex = ParseControlNetConfig(R"({"_class_name": "ControlNetModelEx"})", "x.json");
  ASSERT_TRUE(controlnet_ex.ok()) << controlnet_ex.status();
  EXPECT_THAT(controlnet_ex->conditioning_embedding_out_channels, ElementsAre(64, 96, 256, 512));
  EXPECT_EQ(DetectControlNetEmbedding(*controlnet_ex), ControlNetEmbeddingKind::kFrameDiffuserEx);
  // Keys of a diffusers encoder override a misleading class name.
  EXPECT_EQ(DetectControlNetEmbedding(*controlnet_ex, {"controlnet_cond_embedding.conv_in.weight"}),
            ControlNetEmbeddingKind::kDiffusers);

  auto vae = ParseAutoencoderKLConfig("{}", "v.json");
  ASSERT_TRUE(vae.ok()) << vae.status();
  EXPECT_THAT(vae->block_out_channels, ElementsAre(64));
  EXPECT_EQ(vae->latent_channels, 4);
  EXPECT_EQ(vae->norm_num_groups, 32);
  EXPECT_DOUBLE_EQ(vae->scaling_factor, 0.18215);
  EXPECT_FALSE(vae->shift_factor.has_value());

  auto clip = ParseCLIPTextConfig("{}", "t.json");
  ASSERT_TRUE(clip.ok()) << clip.status();
  EXPECT_EQ(clip->vocab_size, 49408);
  EXPECT_EQ(clip->hidden_size, 512);
  EXPECT_EQ(clip->intermediate_size, 2048);
  EXPECT_EQ(clip->num_hidden_layers, 12);
  EXPECT_EQ(clip->num_attention_heads, 8);
  EXPECT_EQ(clip->max_position_embeddings, 77);
  EXPECT_EQ(clip->hidden_act, "quick_gelu");
  EXPECT_EQ(clip->projection_dim, 512);
  EXPECT_EQ(clip->pad_token_id, 1);
  EXPECT_EQ(clip->bos_token_id, 0);
  EXPECT_EQ(clip->eos_token_id, 2);
}

TEST(ModelConfigsDefaultsTest, UseDefaultValuesKeysCountAsAbsent) {
  auto config = ParseControlNetConfig(
      R"({"global_pool_conditions": true, "conditioning_channels": 10,
          "_use_default_values": ["global_pool_conditions"]})",
      "defaults.json");
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_FALSE(config->global_pool_conditions);
  EXPECT_EQ(config->conditioning_channels, 10);
}

TEST(ModelConfigsDefaultsTest, AcceptsPythonNonFiniteTokens) {
  // Python's json writes -Infinity / NaN; a key we ignore may hold them and a
  // number field reads them.
  auto vae = ParseAutoencoderKLConfig(
      R"({"lambda_min_clipped": -Infinity, "note": "NaN and Infinity in a string",
          "latents_mean": [0.5, NaN, Infinity]})",
      "nonfinite.json");
  ASSERT_TRUE(vae.ok()) << vae.status();
  ASSERT_TRUE(vae->latents_mean.has_value());
  ASSERT_EQ(vae->latents_mean->size(), 3u);
  EXPECT_DOUBLE_EQ((*vae->latents_mean)[0], 0.5);
  EXPECT_TRUE(std::isnan((*vae->latents_mean)[1]));
  EXPECT_EQ((*vae->latents_mean)[2], std::numeric_limits<double>::infinity());
}

// ---------------------------------------------------------------------------
// Errors.

void ExpectError(const absl::Status& status, absl::StatusCode code,
                 const std::vector<std::string>& named) {
  EXPECT_EQ(status.code(), code) << status;
  for (const std::string& name : named) {
    EXPECT_THAT(std::string(status.message()), HasSubstr(name));
  }
}

TEST(ModelConfigsErrorTest, MissingFileIsNotFoundNamingThePath) {
  const std::string path = ::testing::TempDir() + "/no_such_dir/config.json";
  ExpectError(LoadUNet2DConditionConfig(path).status(), absl::StatusCode::kNotFound, {path});
  ExpectError(LoadControlNetConfig(path).status(), absl::StatusCode::kNotFound, {path});
  ExpectError(LoadAutoencoderKLConfig(path).status(), absl::StatusCode::kNotFound, {path});
  ExpectError(LoadCLIPTextConfig(path).status(), absl::StatusCode::kNotFound, {path});
}

TEST(ModelConfigsErrorTest, BadJsonNamesTheFile) {
  ExpectError(ParseUNet2DConditionConfig(R"({"in_channels": 4,)", "unet/config.json").status(),
              absl::StatusCode::kInvalidArgument, {"unet/config.json", "not valid JSON"});
  ExpectError(ParseAutoencoderKLConfig("[1, 2]", "vae/config.json").status(),
              absl::StatusCode::kInvalidArgument, {"vae/config.json", "expected an object"});
}

TEST(ModelConfigsErrorTest, WrongTypeNamesFileAndKey) {
  ExpectError(ParseUNet2DConditionConfig(R"({"in_channels": "4"})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"u.json", "in_channels", "\"4\""});
  ExpectError(
      ParseUNet2DConditionConfig(R"({"block_out_channels": [16, 3.5, 32, 32]})", "u.json").status(),
      absl::StatusCode::kInvalidArgument, {"u.json", "block_out_channels"});
  ExpectError(ParseUNet2DConditionConfig(R"({"use_linear_projection": 1})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"use_linear_projection"});
  ExpectError(ParseAutoencoderKLConfig(R"({"scaling_factor": "0.18"})", "v.json").status(),
              absl::StatusCode::kInvalidArgument, {"v.json", "scaling_factor"});
  ExpectError(ParseAutoencoderKLConfig(R"({"scaling_factor": Infinity})", "v.json").status(),
              absl::StatusCode::kInvalidArgument, {"scaling_factor"});
  ExpectError(
      ParseCLIPTextConfig(R"({"hidden_size": 30, "num_attention_heads": 4})", "t.json").status(),
      absl::StatusCode::kInvalidArgument, {"t.json", "num_attention_heads"});
  ExpectError(ParseUNet2DConditionConfig(R"({"in_channels": -4})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"in_channels", "positive"});
}

// This project's extension key: absent = the authors' layout; 3 * f * f
// channels of basecolor patches after the previous latent.
TEST(ModelConfigsDefaultsTest, BasecolorPatchChannelsWidenTheFrameDiffuserInput) {
  auto plain = ParseUNet2DConditionConfig("{}", "u.json");
  ASSERT_TRUE(plain.ok()) << plain.status();
  EXPECT_EQ(plain->basecolor_patch_channels, 0);
  EXPECT_EQ(plain->FrameDiffuserInputChannels(), 8);
  auto patched = ParseUNet2DConditionConfig(R"({"basecolor_patch_channels": 192})", "u.json");
  ASSERT_TRUE(patched.ok()) << patched.status();
  EXPECT_EQ(patched->FrameDiffuserInputChannels(), 200);
  ExpectError(ParseUNet2DConditionConfig(R"({"basecolor_patch_channels": 100})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"u.json", "basecolor_patch_channels", "100"});
  ExpectError(ParseUNet2DConditionConfig(R"({"basecolor_patch_channels": -3})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"basecolor_patch_channels"});
}

TEST(ModelConfigsErrorTest, UnknownBlockTypeNamesTheValue) {
  ExpectError(ParseUNet2DConditionConfig(
                  R"({"down_block_types": ["CrossAttnDownBlock2D", "SimpleCrossAttnDownBlock2D",
                      "DownBlock2D", "DownBlock2D"]})",
                  "u.json")
                  .status(),
              absl::StatusCode::kInvalidArgument,
              {"u.json", "down_block_types", "SimpleCrossAttnDownBlock2D"});
  ExpectError(ParseUNet2DConditionConfig(
                  R"({"up_block_types": ["UpBlock2D", "AttnUpBlock2D", "UpBlock2D", "UpBlock2D"]})",
                  "u.json")
                  .status(),
              absl::StatusCode::kInvalidArgument, {"up_block_types", "AttnUpBlock2D"});
  ExpectError(
      ParseAutoencoderKLConfig(R"({"down_block_types": ["AttnDownEncoderBlock2D"]})", "v.json")
          .status(),
      absl::StatusCode::kInvalidArgument, {"AttnDownEncoderBlock2D"});
  ExpectError(
      ParseControlNetConfig(R"({"mid_block_type": "UNetMidBlock2DSimpleCrossAttn"})", "c.json")
          .status(),
      absl::StatusCode::kInvalidArgument, {"mid_block_type", "UNetMidBlock2DSimpleCrossAttn"});
}

TEST(ModelConfigsErrorTest, InconsistentListLengths) {
  ExpectError(ParseUNet2DConditionConfig(R"({"block_out_channels": [32, 64]})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"block_out_channels", "2 entries"});
  ExpectError(ParseUNet2DConditionConfig(R"({"attention_head_dim": [8, 8]})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"attention_head_dim"});
  ExpectError(ParseUNet2DConditionConfig(R"({"up_block_types": ["UpBlock2D"]})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"up_block_types"});
  ExpectError(ParseAutoencoderKLConfig(R"({"block_out_channels": [8, 16]})", "v.json").status(),
              absl::StatusCode::kInvalidArgument, {"down_block_types"});
}

TEST(ModelConfigsErrorTest, UnsupportedDiffusersFeaturesAreUnimplemented) {
  ExpectError(ParseUNet2DConditionConfig(R"({"class_embed_type": "timestep"})", "u.json").status(),
              absl::StatusCode::kUnimplemented, {"u.json", "class_embed_type", "timestep"});
  ExpectError(
      ParseUNet2DConditionConfig(R"({"time_embedding_type": "fourier"})", "u.json").status(),
      absl::StatusCode::kUnimplemented, {"time_embedding_type", "fourier"});
  ExpectError(ParseUNet2DConditionConfig(R"({"only_cross_attention": true})", "u.json").status(),
              absl::StatusCode::kUnimplemented, {"only_cross_attention"});
  ExpectError(
      ParseUNet2DConditionConfig(R"({"addition_embed_type": "text_time"})", "u.json").status(),
      absl::StatusCode::kUnimplemented, {"addition_embed_type"});
  ExpectError(ParseAutoencoderKLConfig(R"({"act_fn": "gelu"})", "v.json").status(),
              absl::StatusCode::kUnimplemented, {"act_fn", "gelu"});
}

TEST(ModelConfigsErrorTest, WrongClassOrUNetNumAttentionHeads) {
  ExpectError(ParseUNet2DConditionConfig(R"({"_class_name": "AutoencoderKL"})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"_class_name", "AutoencoderKL"});
  // diffusers' UNet2DConditionModel refuses num_attention_heads (issue #2011).
  ExpectError(ParseUNet2DConditionConfig(R"({"num_attention_heads": 8})", "u.json").status(),
              absl::StatusCode::kInvalidArgument, {"num_attention_heads"});
  // Heads that do not divide the channels.
  auto config = ParseUNet2DConditionConfig(R"({"attention_head_dim": 7})", "u.json");
  ASSERT_TRUE(config.ok()) << config.status();
  ExpectError(ComputeUNetLayout(*config).status(), absl::StatusCode::kInvalidArgument,
              {"down_blocks.0", "320", "7"});
  // ControlNetModelEx needs exactly 4 embedding widths.
  ExpectError(ParseControlNetConfig(R"({"_class_name": "ControlNetModelEx",
                  "conditioning_embedding_out_channels": [16, 32, 96]})",
                                    "c.json")
                  .status(),
              absl::StatusCode::kInvalidArgument, {"conditioning_embedding_out_channels"});
}

TEST(ModelConfigsErrorTest, InferConvInChannelsValidatesTheShape) {
  UNet2DConditionConfig config;  // block_out_channels[0] = 320, in_channels 4
  EXPECT_EQ(*InferConvInChannels(config, {320, 4, 3, 3}), 4);
  EXPECT_EQ(*InferConvInChannels(config, {320, 8, 3, 3}), 8);
  ExpectError(InferConvInChannels(config, {320, 6, 3, 3}).status(),
              absl::StatusCode::kInvalidArgument, {"[320, 6, 3, 3]", "in_channels 4"});
  ExpectError(InferConvInChannels(config, {16, 8, 3, 3}).status(),
              absl::StatusCode::kInvalidArgument, {"[16, 8, 3, 3]"});
  ExpectError(InferConvInChannels(config, {320, 8}).status(), absl::StatusCode::kInvalidArgument,
              {"[320, 8]"});
}

}  // namespace
}  // namespace fd::model
