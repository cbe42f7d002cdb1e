// trainer/trainer.h on the tiny preset at 32x32: what each stage freezes and
// trains, that training lowers the loss, stage 3's generated frames, the
// round trip to the server's pipeline, and bitwise --resume.
#include "trainer/trainer.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "absl/strings/match.h"
#include "model/lora/lora_layers.h"
#include "model/networks/gradient_checkpoint.h"
#include "model/pipeline/conditioning.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"
#include "nlohmann/json.hpp"
#include "tests/trainer/trainer_test_util.h"
#include "trainer/decoder_latents.h"

namespace fd::trainer {
namespace {

namespace fs = std::filesystem;

class TrainerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::MakeTempDir("trainer");
    testing::WriteSequence(dir_ + "/train", {8, 32, 32, 1, true, true});
    testing::WriteSequence(dir_ + "/val", {4, 32, 32, 2, true, true});
  }
  void TearDown() override { fs::remove_all(dir_); }

  TrainerOptions Options(const std::string& out) {
    TrainerOptions o = testing::QuickOptions(dir_ + "/train", dir_ + "/" + out);
    o.validation_dirs = {dir_ + "/val"};
    return o;
  }

  std::unique_ptr<Trainer> Make(TrainerOptions options) {
    absl::StatusOr<std::unique_ptr<Trainer>> trainer = Trainer::Create(std::move(options));
    EXPECT_TRUE(trainer.ok()) << trainer.status();
    return trainer.ok() ? *std::move(trainer) : nullptr;
  }

  // Loads the trainer's output folder as the server does and expects the
  // trainer's validation renders to be bitwise what that environment renders.
  // Returns the environment; null (after a failure) when a step fails.
  static std::shared_ptr<fd::model::Environment> ExpectServedAsValidated(Trainer& t,
                                                                         const TrainerOptions& o) {
    absl::StatusOr<ValidationResult> ours = t.Validate();
    absl::StatusOr<std::shared_ptr<fd::model::Environment>> served =
        fd::model::LoadEnvironment(o.out_dir);
    absl::StatusOr<TrainingData> val = LoadTrainingData(o.validation_dirs, {o.width, o.height});
    if (!ours.ok() || !served.ok() || !val.ok()) {
      ADD_FAILURE() << ours.status() << " / " << served.status() << " / " << val.status();
      return nullptr;
    }
    absl::StatusOr<ValidationResult> theirs =
        RenderValidation(*served, val->sequences[0], o.validation_frames);
    if (!theirs.ok() || theirs->rendered.size() != ours->rendered.size()) {
      ADD_FAILURE() << theirs.status() << ": not the trainer's frame count";
      return nullptr;
    }
    for (size_t i = 0; i < ours->rendered.size(); ++i) {
      EXPECT_TRUE(torch::equal(theirs->rendered[i], ours->rendered[i])) << "frame " << i;
    }
    return *served;
  }

  std::string dir_;
};

// Every tensor the trainer could touch, by name, cloned.
std::map<std::string, torch::Tensor> Snapshot(const Trainer& t) {
  std::map<std::string, torch::Tensor> out;
  auto add = [&](const std::string& prefix, torch::nn::Module& m) {
    for (const auto& p : m.named_parameters()) out[prefix + p.key()] = p.value().detach().clone();
    int i = 0;
    for (const auto& sub : m.modules(/*include_self=*/false)) {
      if (auto* layer = dynamic_cast<fd::model::LoraAdaptable*>(sub.get())) {
        for (const fd::model::LiveLoraAdapter& a : layer->live_adapters()) {
          out[prefix + "lora." + std::to_string(i) + ".A"] = a.down.detach().clone();
          out[prefix + "lora." + std::to_string(i) + ".B"] = a.up.detach().clone();
        }
      }
      ++i;
    }
  };
  if (t.vae()) add("vae.", *t.vae());
  if (t.unet()) add("unet.", *t.unet());
  if (t.controlnet()) add("controlnet.", *t.controlnet());
  return out;
}

// Every tensor of `a` is bitwise the same-named tensor of `b`, and no more.
void ExpectSameWeights(const Trainer& a, const Trainer& b) {
  const std::map<std::string, torch::Tensor> x = Snapshot(a), y = Snapshot(b);
  ASSERT_EQ(x.size(), y.size());
  for (const auto& [name, value] : x) {
    ASSERT_TRUE(y.count(name)) << name;
    EXPECT_TRUE(torch::equal(value, y.at(name))) << name;
  }
}

// Which prefixes a stage trains (the authors' flags per stage).
bool Trains(Stage stage, const std::string& name) {
  const bool lora = absl::StrContains(name, "lora.");
  switch (stage) {
    case Stage::kVae:
      return absl::StartsWith(name, "vae.");
    case Stage::kBase:
      return absl::StartsWith(name, "unet.") && !lora;
    case Stage::kControlNet:
      return absl::StartsWith(name, "controlnet.");
    case Stage::kControlLora:
      return lora;
    case Stage::kSelfConditioning:
      return lora || absl::StartsWith(name, "controlnet.");
    case Stage::kDecoder:
      return absl::StartsWith(name, "vae.decoder.") ||
             absl::StartsWith(name, "vae.post_quant_conv.");
  }
  return false;
}

class TrainerReplicasTest : public TrainerTest, public ::testing::WithParamInterface<int> {};

TEST_P(TrainerReplicasTest, EachStageTrainsExactlyItsParameters) {
  TrainerOptions o = Options("freeze");
  o.selfcond_every = 1;
  o.replicas = GetParam();
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  for (int s = 0; s < kStageCount; ++s) {
    const Stage stage = static_cast<Stage>(s);
    absl::Status begun = t->BeginStage(stage);
    ASSERT_TRUE(begun.ok()) << StageName(stage) << ": " << begun;
    const std::map<std::string, torch::Tensor> before = Snapshot(*t);
    for (int i = 0; i < 3; ++i) {
      if (stage == Stage::kSelfConditioning && i == 1) {
        ASSERT_TRUE(t->GeneratePool().ok());
      }
      absl::StatusOr<double> loss = t->TrainStep();
      ASSERT_TRUE(loss.ok()) << loss.status();
      EXPECT_TRUE(std::isfinite(*loss));
    }
    const std::map<std::string, torch::Tensor> after = Snapshot(*t);
    int trained = 0, frozen = 0, moved = 0;
    for (const auto& [name, value] : after) {
      auto it = before.find(name);
      ASSERT_NE(it, before.end()) << name;
      const bool same = torch::equal(it->second, value);
      if (Trains(stage, name)) {
        ++trained;
        moved += same ? 0 : 1;
      } else {
        ++frozen;
        EXPECT_TRUE(same) << StageName(stage) << ": frozen " << name << " changed";
      }
    }
    EXPECT_GT(trained, 0) << StageName(stage);
    // Every trainable tensor moves (weight decay moves even zero-gradient
    // ones except exact zeros; lora_B starts at zero and gets a gradient).
    EXPECT_EQ(moved, trained) << StageName(stage);
    if (stage != Stage::kVae) {
      EXPECT_GT(frozen, 0) << StageName(stage);
    }
    ASSERT_TRUE(t->EndStage().ok()) << StageName(stage);
  }
}

INSTANTIATE_TEST_SUITE_P(Replicas, TrainerReplicasTest, ::testing::Values(1, 2));

