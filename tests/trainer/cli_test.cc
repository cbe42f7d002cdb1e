// trainer/cli.h: --help, the defaults, and a clear message for every bad
// flag (table-driven).
#include "trainer/cli.h"

#include <gtest/gtest.h>

#include "absl/strings/match.h"

namespace fd::trainer {
namespace {

std::vector<std::string> With(std::vector<std::string> extra) {
  std::vector<std::string> args = {"all", "--data", "/d", "--out", "/o"};
  args.insert(args.end(), extra.begin(), extra.end());
  return args;
}

TEST(TrainCliTest, HelpListsCommandsAndFlags) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs({"--help"});
  ASSERT_TRUE(parsed.ok());
  EXPECT_TRUE(parsed->help);
  for (const char* part :
       {"stage0", "stage3", "--data", "--resume", "--base", "--S_steps", "--no-sky-injection",
        "--device", "--selfcond_steps", "--gradient_checkpointing", "--inference_steps"}) {
    EXPECT_TRUE(absl::StrContains(Usage(), part)) << part;
  }
}

TEST(TrainCliTest, ParsesFlagsIntoOptions) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs({"stage2",
                                                      "--data",
                                                      "/a",
                                                      "--data=/b",
                                                      "--val",
                                                      "/v",
                                                      "--out",
                                                      "/o",
                                                      "--resolution",
                                                      "128x64",
                                                      "--stage2_steps",
                                                      "40",
                                                      "--stage2_lr",
                                                      "3e-4",
                                                      "--batch_size",
                                                      "2",
                                                      "--grad_accum",
                                                      "3",
                                                      "--no-sky-injection",
                                                      "--resume",
                                                      "--device",
                                                      "cuda:1",
                                                      "--threads",
                                                      "2",
                                                      "--preset",
                                                      "small",
                                                      "--seed",
                                                      "9",
                                                      "--export_dtype",
                                                      "float16",
                                                      "--gradient_checkpointing"});
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  const TrainerOptions& o = parsed->options;
  EXPECT_EQ(o.data_dirs, (std::vector<std::string>{"/a", "/b"}));
  EXPECT_EQ(o.validation_dirs, std::vector<std::string>{"/v"});
  EXPECT_EQ(o.stages, std::vector<Stage>{Stage::kControlLora});
  EXPECT_EQ(o.width, 128);
  EXPECT_EQ(o.height, 64);
  const StageSchedule& s2 = o.schedule[static_cast<int>(Stage::kControlLora)];
  EXPECT_EQ(s2.steps, 40);
  EXPECT_EQ(s2.warmup, 4);  // the default 10 % share
  EXPECT_DOUBLE_EQ(s2.lr, 3e-4);
  EXPECT_EQ(o.batch_size, 2);
  EXPECT_EQ(o.grad_accum, 3);
  EXPECT_FALSE(o.sky_injection);
  EXPECT_TRUE(o.resume);
  EXPECT_TRUE(o.device.is_cuda());
  EXPECT_EQ(o.device.index(), 1);
  EXPECT_EQ(o.threads, 2);
  EXPECT_EQ(o.preset, "small");
  EXPECT_EQ(o.seed, 9u);
  EXPECT_EQ(o.export_dtype, torch::kFloat16);
  EXPECT_TRUE(o.gradient_checkpointing);
  EXPECT_FALSE(
      ParseTrainArgs({"stage2", "--data", "/a", "--out", "/o"})->options.gradient_checkpointing);
}