// --pixel_loss_weight: from the same state and batch, the first base-UNet
// step's loss is the latent loss plus the weighted pixel term, its gradient
// reaches the UNet through the decoder (three steps train other weights than
// without it), and the VAE stays frozen.
TEST_F(TrainerTest, PixelLossTrainsTheDenoiserThroughTheFrozenDecoder) {
  std::map<std::string, torch::Tensor> trained[2];
  double first_loss[2] = {0, 0};
  for (int with_pixels = 0; with_pixels < 2; ++with_pixels) {
    TrainerOptions o = Options(with_pixels ? "pixels" : "latents");
    o.pixel_loss_weight = with_pixels ? 1.0 : 0.0;
    std::unique_ptr<Trainer> t = Make(o);
    ASSERT_NE(t, nullptr);
    ASSERT_TRUE(t->BeginStage(Stage::kVae).ok());
    ASSERT_TRUE(t->TrainStep().ok());
    ASSERT_TRUE(t->EndStage().ok());
    ASSERT_TRUE(t->BeginStage(Stage::kBase).ok());
    const std::map<std::string, torch::Tensor> before = Snapshot(*t);
    absl::StatusOr<double> loss = t->TrainStep();
    ASSERT_TRUE(loss.ok()) << loss.status();
    first_loss[with_pixels] = *loss;
    // Adam's first update is the gradient's sign alone; later ones see its size.
    for (int i = 0; i < 2; ++i) ASSERT_TRUE(t->TrainStep().ok());
    trained[with_pixels] = Snapshot(*t);
    for (const auto& [name, value] : trained[with_pixels]) {
      if (absl::StartsWith(name, "vae.")) {
        EXPECT_TRUE(torch::equal(before.at(name), value)) << "the VAE moved: " << name;
      }
    }
  }
  EXPECT_GT(first_loss[1], first_loss[0] + 1e-3);
  int differ = 0;
  for (const auto& [name, value] : trained[0]) {
    if (absl::StartsWith(name, "vae.")) {
      EXPECT_TRUE(torch::equal(trained[1].at(name), value)) << name;
    } else if (!torch::equal(trained[1].at(name), value)) {
      ++differ;
    }
  }
  EXPECT_GT(differ, 0);  // the pixel term's gradient moved the UNet
}

// --colour_latent_scale: the VAE's last three latent channels learn the
// block colour (scaled), which an untied VAE's do not; the folder stays an
// AutoencoderKL the server loads, records the scale, and a resume must
// agree on it.
TEST_F(TrainerTest, ColourLatentTiesTheLastChannelsToTheBlockColour) {
  absl::StatusOr<TrainingData> data = LoadTrainingData({dir_ + "/train"}, {32, 32});
  ASSERT_TRUE(data.ok()) << data.status();
  const torch::Tensor frames = ToSigned(data->sequences[0].final_image);
  constexpr double kScale = 2.0;
  double tie_error[2] = {0, 0};
  for (int tied = 0; tied < 2; ++tied) {
    TrainerOptions o = Options(tied ? "tied" : "untied");
    o.colour_latent_scale = tied ? kScale : 0.0;
    StageSchedule& vae = o.schedule[static_cast<int>(Stage::kVae)];
    vae.steps = 60;
    vae.lr = 2e-3;
    o.stages = {Stage::kVae};
    std::unique_ptr<Trainer> t = Make(o);
    ASSERT_NE(t, nullptr);
    absl::Status ran = t->Run();
    ASSERT_TRUE(ran.ok()) << ran;
    torch::NoGradGuard no_grad;
    absl::StatusOr<fd::model::AutoencoderKL> exported =
        fd::model::LoadVae(o.out_dir + "/vae", torch::kCPU, torch::kFloat32);
    ASSERT_TRUE(exported.ok()) << exported.status();
    const torch::Tensor mean = (*exported)->encode(frames).mean;
    tie_error[tied] =
        torch::mse_loss(ColourLatents(mean), kScale * BlockColour(frames, 8)).item<double>();
    std::ifstream in(o.out_dir + "/environment.json");
    const nlohmann::json vae_stage = nlohmann::json::parse(in).at("training").at("stages").at(0);
    EXPECT_EQ(vae_stage.at("stage"), "stage0-vae");
    EXPECT_EQ(vae_stage.value("colour_latent_scale", 0.0), o.colour_latent_scale);
  }
  EXPECT_LT(tie_error[1], 0.25 * tie_error[0]) << tie_error[1] << " vs " << tie_error[0];

  // A folder trained with the tie resumes only with it.
  TrainerOptions other = Options("tied");
  other.colour_latent_scale = 1.0;
  other.stages = {Stage::kBase};
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(other);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "colour_latent_scale"))
      << refused.status();
}

TEST(BlockColourTest, AveragesEachBlockAndTakesTheLastChannels) {
  const torch::Tensor frames = torch::arange(2 * 3 * 4 * 4, torch::kFloat32).view({2, 3, 4, 4});
  const torch::Tensor blocks = BlockColour(frames, 2);
  ASSERT_EQ(blocks.sizes(), (std::vector<int64_t>{2, 3, 2, 2}));
  // Block (0, 0) of channel 0: values 0, 1, 4, 5.
  EXPECT_FLOAT_EQ(blocks[0][0][0][0].item<float>(), 2.5f);
  EXPECT_TRUE(torch::equal(ColourLatents(torch::arange(7).view({1, 7, 1, 1})).flatten(),
                           torch::tensor({4, 5, 6}, torch::kLong)));
}

TEST_F(TrainerTest, ReplicasSumTheirGradientsDeterministically) {
  TrainerOptions o = Options("replicas");
  o.replicas = 2;
  o.overfit_one_batch = true;
  StageSchedule& vae = o.schedule[static_cast<int>(Stage::kVae)];
  vae.steps = 60;
  vae.warmup = 5;
  vae.lr = 3e-3;
  std::unique_ptr<Trainer> a = Make(o);
  o.out_dir = dir_ + "/replicas-again";
  std::unique_ptr<Trainer> b = Make(o);
  ASSERT_NE(a, nullptr);
  ASSERT_NE(b, nullptr);
  ASSERT_TRUE(a->BeginStage(Stage::kVae).ok());
  ASSERT_TRUE(b->BeginStage(Stage::kVae).ok());
  double first = 0, last = 0;
  for (int i = 0; i < vae.steps; ++i) {
    absl::StatusOr<double> loss = a->TrainStep();
    ASSERT_TRUE(loss.ok()) << loss.status();
    ASSERT_TRUE(b->TrainStep().ok());
    if (i == 0) first = *loss;
    last = *loss;
  }
  // The summed shard gradients descend the batch loss.
  EXPECT_LT(last, first / 3) << first << " -> " << last;
  const std::map<std::string, torch::Tensor> wa = Snapshot(*a), wb = Snapshot(*b);
  for (const auto& [name, value] : wa) EXPECT_TRUE(torch::equal(value, wb.at(name))) << name;
}

// --gradient_checkpointing reaches the UNet and ControlNet (masters and
// replicas) and changes memory and time only: every stage's losses and the
// trained weights are those of the plain run (float rounding aside).
TEST_F(TrainerTest, GradientCheckpointingTrainsLikeThePlainRun) {
  auto run = [&](bool checkpointing, std::vector<double>* losses) {
    TrainerOptions o = Options(checkpointing ? "checkpointed" : "plain");
    o.selfcond_every = 1;
    o.replicas = 2;
    o.gradient_checkpointing = checkpointing;
    std::unique_ptr<Trainer> t = Make(o);
    EXPECT_NE(t, nullptr);
    if (t == nullptr) return std::map<std::string, torch::Tensor>();
    for (int s = 0; s < kStageCount; ++s) {
      const Stage stage = static_cast<Stage>(s);
      EXPECT_TRUE(t->BeginStage(stage).ok()) << StageName(stage);
      if (stage != Stage::kVae) {
        int flagged = 0;
        std::vector<std::shared_ptr<torch::nn::Module>> nets;
        if (t->unet()) nets.push_back(t->unet().ptr());
        if (t->controlnet()) nets.push_back(t->controlnet().ptr());
        for (const std::shared_ptr<torch::nn::Module>& net : nets) {
          for (const auto& sub : net->modules(/*include_self=*/false)) {
            auto* block = dynamic_cast<fd::model::GradientCheckpointable*>(sub.get());
            if (block == nullptr) continue;
            EXPECT_EQ(block->gradient_checkpointing(), checkpointing) << StageName(stage);
            ++flagged;
          }
        }
        EXPECT_GT(flagged, 0) << StageName(stage);
      }
      for (int i = 0; i < 3; ++i) {
        if (stage == Stage::kSelfConditioning && i == 1) {
          EXPECT_TRUE(t->GeneratePool().ok());
        }
        absl::StatusOr<double> loss = t->TrainStep();
        EXPECT_TRUE(loss.ok()) << loss.status();
        losses->push_back(loss.ok() ? *loss : -1);
      }
      EXPECT_TRUE(t->EndStage().ok()) << StageName(stage);
    }
    return Snapshot(*t);
  };
  std::vector<double> plain_losses, checkpointed_losses;
  const std::map<std::string, torch::Tensor> plain = run(false, &plain_losses);
  const std::map<std::string, torch::Tensor> checkpointed = run(true, &checkpointed_losses);
  ASSERT_EQ(plain_losses.size(), checkpointed_losses.size());
  for (size_t i = 0; i < plain_losses.size(); ++i) {
    EXPECT_NEAR(plain_losses[i], checkpointed_losses[i], 1e-5 * std::abs(plain_losses[i]) + 1e-7)
        << "step " << i;
  }
  ASSERT_EQ(plain.size(), checkpointed.size());
  for (const auto& [name, value] : plain) {
    EXPECT_TRUE(torch::allclose(value, checkpointed.at(name), 1e-4, 1e-6)) << name;
  }
}

TEST_F(TrainerTest, OverfitsOneBatch) {
  // The base UNet both as the authors train it (noise) and predicting v.
  struct Case {
    Stage stage;
    std::string prediction_type;
  };
  for (const Case& c :
       {Case{Stage::kVae, ""}, Case{Stage::kBase, ""}, Case{Stage::kBase, "v_prediction"}}) {
    const std::string what = std::string(StageName(c.stage)) + " " + c.prediction_type;
    TrainerOptions o = Options(std::string("overfit-") + StageName(c.stage) + c.prediction_type);
    o.overfit_one_batch = true;
    o.prediction_type = c.prediction_type;
    StageSchedule& sched = o.schedule[static_cast<int>(c.stage)];
    sched.steps = 300;
    sched.warmup = 10;
    sched.lr = c.stage == Stage::kVae ? 3e-3 : 2e-3;
    std::unique_ptr<Trainer> t = Make(o);
    ASSERT_NE(t, nullptr);
    if (c.stage == Stage::kBase) {
      ASSERT_TRUE(t->BeginStage(Stage::kVae).ok());
      ASSERT_TRUE(t->EndStage().ok());
    }
    ASSERT_TRUE(t->BeginStage(c.stage).ok());
    double first = 0, last = 0;
    for (int i = 0; i < sched.steps; ++i) {
      absl::StatusOr<double> loss = t->TrainStep();
      ASSERT_TRUE(loss.ok()) << loss.status();
      if (i == 0) first = *loss;
      last = *loss;
    }
    EXPECT_LT(last, first / 10) << what << ": " << first << " -> " << last;
  }
}

// --prediction_type v_prediction (OverfitsOneBatch trains it): the
// scheduler config every sampler reads says so, the record names it, the
// server's environment loads it, and it is part of a checkpoint's options.
TEST_F(TrainerTest, VPredictionReachesTheSchedulerConfigAndTheServer) {
  TrainerOptions o = Options("v");
  o.prediction_type = "v_prediction";
  o.stages = {Stage::kVae, Stage::kBase};
  ASSERT_TRUE(Make(o)->Run().ok());
  std::ifstream scheduler_in(o.out_dir + "/scheduler/scheduler_config.json");
  EXPECT_EQ(nlohmann::json::parse(scheduler_in).at("prediction_type"), "v_prediction");
  std::ifstream env_in(o.out_dir + "/environment.json");
  EXPECT_EQ(nlohmann::json::parse(env_in).at("training").at("prediction_type"), "v_prediction");

  TrainerOptions epsilon = Options("v");
  epsilon.stages = {Stage::kControlNet};
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(epsilon);
  ASSERT_FALSE(refused.ok());
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "prediction_type")) << refused.status();
  TrainerOptions with_base = Options("v-base");
  with_base.base_dir = o.out_dir;
  with_base.prediction_type = "v_prediction";
  refused = Trainer::Create(with_base);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);

  // The training step regresses on v: the same networks, batch, noise and
  // timesteps give another loss than with the noise as target.
  auto first_base_loss = [&](const std::string& prediction_type) {
    TrainerOptions p = Options("v-loss-" + prediction_type);
    p.prediction_type = prediction_type;
    p.overfit_one_batch = true;
    std::unique_ptr<Trainer> t = Make(p);
    EXPECT_TRUE(t->BeginStage(Stage::kVae).ok());
    EXPECT_TRUE(t->EndStage().ok());
    EXPECT_TRUE(t->BeginStage(Stage::kBase).ok());
    absl::StatusOr<double> loss = t->TrainStep();
    EXPECT_TRUE(loss.ok()) << loss.status();
    return loss.value_or(0);
  };
  EXPECT_NE(first_base_loss("v_prediction"), first_base_loss("epsilon"));

  // Through stage 1 the server's loader reads it back.
  o.stages = {Stage::kControlNet};
  o.schedule[static_cast<int>(Stage::kControlNet)].steps = 2;
  ASSERT_TRUE(Make(o)->Run().ok());
  absl::StatusOr<std::shared_ptr<fd::model::Environment>> env =
      fd::model::LoadEnvironment(o.out_dir);
  ASSERT_TRUE(env.ok()) << env.status();
  absl::StatusOr<const fd::model::Scheduler*> sampler =
      (*env)->GetScheduler((*env)->settings.scheduler);
  ASSERT_TRUE(sampler.ok()) << sampler.status();
  EXPECT_EQ((*sampler)->settings().prediction_type, "v_prediction");
}