TEST(TrainCliTest, ParsesTheStageOneUNetRateAndTheTimestepSampling) {
  absl::StatusOr<ParsedArgs> parsed =
      ParseTrainArgs(With({"--stage1_unet_lr", "2e-4", "--timestep_sampling", "cubic"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_DOUBLE_EQ(parsed->options.schedule[static_cast<int>(Stage::kControlNet)].unet_lr, 2e-4);
  EXPECT_EQ(parsed->options.timestep_sampling, TimestepSampling::kCubic);
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->options.schedule[static_cast<int>(Stage::kControlNet)].unet_lr, 0.0);
  EXPECT_EQ(defaults->options.timestep_sampling, TimestepSampling::kUniform);  // the authors'
}

TEST(TrainCliTest, ParsesBasecolorPatches) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs(With({"--basecolor_patches"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_TRUE(parsed->options.basecolor_patches);
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_FALSE(defaults->options.basecolor_patches);  // the authors' layout
}

TEST(TrainCliTest, ParsesTheRecolourProbability) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs(With({"--recolour_probability", "0.5"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->options.recolour_probability, 0.5);
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->options.recolour_probability, 0.0);  // the authors' samples
  absl::StatusOr<ParsedArgs> negative = ParseTrainArgs(With({"--recolour_probability", "-1"}));
  EXPECT_EQ(negative.status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(TrainCliTest, ParsesTheMaxBlurSigma) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs(With({"--max_blur_sigma", "2.5"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->options.max_blur_sigma, 2.5);
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->options.max_blur_sigma, 0.0);  // the authors' samples
  absl::StatusOr<ParsedArgs> negative = ParseTrainArgs(With({"--max_blur_sigma", "-1"}));
  EXPECT_EQ(negative.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(negative.status().message(), "--max_blur_sigma"));
}

TEST(TrainCliTest, ParsesTheFlipProbabilityAndNormalisesThePlane) {
  absl::StatusOr<ParsedArgs> parsed =
      ParseTrainArgs(With({"--flip_probability", "0.5", "--flip_plane_normal", "3,0,-4"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->options.flip_probability, 0.5);
  ASSERT_TRUE(parsed->options.flip_plane_normal.has_value());
  EXPECT_NEAR((*parsed->options.flip_plane_normal)[0], 0.6, 1e-12);
  EXPECT_EQ((*parsed->options.flip_plane_normal)[1], 0.0);
  EXPECT_NEAR((*parsed->options.flip_plane_normal)[2], -0.8, 1e-12);
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->options.flip_probability, 0.0);  // the authors' samples
  EXPECT_FALSE(defaults->options.flip_plane_normal.has_value());
  for (const char* bad : {"1,0", "0,0,0", "a,b,c", "1,0,0,0", "nan,0,0"}) {
    absl::StatusOr<ParsedArgs> refused = ParseTrainArgs(With({"--flip_plane_normal", bad}));
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << bad;
    EXPECT_TRUE(absl::StrContains(refused.status().message(), "--flip_plane_normal")) << bad;
  }
}

TEST(TrainCliTest, ParsesTheEmaDecay) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs(With({"--ema_decay", "0.9999"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->options.ema_decay, 0.9999);
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->options.ema_decay, 0.0);  // the authors': the last weights
  for (const char* bad : {"-0.5", "x"}) {
    absl::StatusOr<ParsedArgs> refused = ParseTrainArgs(With({"--ema_decay", bad}));
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << bad;
    EXPECT_TRUE(absl::StrContains(refused.status().message(), "--ema_decay")) << bad;
  }
}

TEST(TrainCliTest, ParsesTheColourLatentScale) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs(With({"--colour_latent_scale", "2.5"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->options.colour_latent_scale, 2.5);
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->options.colour_latent_scale, 0.0);  // the authors' VAE loss
  absl::StatusOr<ParsedArgs> negative = ParseTrainArgs(With({"--colour_latent_scale", "-1"}));
  EXPECT_EQ(negative.status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(TrainCliTest, ParsesTheDecoderLatentSource) {
  absl::StatusOr<ParsedArgs> parsed =
      ParseTrainArgs(With({"--decoder_latents_from", "/envs/street", "--decoder_chains", "8",
                           "--decoder_chain_frames", "32"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->options.decoder_latents_from, "/envs/street");
  EXPECT_EQ(parsed->options.decoder_chains, 8);
  EXPECT_EQ(parsed->options.decoder_chain_frames, 32);
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->options.decoder_latents_from, "");  // the encoder's latents
  EXPECT_EQ(defaults->options.decoder_chains, 64);
  EXPECT_EQ(defaults->options.decoder_chain_frames, 16);
  absl::StatusOr<ParsedArgs> zero = ParseTrainArgs(With({"--decoder_chain_frames", "0"}));
  EXPECT_EQ(zero.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(zero.status().message(), "--decoder_chain_frames"))
      << zero.status();
}

TEST(TrainCliTest, ParsesThePredictionTypeAndATrainedVae) {
  absl::StatusOr<ParsedArgs> parsed =
      ParseTrainArgs(With({"--prediction_type", "v_prediction", "--vae", "/envs/street"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->options.prediction_type, "v_prediction");
  EXPECT_EQ(parsed->options.vae_dir, "/envs/street");
  absl::StatusOr<ParsedArgs> defaults = ParseTrainArgs(With({}));
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->options.prediction_type, "");  // epsilon, the authors'
  EXPECT_EQ(defaults->options.vae_dir, "");
}

TEST(TrainCliTest, ParsesTheExportedInferenceSteps) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs(With({"--inference_steps", "2"}));
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->options.inference_steps, 2);
  EXPECT_EQ(ParseTrainArgs(With({}))->options.inference_steps, 10);  // the authors' UniPC count
}

TEST(TrainCliTest, CommandsSelectStages) {
  absl::StatusOr<ParsedArgs> all = ParseTrainArgs(With({}));
  ASSERT_TRUE(all.ok());
  EXPECT_TRUE(all->options.stages.empty());  // = every stage
  absl::StatusOr<ParsedArgs> zero = ParseTrainArgs({"stage0", "--data", "/d", "--out", "/o"});
  ASSERT_TRUE(zero.ok());
  // The decoder fine-tune sits between them; the trainer drops it unless
  // --decoder_steps gives it steps.
  EXPECT_EQ(zero->options.stages, (std::vector<Stage>{Stage::kVae, Stage::kDecoder, Stage::kBase}));
  EXPECT_EQ(zero->options.schedule[static_cast<int>(Stage::kDecoder)].steps, 0);
  absl::StatusOr<ParsedArgs> decoder = ParseTrainArgs(
      {"decoder", "--data", "/d", "--out", "/o", "--decoder_steps", "400", "--decoder_lr", "1e-4"});
  ASSERT_TRUE(decoder.ok()) << decoder.status();
  EXPECT_EQ(decoder->options.stages, std::vector<Stage>{Stage::kDecoder});
  const StageSchedule& sched = decoder->options.schedule[static_cast<int>(Stage::kDecoder)];
  EXPECT_EQ(sched.steps, 400);
  EXPECT_EQ(sched.warmup, 20);  // 5 % by default
  EXPECT_DOUBLE_EQ(sched.lr, 1e-4);
}

struct BadArgs {
  const char* name;
  std::vector<std::string> args;
  const char* message_part;
};

class TrainCliBadTest : public ::testing::TestWithParam<BadArgs> {};

TEST_P(TrainCliBadTest, GivesAClearMessage) {
  absl::StatusOr<ParsedArgs> parsed = ParseTrainArgs(GetParam().args);
  ASSERT_FALSE(parsed.ok());
  EXPECT_EQ(parsed.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(parsed.status().message(), GetParam().message_part))
      << parsed.status();
  EXPECT_LT(parsed.status().message().size(), 200u) << "must not echo unbounded input";
}

INSTANTIATE_TEST_SUITE_P(
    Cases, TrainCliBadTest,
    ::testing::Values(
        BadArgs{"no_command", {"--data", "/d", "--out", "/o"}, "no command"},
        BadArgs{"unknown_command", {"stage9", "--data", "/d", "--out", "/o"}, "unknown command"},
        BadArgs{"two_commands", With({"stage1"}), "one command"},
        BadArgs{"unknown_flag", With({"--learning_rate", "1"}), "unknown flag '--learning_rate'"},
        BadArgs{"missing_value", With({"--batch_size"}), "--batch_size needs a value"},
        BadArgs{"not_a_number", With({"--batch_size", "two"}), "--batch_size: expected an integer"},
        BadArgs{"zero_batch", With({"--batch_size", "0"}),
                "--batch_size: expected an integer >= 1"},
        BadArgs{"negative_lr", With({"--stage1_lr", "-1"}), "--stage1_lr: expected a number"},
        BadArgs{"bad_resolution", With({"--resolution", "100x64"}), "--resolution: expected WxH"},
        BadArgs{"bad_device", With({"--device", "tpu"}), "--device: expected cpu or cuda:N"},
        BadArgs{"bad_dtype", With({"--dtype", "float64"}), "--dtype: expected float32 or bfloat16"},
        BadArgs{"bad_preset", With({"--preset", "huge"}),
                "--preset: expected tiny, small, compact, sd15"},
        BadArgs{"bad_exr", With({"--exr_values", "srgb"}), "--exr_values"},
        BadArgs{"bad_timestep_sampling", With({"--timestep_sampling", "log"}),
                "--timestep_sampling: expected uniform or cubic"},
        BadArgs{"zero_inference_steps", With({"--inference_steps", "0"}),
                "--inference_steps: expected an integer >= 1"},
        BadArgs{"zero_unet_lr", With({"--stage1_unet_lr", "0"}), "--stage1_unet_lr"},
        BadArgs{"bad_prediction_type", With({"--prediction_type", "sample"}),
                "--prediction_type: expected epsilon or v_prediction"},
        BadArgs{"switch_with_value", With({"--resume=yes"}), "--resume takes no value"},
        BadArgs{"warmup_too_long", With({"--stage1_steps", "5", "--stage1_warmup", "9"}),
                "--stage1_warmup (9) exceeds --stage1_steps (5)"},
        BadArgs{"no_data", {"all", "--out", "/o"}, "--data is required"},
        BadArgs{"no_out", {"all", "--data", "/d"}, "--out is required"},
        BadArgs{"long_value_cut", With({"--device", std::string(5000, 'x')}), "..."}),
    [](const ::testing::TestParamInfo<BadArgs>& info) { return std::string(info.param.name); });

}  // namespace
}  // namespace fd::trainer