// --vae keeps a trained autoencoder: stage 0a is done at creation, the base
// UNet trains on its latents, the weights are bitwise the given ones and the
// record names where they came from.
TEST_F(TrainerTest, ATrainedVaeReplacesStageZeroA) {
  TrainerOptions o = Options("vae-source");
  o.latent_channels = 8;
  o.stages = {Stage::kVae};
  o.command_line = "framediffuser-train stage0 --latent_channels 8";
  ASSERT_TRUE(Make(o)->Run().ok());
  TrainerOptions reuse = Options("vae-reuse");
  reuse.vae_dir = o.out_dir;  // an environment folder: its vae/
  reuse.command_line = "framediffuser-train stage0 --vae " + o.out_dir;
  reuse.stages = {Stage::kVae, Stage::kBase};
  std::unique_ptr<Trainer> t = Make(reuse);
  ASSERT_NE(t, nullptr);
  EXPECT_TRUE(t->completed(Stage::kVae));
  absl::Status ran = t->Run();
  ASSERT_TRUE(ran.ok()) << ran;
  EXPECT_TRUE(t->completed(Stage::kBase));
  EXPECT_EQ(t->unet()->config().out_channels, 8);
  absl::StatusOr<fd::model::AutoencoderKL> source =
      fd::model::LoadVae(o.out_dir + "/vae", torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(source.ok()) << source.status();
  auto kept = t->vae()->named_parameters();
  for (const auto& p : (*source)->named_parameters()) {
    EXPECT_TRUE(torch::equal(p.value(), kept[p.key()])) << p.key();
  }
  std::ifstream in(reuse.out_dir + "/environment.json");
  const nlohmann::json training = nlohmann::json::parse(in).at("training");
  EXPECT_EQ(training.at("stages").at(0).at("stage"), "stage0-vae");
  EXPECT_EQ(training.at("stages").at(0).at("from"), o.out_dir);
  // How that VAE was trained comes along from its environment's record.
  EXPECT_EQ(training.at("stages").at(0).at("steps"),
            o.schedule[static_cast<int>(Stage::kVae)].steps);
  EXPECT_EQ(training.at("stages").at(0).at("from_commands"),
            nlohmann::json::array({o.command_line}));
  EXPECT_GT(training.at("vae_reconstruction_psnr_db").get<double>(), 0);

  // Kept again from that folder, the record still names the commands that
  // trained the autoencoder, not the ones that only passed --vae.
  TrainerOptions again = Options("vae-reuse-again");
  again.vae_dir = reuse.out_dir;
  again.command_line = "framediffuser-train stage0 --vae " + reuse.out_dir;
  again.stages = {Stage::kVae};
  ASSERT_TRUE(Make(again)->Run().ok());
  std::ifstream again_in(again.out_dir + "/environment.json");
  const nlohmann::json again_vae =
      nlohmann::json::parse(again_in).at("training").at("stages").at(0);
  EXPECT_EQ(again_vae.at("from"), reuse.out_dir);
  EXPECT_EQ(again_vae.at("from_commands"), nlohmann::json::array({o.command_line}));
  EXPECT_EQ(again_vae.at("steps"), o.schedule[static_cast<int>(Stage::kVae)].steps);

  TrainerOptions missing = Options("vae-missing");
  missing.vae_dir = dir_ + "/nowhere";
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(missing);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "--vae")) << refused.status();
  TrainerOptions both = Options("vae-both");
  both.vae_dir = o.out_dir;
  both.base_dir = o.out_dir;
  refused = Trainer::Create(both);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(TrainerTest, StageThreePreviousFramesAreTheModelsOwnRenders) {
  TrainerOptions o = Options("selfcond");
  o.stages = {Stage::kVae, Stage::kBase, Stage::kControlNet, Stage::kControlLora};
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  ASSERT_TRUE(t->Run().ok());
  ASSERT_TRUE(t->BeginStage(Stage::kSelfConditioning).ok());
  ASSERT_TRUE(t->TrainStep().ok());
  ASSERT_TRUE(t->GeneratePool().ok());
  ASSERT_EQ(t->pool().size(), 3u);
  // Re-render every pool frame with an explicit call of the server's pipeline.
  absl::StatusOr<std::shared_ptr<fd::model::Environment>> env =
      t->EnvironmentView(fd::model::SchedulerType::kDPMSolverMultistep, o.selfcond_steps);
  ASSERT_TRUE(env.ok()) << env.status();
  fd::model::FramePipeline pipeline(*env);
  for (const GeneratedFrame& g : t->pool()) {
    ASSERT_EQ(g.chain_depth, 1);
    const TrainingSequence& seq = t->data().sequences[static_cast<size_t>(g.sequence)];
    fd::model::PipelineInput request = MakeFrameRequest(
        {&seq, g.position, seq.final_image[g.previous_position], g.previous_position, g.seed});
    absl::StatusOr<std::vector<fd::model::FrameOutput>> out =
        pipeline.Render(absl::MakeConstSpan(&request, 1));
    ASSERT_TRUE(out.ok()) << out.status();
    EXPECT_TRUE(torch::equal((*out)[0].image_uint8.permute({2, 0, 1}), g.image));
    EXPECT_FALSE(torch::equal(g.image, seq.final_image[g.position]));
  }
  // The next round chains from this one: errors compound.
  ASSERT_TRUE(t->TrainStep().ok());
  ASSERT_TRUE(t->GeneratePool().ok());
  int chained = 0;
  for (const GeneratedFrame& g : t->pool()) chained += g.chain_depth == 2 ? 1 : 0;
  EXPECT_GE(chained, 1);
  // A training sample with ratio 1 uses a pool frame as its previous frame.
  SampleOptions samples;
  samples.stage = Stage::kSelfConditioning;
  samples.generated_ratio = 1.0;
  absl::StatusOr<TrainingSample> s = BuildSample(t->data(), samples, t->pool(), 0, 5);
  ASSERT_TRUE(s.ok());
  bool found = false;
  for (const GeneratedFrame& g : t->pool()) found = found || torch::equal(g.image, s->previous);
  EXPECT_TRUE(found);
}

TEST_F(TrainerTest, TheServerRendersWhatTheTrainerValidated) {
  TrainerOptions o = Options("served");
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  ASSERT_TRUE(t->Run().ok());
  for (int s = 0; s < kStageCount; ++s) EXPECT_TRUE(t->completed(static_cast<Stage>(s)));
  // The output folder is an environment folder as the server loads it.
  const std::shared_ptr<fd::model::Environment> served = ExpectServedAsValidated(*t, o);
  ASSERT_NE(served, nullptr);
  EXPECT_EQ(served->settings.width, 32);
  EXPECT_FALSE(served->lora_path.empty());
  EXPECT_TRUE(fs::exists(o.out_dir + "/train/log.jsonl"));
  EXPECT_TRUE(fs::exists(o.out_dir + "/checkpoints/LATEST"));
}

// --basecolor_patches: stage 1 widens conv_in by the 3 f^2 patch channels and
// trains them with the UNet (--stage1_unet_lr); the exported unet/config.json
// names them; the server's pipeline feeds them after the previous latent, so
// it renders what the trainer validated; a resume must repeat the flag.
TEST_F(TrainerTest, BasecolorPatchesReachTheUNetInTrainingAndServing) {
  TrainerOptions o = Options("patches");
  o.basecolor_patches = true;
  o.schedule[static_cast<int>(Stage::kControlNet)].unet_lr = 1e-3;
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  ASSERT_TRUE(t->Run().ok());
  const int64_t f = t->vae()->downsampling_factor();
  const int64_t patches = 3 * f * f;
  EXPECT_EQ(t->unet()->input_channels(), 8 + patches);
  EXPECT_GT(t->unet()->conv_in->weight.slice(1, 8).abs().max().item<double>(), 0.0)
      << "stage 1 trains the patch weights, which start at zero";
  std::ifstream config_file(o.out_dir + "/unet/config.json");
  EXPECT_EQ(nlohmann::json::parse(config_file).at("basecolor_patch_channels"), patches);

  const std::shared_ptr<fd::model::Environment> served = ExpectServedAsValidated(*t, o);
  ASSERT_NE(served, nullptr);
  EXPECT_EQ(served->unet->config().basecolor_patch_channels, patches);
  absl::StatusOr<TrainingData> val = LoadTrainingData(o.validation_dirs, {32, 32});
  ASSERT_TRUE(val.ok());

  // The UNet's extra input: the previous latent, then the frame's own basecolor patches.
  const TrainingSequence& seq = val->sequences[0];
  fd::model::PipelineInput r;
  r.basecolor = seq.basecolor[1].permute({1, 2, 0});
  r.normals = seq.normals[1].permute({1, 2, 0});
  r.depth = seq.depth[1].permute({1, 2, 0});
  r.roughness = seq.roughness[1].permute({1, 2, 0});
  r.previous_frame = seq.final_image[0].permute({1, 2, 0});
  r.previous_basecolor = seq.basecolor[0].permute({1, 2, 0});
  r.sky_image = seq.final_image[1].permute({1, 2, 0});  // the trainer's sky mode
  r.keep_intermediates = true;
  fd::model::FramePipeline pipeline(served);
  absl::StatusOr<std::vector<fd::model::FrameState>> begun = pipeline.Begin({r});
  ASSERT_TRUE(begun.ok()) << begun.status();
  const fd::model::FrameState& state = (*begun)[0];
  ASSERT_EQ(state.prev_latent.size(1), 4 + patches);
  absl::StatusOr<torch::Tensor> expected = fd::model::BasecolorPatches(state.condition, f);
  ASSERT_TRUE(expected.ok()) << expected.status();
  EXPECT_TRUE(torch::equal(state.prev_latent.slice(1, 4), *expected));

  TrainerOptions without = o;
  without.basecolor_patches = false;
  without.resume = true;
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(without);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "--basecolor_patches"))
      << refused.status();
}

TEST_F(TrainerTest, ResumeAfterAnInterruptionIsBitwiseTheUninterruptedRun) {
  TrainerOptions o = Options("whole");
  o.schedule[static_cast<int>(Stage::kSelfConditioning)].steps = 5;
  o.grad_accum = 2;
  std::unique_ptr<Trainer> whole = Make(o);
  ASSERT_NE(whole, nullptr);
  ASSERT_TRUE(whole->Run().ok());

  TrainerOptions broken = o;
  broken.out_dir = dir_ + "/broken";
  int calls = 0;
  // Stages 0a, 0a' (the decoder fine-tune), 0b, 1 and 2 ask twice each (not
  // after their last step); stop in stage 3 after step 3: the pool of the
  // round at step 2 must survive.
  broken.stop_requested = [&] { return ++calls == 5 * 2 + 3; };
  {
    std::unique_ptr<Trainer> first = Make(broken);
    ASSERT_NE(first, nullptr);
    absl::Status interrupted = first->Run();
    ASSERT_TRUE(absl::IsCancelled(interrupted)) << interrupted;
    EXPECT_EQ(first->stage(), Stage::kSelfConditioning);
    EXPECT_EQ(first->step(), 3);
  }
  // Without --resume the unfinished stage is refused.
  broken.stop_requested = nullptr;
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(broken);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "--resume")) << refused.status();
  broken.resume = true;
  std::unique_ptr<Trainer> resumed = Make(broken);
  ASSERT_NE(resumed, nullptr);
  EXPECT_EQ(resumed->step(), 3);
  EXPECT_EQ(resumed->pool().size(), 3u);
  ASSERT_TRUE(resumed->Run().ok());

  ExpectSameWeights(*whole, *resumed);
}

// --ema_decay: stage 1 ends with the moving average of its weights, computed
// here step by step (EMAModel's decay), which the export, the validation and
// the server hold; its last weights are exported to train/last-stage1/.
TEST_F(TrainerTest, TheWeightAverageIsWhatAStageExportsAndHandsOn) {
  TrainerOptions o = Options("ema");
  o.ema_decay = 0.5;
  o.stages = {Stage::kVae, Stage::kBase};
  o.schedule[static_cast<int>(Stage::kControlNet)].steps = 4;
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  ASSERT_TRUE(t->Run().ok());
  ASSERT_TRUE(t->BeginStage(Stage::kControlNet).ok());
  const std::vector<torch::Tensor> params = t->trainable();
  std::vector<torch::Tensor> expected, last;
  for (const torch::Tensor& p : params) expected.push_back(p.detach().clone());
  for (int64_t n = 1; n <= 4; ++n) {
    ASSERT_TRUE(t->TrainStep().ok());
    const double decay = n == 1 ? 0.0 : std::min(0.5, n / (9.0 + n));
    for (size_t i = 0; i < params.size(); ++i) {
      expected[i] = decay * expected[i] + (1 - decay) * params[i].detach();
    }
  }
  for (const torch::Tensor& p : params) last.push_back(p.detach().clone());
  ASSERT_TRUE(t->EndStage().ok());
  int averaged = 0;
  for (size_t i = 0; i < params.size(); ++i) {
    EXPECT_TRUE(torch::allclose(params[i], expected[i], 1e-5, 1e-7)) << "tensor " << i;
    averaged += torch::equal(params[i], last[i]) ? 0 : 1;
  }
  EXPECT_GT(averaged, 0) << "the average is the last weights";

  // The export is the average (served as validated), train/last-stage1 the last weights.
  std::shared_ptr<fd::model::Environment> served = ExpectServedAsValidated(*t, o);
  ASSERT_NE(served, nullptr);
  absl::StatusOr<std::shared_ptr<fd::model::Environment>> last_served =
      fd::model::LoadEnvironment(o.out_dir + "/train/last-stage1");
  ASSERT_TRUE(last_served.ok()) << last_served.status();
  const std::vector<torch::Tensor> exported = served->controlnet->parameters();
  const std::vector<torch::Tensor> exported_last = (*last_served)->controlnet->parameters();
  ASSERT_EQ(exported.size(), params.size());
  ASSERT_EQ(exported_last.size(), params.size());
  for (size_t i = 0; i < params.size(); ++i) {
    EXPECT_TRUE(torch::equal(exported[i].to(torch::kFloat32), params[i])) << "tensor " << i;
    EXPECT_TRUE(torch::equal(exported_last[i].to(torch::kFloat32), last[i])) << "tensor " << i;
  }
  std::ifstream in(o.out_dir + "/environment.json");
  const nlohmann::json env = nlohmann::json::parse(in);
  for (const nlohmann::json& stage : env.at("training").at("stages")) {
    EXPECT_EQ(stage.value("ema_decay", 0.0), 0.5) << stage.dump();
  }
}

// An interrupted stage resumes its average too (bitwise the uninterrupted
// run), and only with the --ema_decay it began with.
TEST_F(TrainerTest, TheWeightAverageResumesBitwiseAndOnlyWithItsDecay) {
  TrainerOptions o = Options("ema-whole");
  o.ema_decay = 0.9;
  o.stages = {Stage::kVae, Stage::kBase, Stage::kControlNet};
  o.schedule[static_cast<int>(Stage::kControlNet)].steps = 5;
  std::unique_ptr<Trainer> whole = Make(o);
  ASSERT_NE(whole, nullptr);
  ASSERT_TRUE(whole->Run().ok());

  TrainerOptions broken = o;
  broken.out_dir = dir_ + "/ema-broken";
  int calls = 0;
  // Stages 0a and 0b ask twice each; stop in stage 1 after step 2.
  broken.stop_requested = [&] { return ++calls == 2 * 2 + 2; };
  {
    std::unique_ptr<Trainer> first = Make(broken);
    ASSERT_NE(first, nullptr);
    ASSERT_TRUE(absl::IsCancelled(first->Run()));
    EXPECT_EQ(first->step(), 2);
  }
  broken.stop_requested = nullptr;
  broken.resume = true;
  for (double other : {0.0, 0.5}) {
    TrainerOptions changed = broken;
    changed.ema_decay = other;
    absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(changed);
    ASSERT_FALSE(refused.ok()) << other;
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
    EXPECT_TRUE(absl::StrContains(refused.status().message(), "--ema_decay")) << refused.status();
  }
  std::unique_ptr<Trainer> resumed = Make(broken);
  ASSERT_NE(resumed, nullptr);
  ASSERT_TRUE(resumed->Run().ok());
  ExpectSameWeights(*whole, *resumed);
  EXPECT_TRUE(fs::exists(broken.out_dir + "/train/last-stage1/controlnet"));
}

TEST_F(TrainerTest, StartsFromADiffusersBaseFolder) {
  // Stage 0's output folder has what --base reads: unet/ (4-channel
  // conv_in), vae/, scheduler/, prompt_embeds.safetensors.
  TrainerOptions o = Options("base");
  o.stages = {Stage::kVae, Stage::kBase};
  ASSERT_TRUE(Make(o)->Run().ok());
  TrainerOptions from_base = Options("from-base");
  from_base.base_dir = o.out_dir;
  from_base.stages = {Stage::kControlNet};
  std::unique_ptr<Trainer> t = Make(from_base);
  ASSERT_NE(t, nullptr);
  EXPECT_TRUE(t->completed(Stage::kVae));
  EXPECT_TRUE(t->completed(Stage::kBase));
  EXPECT_EQ(t->unet()->input_channels(), 4);
  absl::Status ran = t->Run();
  ASSERT_TRUE(ran.ok()) << ran;
  // Stage 1 kept the base UNet frozen: it is the one in --base.
  absl::StatusOr<fd::model::UNet2DConditionModel> base =
      fd::model::LoadUNet(o.out_dir + "/unet", torch::kCPU, torch::kFloat32, false);
  ASSERT_TRUE(base.ok()) << base.status();
  auto trained = t->unet()->named_parameters();
  for (const auto& p : (*base)->named_parameters()) {
    EXPECT_TRUE(torch::equal(p.value(), trained[p.key()])) << p.key();
  }
  EXPECT_TRUE(fs::exists(from_base.out_dir + "/controlnet/config.json"));
  TrainerOptions no_text = Options("no-text");
  fs::create_directories(dir_ + "/bare");
  fs::copy(o.out_dir + "/unet", dir_ + "/bare/unet");
  fs::copy(o.out_dir + "/vae", dir_ + "/bare/vae");
  fs::copy(o.out_dir + "/scheduler", dir_ + "/bare/scheduler");
  no_text.base_dir = dir_ + "/bare";
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(no_text);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "prompt_embeds")) << refused.status();
}

// The ablations' settings and the training record reach environment.json,
// and the server's loader follows them: stage 1 alone has no ControlLoRA
// and black irradiance; --no-irradiance keeps it black; --latent_channels
// widens the latent everywhere.
TEST_F(TrainerTest, AblationSettingsAndTheTrainingRecordReachEnvironmentJson) {
  TrainerOptions o = Options("ablation");
  o.latent_channels = 8;
  o.vae_crop = 16;
  o.irradiance = false;
  o.recolour_probability = 0.5;
  o.pixel_loss_weight = 0.25;
  o.flip_probability = 0.5;
  o.flip_plane_normal = std::array<double, 3>{0, 1, 0};
  o.max_blur_sigma = 1.5;
  o.inference_steps = 3;
  o.command_line = "framediffuser-train stage1 --out ablation";
  o.stages = {Stage::kVae, Stage::kBase, Stage::kControlNet};
  ASSERT_TRUE(Make(o)->Run().ok());
  auto read_json = [&] {
    std::ifstream in(o.out_dir + "/environment.json");
    return nlohmann::json::parse(in);
  };
  nlohmann::json env = read_json();
  EXPECT_EQ(env.at("controllora"), false);
  EXPECT_EQ(env.at("irradiance"), "black");
  EXPECT_EQ(env.at("steps"), 3);  // --inference_steps
  absl::StatusOr<std::shared_ptr<fd::model::Environment>> single =
      fd::model::LoadEnvironment(o.out_dir);  // LoraPolicy::kRequire, yet no ControlLoRA needed
  ASSERT_TRUE(single.ok()) << single.status();
  EXPECT_TRUE((*single)->lora_path.empty());
  EXPECT_FALSE((*single)->settings.irradiance_from_previous);
  EXPECT_EQ((*single)->vae->config().latent_channels, 8);
  EXPECT_EQ((*single)->unet->input_channels(), 16);

  o.stages = {};
  o.command_line = "framediffuser-train all --out ablation";
  ASSERT_TRUE(Make(o)->Run().ok());
  env = read_json();
  EXPECT_FALSE(env.contains("controllora"));
  EXPECT_EQ(env.at("irradiance"), "black");
  const nlohmann::json& training = env.at("training");
  EXPECT_EQ(training.at("commands"), nlohmann::json({"framediffuser-train stage1 --out ablation",
                                                     "framediffuser-train all --out ablation"}));
  EXPECT_EQ(training.at("latent_channels"), 8);
  EXPECT_EQ(training.at("irradiance"), false);
  EXPECT_EQ(training.at("recolour_probability"), 0.5);
  ASSERT_EQ(training.at("stages").size(), 6u);  // with the decoder fine-tune (Options)
  for (const nlohmann::json& stage : training.at("stages")) {
    EXPECT_GT(stage.at("seconds").get<double>(), 0) << stage.dump();
    EXPECT_GE(stage.at("steps").get<int>(), 1) << stage.dump();
    const std::string name = stage.at("stage");
    const bool diffusion = name != "stage0-vae" && name != "stage0-decoder";
    EXPECT_EQ(stage.value("pixel_loss_weight", 0.0), diffusion ? 0.25 : 0.0) << stage.dump();
    const bool conditioned = diffusion && name != "stage0-base";  // stages 1-3 mirror
    EXPECT_EQ(stage.value("flip_probability", 0.0), conditioned ? 0.5 : 0.0) << stage.dump();
    if (conditioned) {
      EXPECT_EQ(stage.at("flip_plane_normal"), nlohmann::json({0, 1, 0}));
    }
    const bool previous = name == "stage2" || name == "stage3";  // the blurred previous frame
    EXPECT_EQ(stage.value("previous_blur_max_sigma", 0.0), previous ? 1.5 : 0.0) << stage.dump();
  }
  EXPECT_EQ(training.at("vae_reconstruction_psnr_on"), "held-out frames");
  absl::StatusOr<std::shared_ptr<fd::model::Environment>> full =
      fd::model::LoadEnvironment(o.out_dir);
  ASSERT_TRUE(full.ok()) << full.status();
  EXPECT_FALSE((*full)->lora_path.empty());
  EXPECT_FALSE((*full)->settings.irradiance_from_previous);

  // Every stage-2 sample of --no-irradiance has a black channel 9.
  absl::StatusOr<TrainingData> data = LoadTrainingData(o.data_dirs, {32, 32});
  ASSERT_TRUE(data.ok()) << data.status();
  SampleOptions samples;
  samples.stage = Stage::kControlLora;
  samples.irradiance = false;
  for (int64_t i = 0; i < 8; ++i) {
    absl::StatusOr<TrainingSample> sample = BuildSample(*data, samples, {}, 7, i);
    ASSERT_TRUE(sample.ok()) << sample.status();
    EXPECT_EQ(sample->irradiance_u8.max().item<int>(), 0) << "sample " << i;
    EXPECT_TRUE(sample->previous.defined());
  }
}

TEST_F(TrainerTest, RefusesOutOfRangeTrainingOptions) {
  TrainerOptions o = Options("recolour");
  o.recolour_probability = 1.5;
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(o);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("--recolour_probability"), std::string::npos);
  // --flip_probability: in [0, 1], with a unit plane normal.
  for (const auto& [probability, plane] :
       std::vector<std::pair<double, std::optional<std::array<double, 3>>>>{
           {1.5, std::array<double, 3>{1, 0, 0}},
           {0.5, std::nullopt},
           {0.5, std::array<double, 3>{2, 0, 0}}}) {
    o = Options("flip");
    o.flip_probability = probability;
    o.flip_plane_normal = plane;
    refused = Trainer::Create(o);
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << probability;
    EXPECT_TRUE(absl::StrContains(refused.status().message(), "--flip_")) << refused.status();
  }
  // --ema_decay: in [0, 1) (1 would never move the average).
  for (double decay : {-0.1, 1.0}) {
    o = Options("ema");
    o.ema_decay = decay;
    refused = Trainer::Create(o);
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << decay;
    EXPECT_TRUE(absl::StrContains(refused.status().message(), "--ema_decay")) << refused.status();
  }
  o = Options("pixel");
  o.pixel_loss_weight = -1;
  refused = Trainer::Create(o);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("--pixel_loss_weight"), std::string::npos);
  // --colour_latent_scale: not negative, on a VAE stage 0 trains, with room
  // for channels besides the three tied ones.
  for (const auto& [scale, latent_channels, vae_dir] :
       std::vector<std::tuple<double, int64_t, std::string>>{
           {-1.0, 0, ""}, {1.0, 3, ""}, {1.0, 0, dir_ + "/some-environment"}}) {
    o = Options("colour");
    o.colour_latent_scale = scale;
    o.latent_channels = latent_channels;
    o.vae_dir = vae_dir;
    refused = Trainer::Create(o);
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << scale;
    EXPECT_NE(refused.status().message().find("--colour_latent_scale"), std::string::npos)
        << refused.status();
  }
}

TEST_F(TrainerTest, StageOneUNetLrTrainsTheUNetInItsOwnGroup) {
  TrainerOptions o = Options("stage1_unet");
  o.schedule[static_cast<int>(Stage::kControlNet)].unet_lr = 3e-4;
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  for (Stage stage : {Stage::kVae, Stage::kBase}) {
    ASSERT_TRUE(t->BeginStage(stage).ok());
    ASSERT_TRUE(t->TrainStep().ok());
    ASSERT_TRUE(t->EndStage().ok());
  }
  ASSERT_TRUE(t->BeginStage(Stage::kControlNet).ok());
  const std::map<std::string, torch::Tensor> before = Snapshot(*t);
  for (int i = 0; i < 2; ++i) ASSERT_TRUE(t->TrainStep().ok());
  // Mid-stage, a resume with another rate is refused: the optimizer's
  // groups would differ.
  ASSERT_TRUE(t->SaveCheckpoint().ok());
  TrainerOptions other_rate = o;
  other_rate.resume = true;
  other_rate.schedule[static_cast<int>(Stage::kControlNet)].unet_lr = 0;
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(other_rate);
  ASSERT_FALSE(refused.ok());
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "stage1_unet_lr")) << refused.status();
  const std::map<std::string, torch::Tensor> after = Snapshot(*t);
  int unet_moved = 0, unet = 0;
  for (const auto& [name, value] : after) {
    const bool same = torch::equal(before.at(name), value);
    if (absl::StartsWith(name, "vae.")) {
      EXPECT_TRUE(same) << name;
    }
    if (absl::StartsWith(name, "unet.")) {
      ++unet;
      unet_moved += same ? 0 : 1;
    }
  }
  EXPECT_EQ(unet_moved, unet);
  ASSERT_TRUE(t->EndStage().ok());

  // The record names the rate; once stage 1 is done, later stages need not
  // repeat the flag.
  std::ifstream in(o.out_dir + "/environment.json");
  const nlohmann::json env = nlohmann::json::parse(in);
  const nlohmann::json& stage1 = env.at("training").at("stages").back();
  EXPECT_EQ(stage1.at("stage"), "stage1");
  EXPECT_DOUBLE_EQ(stage1.at("unet_lr").get<double>(), 3e-4);
  EXPECT_EQ(stage1.at("timestep_sampling"), "uniform");
  // A later command with other flags re-exports; the record keeps what
  // stage 1 was trained with.
  other_rate.stages = {Stage::kControlNet};
  other_rate.timestep_sampling = TimestepSampling::kCubic;
  absl::StatusOr<std::unique_ptr<Trainer>> later = Trainer::Create(other_rate);
  ASSERT_TRUE(later.ok()) << later.status();
  EXPECT_TRUE((*later)->completed(Stage::kControlNet));
  ASSERT_TRUE((*later)->Run().ok());
  std::ifstream again(o.out_dir + "/environment.json");
  const nlohmann::json kept = nlohmann::json::parse(again).at("training").at("stages").back();
  EXPECT_DOUBLE_EQ(kept.at("unet_lr").get<double>(), 3e-4);
  EXPECT_EQ(kept.at("timestep_sampling"), "uniform");
}

// The decoder fine-tune trains on whole frames with the encoder frozen:
// the latents (and the scaling factor the diffusion stages were trained
// with) stay bitwise the same, so it can follow stage 3; the record and a
// --vae run from its folder keep it. Without --decoder_steps it is off.
TEST_F(TrainerTest, TheDecoderFineTuneKeepsTheLatents) {
  TrainerOptions o = Options("decoder");
  o.vae_crop = 32;  // stage 0a on crops; the fine-tune ignores them
  StageSchedule& decoder = o.schedule[static_cast<int>(Stage::kDecoder)];
  decoder.steps = 0;
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  ASSERT_TRUE(t->Run().ok());
  EXPECT_FALSE(t->completed(Stage::kDecoder));  // off: `all` skipped it
  EXPECT_TRUE(t->completed(Stage::kSelfConditioning));
  const double scale = t->vae()->config().scaling_factor;
  const std::map<std::string, torch::Tensor> before = Snapshot(*t);
  const double psnr_before = t->vae_psnr();

  // After stage 3, in the same folder (as street's eighth round was made).
  decoder.steps = 12;
  decoder.warmup = 1;
  decoder.lr = 1e-3;
  o.stages = {Stage::kDecoder};
  o.command_line = "framediffuser-train decoder --decoder_steps 12";
  std::unique_ptr<Trainer> tuned = Make(o);
  ASSERT_NE(tuned, nullptr);
  absl::Status ran = tuned->Run();
  ASSERT_TRUE(ran.ok()) << ran;
  EXPECT_TRUE(tuned->completed(Stage::kDecoder));
  EXPECT_EQ(tuned->vae()->config().scaling_factor, scale);
  EXPECT_NE(tuned->vae_psnr(), psnr_before);  // measured again
  for (const auto& [name, value] : Snapshot(*tuned)) {
    const bool decoder_part =
        absl::StartsWith(name, "vae.decoder.") || absl::StartsWith(name, "vae.post_quant_conv.");
    EXPECT_EQ(torch::equal(before.at(name), value), !decoder_part) << name;
  }
  // The same frames encode to the same latents.
  {
    torch::manual_seed(3);
    const torch::Tensor x = torch::rand({1, 3, o.height, o.width}) * 2 - 1;
    torch::NoGradGuard no_grad;
    absl::StatusOr<fd::model::AutoencoderKL> exported =
        fd::model::LoadVae(o.out_dir + "/vae", torch::kCPU, torch::kFloat32);
    ASSERT_TRUE(exported.ok()) << exported.status();
    EXPECT_TRUE(torch::equal((*exported)->encode(x).mean, t->vae()->encode(x).mean));
    EXPECT_EQ((*exported)->config().scaling_factor, scale);
  }

  std::ifstream in(o.out_dir + "/environment.json");
  const nlohmann::json training = nlohmann::json::parse(in).at("training");
  const nlohmann::json& last = training.at("stages").back();
  EXPECT_EQ(last.at("stage"), "stage0-decoder");
  EXPECT_EQ(last.at("steps"), 12);
  EXPECT_FALSE(last.contains("timestep_sampling"));
  EXPECT_EQ(training.at("commands").back(), o.command_line);
  EXPECT_DOUBLE_EQ(training.at("vae_reconstruction_psnr_db").get<double>(), tuned->vae_psnr());

  // --vae from that folder keeps the fine-tuned decoder and its record.
  TrainerOptions reuse = Options("decoder-reuse");
  reuse.vae_dir = o.out_dir;
  reuse.stages = {Stage::kVae, Stage::kDecoder, Stage::kBase};
  std::unique_ptr<Trainer> kept = Make(reuse);
  ASSERT_NE(kept, nullptr);
  EXPECT_TRUE(kept->completed(Stage::kDecoder));
  absl::Status kept_ran = kept->Run();
  ASSERT_TRUE(kept_ran.ok()) << kept_ran;
  std::ifstream kept_in(reuse.out_dir + "/environment.json");
  const nlohmann::json kept_stages = nlohmann::json::parse(kept_in).at("training").at("stages");
  const nlohmann::json& kept_decoder = kept_stages.back();
  EXPECT_EQ(kept_decoder.at("stage"), "stage0-decoder");
  EXPECT_EQ(kept_decoder.at("from"), o.out_dir);
  EXPECT_EQ(kept_decoder.at("steps"), 12);
  EXPECT_EQ(kept_decoder.at("from_commands").back(), o.command_line);

  // Asked for alone without steps: a clear refusal.
  TrainerOptions off = Options("decoder-off");
  off.schedule[static_cast<int>(Stage::kDecoder)].steps = 0;
  off.stages = {Stage::kDecoder};
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(off);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "--decoder_steps")) << refused.status();
}

// --decoder_latents_from: a finished environment renders chains of training
// frames at its serving settings, and the decoder fine-tune learns to decode
// those latents (not the encoder's) towards the ground truth. Only the
// decoder trains; the record names the source and the fine-tune it follows.
TEST_F(TrainerTest, TheDecoderLearnsTheModelsOwnLatents) {
  TrainerOptions env_options = Options("env");
  StageSchedule& first_tune = env_options.schedule[static_cast<int>(Stage::kDecoder)];
  first_tune.steps = 4;  // the environment had the usual fine-tune, as street's has
  first_tune.warmup = 1;
  std::unique_ptr<Trainer> env_trainer = Make(env_options);
  ASSERT_NE(env_trainer, nullptr);
  ASSERT_TRUE(env_trainer->Run().ok());
  const std::string env_dir = env_options.out_dir;

  TrainerOptions o = Options("own");
  o.vae_dir = env_dir;
  o.decoder_latents_from = env_dir;
  o.decoder_chains = 3;
  o.decoder_chain_frames = 4;
  StageSchedule& decoder = o.schedule[static_cast<int>(Stage::kDecoder)];
  decoder.steps = 12;
  decoder.warmup = 1;
  decoder.lr = 1e-3;
  o.stages = {Stage::kDecoder};
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  EXPECT_FALSE(t->completed(Stage::kDecoder));  // --vae's own fine-tune is not this one
  const std::map<std::string, torch::Tensor> before = Snapshot(*t);
  absl::Status ran = t->Run();
  ASSERT_TRUE(ran.ok()) << ran;
  EXPECT_TRUE(t->completed(Stage::kDecoder));

  // Three chains of four frames after their keyframes (the sequence has 8).
  const std::vector<DecoderLatent>& latents = t->decoder_latents();
  ASSERT_EQ(latents.size(), 12u);
  for (const DecoderLatent& d : latents) {
    EXPECT_GE(d.position, 1);
    EXPECT_LT(d.position, t->data().sequences[0].size());
    EXPECT_EQ(d.latent.sizes(), (torch::IntArrayRef{4, o.height / 8, o.width / 8}));
  }
  for (const auto& [name, value] : Snapshot(*t)) {
    if (!before.count(name)) continue;
    const bool decoder_part =
        absl::StartsWith(name, "vae.decoder.") || absl::StartsWith(name, "vae.post_quant_conv.");
    EXPECT_EQ(torch::equal(before.at(name), value), !decoder_part) << name;
  }
  // The fine-tuned decoder brings those latents nearer their ground truth
  // than the environment's decoder did.
  {
    absl::StatusOr<fd::model::AutoencoderKL> original =
        fd::model::LoadVae(env_dir + "/vae", torch::kCPU, torch::kFloat32);
    ASSERT_TRUE(original.ok()) << original.status();
    std::vector<torch::Tensor> z, frames;
    for (const DecoderLatent& d : latents) {
      z.push_back(d.latent);
      frames.push_back(t->data().sequences[0].final_image[d.position]);
    }
    torch::NoGradGuard no_grad;
    const torch::Tensor zs = torch::stack(z) / t->vae()->config().scaling_factor;
    const torch::Tensor target = torch::stack(frames).to(torch::kFloat32) / 127.5 - 1.0;
    const double mse_before = torch::mse_loss((*original)->decode(zs), target).item<double>();
    const double mse_after = torch::mse_loss(t->vae()->decode(zs), target).item<double>();
    EXPECT_LT(mse_after, 0.9 * mse_before) << mse_before << " -> " << mse_after;
  }

  std::ifstream in(o.out_dir + "/environment.json");
  const nlohmann::json stages = nlohmann::json::parse(in).at("training").at("stages");
  const nlohmann::json& entry = stages.back();
  EXPECT_EQ(entry.at("stage"), "stage0-decoder");
  EXPECT_EQ(entry.at("latents_from"), env_dir);
  EXPECT_EQ(entry.at("chains"), 3);
  EXPECT_EQ(entry.at("chain_frames"), 4);
  EXPECT_GT(entry.at("latents_psnr_db").get<double>(), 0.0);
  EXPECT_EQ(entry.at("follows").at("steps"), 4);  // the environment's own fine-tune
  EXPECT_EQ(entry.at("follows").at("from"), env_dir);

  // The chains follow the environment's "previous_latent": reused, a
  // chain's later frames differ from the encoded ones; its first frame
  // (from the keyframe, always encoded) does not.
  {
    absl::StatusOr<std::shared_ptr<fd::model::Environment>> env =
        fd::model::LoadEnvironment(env_dir);
    ASSERT_TRUE(env.ok()) << env.status();
    DecoderLatentOptions chain_options{1, 3, 7};
    absl::StatusOr<DecoderLatentSet> encoded = RenderDecoderLatents(*env, t->data(), chain_options);
    absl::StatusOr<DecoderLatentSet> again = RenderDecoderLatents(*env, t->data(), chain_options);
    (*env)->settings.reuse_previous_latent = true;
    absl::StatusOr<DecoderLatentSet> reused = RenderDecoderLatents(*env, t->data(), chain_options);
    ASSERT_TRUE(encoded.ok() && again.ok() && reused.ok()) << encoded.status() << reused.status();
    ASSERT_EQ(encoded->latents.size(), 3u);
    ASSERT_EQ(reused->latents.size(), 3u);
    for (size_t i = 0; i < 3; ++i) {
      EXPECT_TRUE(torch::equal(encoded->latents[i].latent, again->latents[i].latent)) << i;
      EXPECT_EQ(reused->latents[i].position, encoded->latents[i].position);
      EXPECT_EQ(torch::equal(reused->latents[i].latent, encoded->latents[i].latent), i == 0) << i;
    }
  }

  // Refused: without --vae, without --decoder_steps, and with an
  // environment whose encoder is not the one being fine-tuned.
  TrainerOptions no_vae = o;
  no_vae.vae_dir.clear();
  no_vae.out_dir = dir_ + "/no-vae";
  absl::StatusOr<std::unique_ptr<Trainer>> refused = Trainer::Create(no_vae);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "--vae")) << refused.status();
  TrainerOptions no_steps = o;
  no_steps.schedule[static_cast<int>(Stage::kDecoder)].steps = 0;
  no_steps.out_dir = dir_ + "/no-steps";
  refused = Trainer::Create(no_steps);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "--decoder_steps")) << refused.status();
  TrainerOptions other_vae = Options("other-vae");
  other_vae.seed = 5;
  other_vae.stages = {Stage::kVae};
  ASSERT_TRUE(Make(other_vae)->Run().ok());
  TrainerOptions mismatch = o;
  mismatch.vae_dir = other_vae.out_dir;
  mismatch.out_dir = dir_ + "/mismatch";
  std::unique_ptr<Trainer> mismatched = Make(mismatch);
  ASSERT_NE(mismatched, nullptr);
  absl::Status mismatch_ran = mismatched->Run();
  EXPECT_EQ(mismatch_ran.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(absl::StrContains(mismatch_ran.message(), "encoder")) << mismatch_ran;
}

TEST_F(TrainerTest, StagesNeedTheirPredecessorAndFinishedOnesAreSkipped) {
  TrainerOptions o = Options("order");
  o.stages = {Stage::kControlLora};
  std::unique_ptr<Trainer> t = Make(o);
  ASSERT_NE(t, nullptr);
  absl::Status status = t->Run();
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(absl::StrContains(status.message(), "stage1")) << status;

  o.stages = {Stage::kVae};
  ASSERT_TRUE(Make(o)->Run().ok());
  // A second run finds stage 0a in --out and skips it; stage 0b runs.
  o.stages = {Stage::kVae, Stage::kBase};
  std::unique_ptr<Trainer> again = Make(o);
  ASSERT_NE(again, nullptr);
  EXPECT_TRUE(again->completed(Stage::kVae));
  ASSERT_TRUE(again->Run().ok());
  EXPECT_TRUE(again->completed(Stage::kBase));
  // Other options than the checkpoint's are refused, naming the option.
  o.width = 40;
  absl::StatusOr<std::unique_ptr<Trainer>> other = Trainer::Create(o);
  ASSERT_FALSE(other.ok());
  EXPECT_TRUE(absl::StrContains(other.status().message(), "width")) << other.status();
}

}  // namespace
}  // namespace fd::trainer
