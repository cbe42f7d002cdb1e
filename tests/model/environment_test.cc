// Environment loading: the authors' checkpoint folder (fd_pipeline/model),
// environment.json parsing and errors, and the authors' inference_configs.json.
#include "model/pipeline/environment.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "model/checkpoint/checkpoint_writer.h"
#include "model/checkpoint/file_source.h"
#include "model/networks/model_configs.h"
#include "model/networks/unet.h"
#include "model/text/clip_text_model.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

using ::testing::HasSubstr;
namespace fs = std::filesystem;

std::string TempDir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() /
                       ("fd_environment_test_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir.string();
}

void WriteFile(const std::string& path, const std::string& text) {
  std::ofstream out(path);
  out << text;
}

TEST(EnvironmentSettingsTest, DefaultsAreTheAuthorsInference) {
  auto s = ParseEnvironmentSettings("{}", "env.json");
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_EQ(s->scheduler, SchedulerType::kUniPCMultistep);
  EXPECT_EQ(s->steps, 10);
  EXPECT_EQ(s->guidance_scale, 1.0);
  EXPECT_EQ(s->lora_scale, 1.0);
  EXPECT_EQ(s->conditioning_scale, 1.0);
  EXPECT_EQ(s->width, 512);
  EXPECT_EQ(s->height, 512);
  EXPECT_EQ(s->sky_mode, SkyFillMode::kSkyImage);
  EXPECT_FALSE(s->reuse_previous_latent);  // the VAE encodes the previous frame
}

TEST(EnvironmentSettingsTest, ParsesFields) {
  auto s = ParseEnvironmentSettings(
      R"({"name": "Park", "description": "d", "prompt": "a park", "width": 640, "height": 384,
          "steps": 4, "scheduler": "dpmsolver++", "sky_mode": "previous_output",
          "lora_scale": 0.5, "conditioning_scale": 0.8, "guidance": 2.5,
          "irradiance": "black", "controllora": false, "previous_latent": "reuse"})",
      "env.json");
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_EQ(s->name, "Park");
  EXPECT_EQ(s->prompt, "a park");
  EXPECT_EQ(s->width, 640);
  EXPECT_EQ(s->height, 384);
  EXPECT_EQ(s->steps, 4);
  EXPECT_EQ(s->scheduler, SchedulerType::kDPMSolverMultistep);
  EXPECT_EQ(s->sky_mode, SkyFillMode::kPreviousOutput);
  EXPECT_EQ(s->lora_scale, 0.5);
  EXPECT_EQ(s->conditioning_scale, 0.8);
  EXPECT_EQ(s->guidance_scale, 2.5);
  EXPECT_FALSE(s->irradiance_from_previous);
  EXPECT_FALSE(s->controllora);
  EXPECT_TRUE(s->reuse_previous_latent);
}

TEST(EnvironmentSettingsTest, BadFieldsAreNamed) {
  const std::pair<const char*, const char*> cases[] = {
      {R"({"width": 500})", "'width'"},
      {R"({"steps": 0})", "'steps'"},
      {R"({"scheduler": "plms"})", "'scheduler'"},
      {R"({"sky_mode": "blue"})", "'sky_mode'"},
      {R"({"prompt": 3})", "'prompt'"},
      {R"({"guidance": 0.5})", "'guidance_scale'"},
      {R"({"irradiance": "none"})", "'irradiance'"},
      {R"({"controllora": "no"})", "'controllora'"},
      {R"({"previous_latent": "keep"})", "'previous_latent'"},
      {R"({"previous_latent": true})", "'previous_latent'"},
      {R"([1, 2])", "not a JSON object"},
  };
  for (const auto& [text, field] : cases) {
    auto s = ParseEnvironmentSettings(text, "env.json");
    ASSERT_FALSE(s.ok()) << text;
    EXPECT_EQ(s.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(std::string(s.status().message()), HasSubstr(field)) << text;
  }
}

TEST(EnvironmentTest, LoadsTheAuthorsCheckpointFolder) {
  const std::string dir = fd::testing::GoldenPath("fd_pipeline/model");
  auto env = LoadEnvironment(dir);
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_THAT((*env)->lora_path, HasSubstr("controllora/pytorch_lora_weights.safetensors"));
  EXPECT_EQ((*env)->settings.scheduler, SchedulerType::kUniPCMultistep);
  EXPECT_TRUE((*env)->GetScheduler(SchedulerType::kUniPCMultistep).ok());
  auto embeds = LoadPromptEmbeds(dir + "/prompt_embeds.safetensors");
  ASSERT_TRUE(embeds.ok());
  EXPECT_TRUE(fd::testing::TensorsEqual((*env)->prompt_embeds, *embeds));
  EXPECT_EQ((*env)->unet->input_channels(), 8);
}

TEST(EnvironmentTest, MissingPartsAreNamed) {
  auto env = LoadEnvironment("/nonexistent/fd_env");
  EXPECT_EQ(env.status().code(), absl::StatusCode::kNotFound);
  // A folder with the networks of config B but no LoRA and no text source.
  const std::string b = fd::testing::GoldenPath("B");
  EnvironmentOptions options;
  options.lora_policy = LoraPolicy::kSkip;
  env = LoadEnvironment(b, options);
  ASSERT_FALSE(env.ok());
  EXPECT_EQ(env.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(env.status().message()), HasSubstr("prompt_embeds.safetensors"));
  // An empty folder: the first missing part is named.
  const std::string empty = TempDir("empty");
  env = LoadEnvironment(empty);
  EXPECT_EQ(env.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(env.status().message()), HasSubstr("unet"));
}

// A folder whose UNet takes basecolor patches (framediffuser-train
// --basecolor_patches) loads when they are 3 * f * f channels for its VAE's
// downsampling f (8 here: 192) and is refused, naming the config, otherwise.
TEST(EnvironmentTest, BasecolorPatchChannelsMustMatchTheVae) {
  const fs::path golden = fd::testing::GoldenPath("fd_pipeline/model");
  std::ifstream config_in(golden / "unet" / "config.json");
  const nlohmann::json golden_config = nlohmann::json::parse(config_in);
  for (const int64_t patches : {int64_t{192}, int64_t{48}}) {
    SCOPED_TRACE(patches);
    const fs::path dir = TempDir("patches" + std::to_string(patches));
    for (const auto& entry : fs::directory_iterator(golden)) {
      if (entry.path().filename() == "unet") continue;
      fs::copy(entry.path(), dir / entry.path().filename(), fs::copy_options::recursive);
    }
    for (const auto& entry : fs::recursive_directory_iterator(dir)) {
      fs::permissions(entry.path(), fs::perms::owner_write, fs::perm_options::add);
    }
    nlohmann::json config_json = golden_config;
    config_json["basecolor_patch_channels"] = patches;
    absl::StatusOr<UNet2DConditionConfig> config =
        ParseUNet2DConditionConfig(config_json.dump(), "config.json");
    ASSERT_TRUE(config.ok()) << config.status();
    config->conv_in_channels = config->FrameDiffuserInputChannels();
    absl::StatusOr<UNet2DConditionModel> unet = MakeUNet(*config);
    ASSERT_TRUE(unet.ok()) << unet.status();
    ASSERT_TRUE(
        WriteModelFolder(**unet, config_json.dump(), (dir / "unet").string(), torch::kFloat32)
            .ok());
    EnvironmentOptions options;
    options.lora_policy = LoraPolicy::kSkip;  // the golden LoRA's conv_in takes 8 channels
    absl::StatusOr<std::shared_ptr<Environment>> env = LoadEnvironment(dir.string(), options);
    if (patches == 192) {
      ASSERT_TRUE(env.ok()) << env.status();
      EXPECT_EQ((*env)->unet->input_channels(), 8 + 192);
    } else {
      ASSERT_FALSE(env.ok());
      EXPECT_EQ(env.status().code(), absl::StatusCode::kInvalidArgument);
      EXPECT_THAT(std::string(env.status().message()),
                  HasSubstr("unet/config.json: basecolor_patch_channels is 48"));
      EXPECT_THAT(std::string(env.status().message()), HasSubstr("192 channels"));
    }
    fs::remove_all(dir);
  }
}

// Every file under `dir`, read into memory (path relative to `dir`).
std::map<std::string, std::string> ReadTree(const std::string& dir) {
  std::map<std::string, std::string> files;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    if (!entry.is_regular_file()) continue;
    std::ifstream in(entry.path(), std::ios::binary);
    std::ostringstream bytes;
    bytes << in.rdbuf();
    files.emplace(fs::relative(entry.path(), dir).generic_string(), bytes.str());
  }
  return files;
}

std::map<std::string, std::string_view> Views(const std::map<std::string, std::string>& files) {
  return {files.begin(), files.end()};
}

// An environment held in memory (what the server embeds) loads exactly as
// the same folder on disk does: every weight, the LoRA and the embeddings.
TEST(EnvironmentTest, LoadsFromMemoryExactlyAsFromDisk) {
  const std::string dir = fd::testing::GoldenPath("fd_pipeline/model");
  auto on_disk = LoadEnvironment(dir);
  ASSERT_TRUE(on_disk.ok()) << on_disk.status();
  const std::map<std::string, std::string> tree = ReadTree(dir);
  const MemoryFiles memory("<memory>/env", Views(tree));
  EnvironmentOptions options;
  options.files = &memory;
  auto in_memory = LoadEnvironment(memory.root(), options);
  ASSERT_TRUE(in_memory.ok()) << in_memory.status();
  EXPECT_EQ((*in_memory)->lora_path, "<memory>/env/controllora/pytorch_lora_weights.safetensors");
  EXPECT_TRUE(fd::testing::TensorsEqual((*in_memory)->prompt_embeds, (*on_disk)->prompt_embeds));
  for (auto [a, b] : {std::pair<torch::nn::Module*, torch::nn::Module*>{(*on_disk)->unet.get(),
                                                                        (*in_memory)->unet.get()},
                      {(*on_disk)->controlnet.get(), (*in_memory)->controlnet.get()},
                      {(*on_disk)->vae.get(), (*in_memory)->vae.get()}}) {
    const auto want = a->named_parameters();
    const auto got = b->named_parameters();
    ASSERT_EQ(want.size(), got.size());
    for (const auto& item : want) {
      ASSERT_TRUE(got.contains(item.key())) << item.key();
      EXPECT_TRUE(fd::testing::TensorsEqual(got[item.key()], item.value())) << item.key();
    }
  }
  EXPECT_EQ((*in_memory)->schedulers.size(), (*on_disk)->schedulers.size());
}

// Missing or corrupt in-memory files are named by their path in the source.
TEST(EnvironmentTest, MemoryFilesErrorsNameThePath) {
  const std::map<std::string, std::string> tree =
      ReadTree(fd::testing::GoldenPath("fd_pipeline/model"));
  std::map<std::string, std::string_view> views = Views(tree);
  views.erase("unet/config.json");
  const MemoryFiles missing("<memory>/env", views);
  EnvironmentOptions options;
  options.files = &missing;
  auto env = LoadEnvironment(missing.root(), options);
  EXPECT_EQ(env.status().code(), absl::StatusCode::kNotFound) << env.status();
  EXPECT_THAT(std::string(env.status().message()), HasSubstr("<memory>/env/unet/config.json"));

  views = Views(tree);
  const std::string truncated = tree.at("vae/diffusion_pytorch_model.safetensors").substr(0, 100);
  views["vae/diffusion_pytorch_model.safetensors"] = truncated;
  const MemoryFiles corrupt("<memory>/env", views);
  options.files = &corrupt;
  env = LoadEnvironment(corrupt.root(), options);
  EXPECT_EQ(env.status().code(), absl::StatusCode::kInvalidArgument) << env.status();
  EXPECT_THAT(std::string(env.status().message()),
              HasSubstr("<memory>/env/vae/diffusion_pytorch_model.safetensors"));
}

TEST(MemoryFilesTest, ServesFilesAndFoldersUnderItsRoot) {
  const MemoryFiles files("<m>", {{"a/b.txt", "hello"}, {"a/c/d.bin", "xy"}, {"top.json", "{}"}});
  EXPECT_TRUE(files.IsDirectory("<m>"));
  EXPECT_TRUE(files.IsDirectory("<m>/a"));
  EXPECT_TRUE(files.IsDirectory("<m>/a/c"));
  EXPECT_FALSE(files.IsDirectory("<m>/a/b.txt"));
  EXPECT_TRUE(files.IsFile("<m>/a/b.txt"));
  EXPECT_TRUE(files.IsFile("<m>/a/./c/d.bin"));
  EXPECT_FALSE(files.IsFile("<m>/a"));
  EXPECT_FALSE(files.IsFile("/elsewhere/a/b.txt"));
  EXPECT_EQ(files.List("<m>"), (std::vector<std::string>{"a", "top.json"}));
  EXPECT_EQ(files.List("<m>/a"), (std::vector<std::string>{"b.txt", "c"}));
  EXPECT_TRUE(files.List("<m>/nothing").empty());
  EXPECT_EQ(*files.ReadText("<m>/a/b.txt"), "hello");
  EXPECT_EQ(files.ReadText("<m>/a/x").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(files.OpenSafetensors("<m>/top.json").status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(InferenceConfigsTest, ParsesTheAuthorsFormat) {
  const std::string json = R"({
    "Park": {"gbuffer_dir": "./data/Park", "controlnet_path": "./Models/Park/controlnet",
             "controllora_path": "./Models/Park/pytorch_lora_weights.safetensors",
             "output_dir": "./out", "prompt": "A park", "negative_prompt": "lowres",
             "enable_injection": false},
    "Hill": {"controlnet_path": "/abs/controlnet", "controllora_path": "c.safetensors",
             "prompt": "A hill"}})";
  auto entries = ParseInferenceConfigs(json, "/configs");
  ASSERT_TRUE(entries.ok()) << entries.status();
  ASSERT_EQ(entries->size(), 2u);
  const InferenceConfigEntry* park = nullptr;
  const InferenceConfigEntry* hill = nullptr;
  for (const auto& e : *entries) (e.name == "Park" ? park : hill) = &e;
  ASSERT_TRUE(park && hill);
  EXPECT_EQ(park->controlnet_path, "/configs/Models/Park/controlnet");
  EXPECT_EQ(park->controllora_path, "/configs/Models/Park/pytorch_lora_weights.safetensors");
  EXPECT_EQ(park->prompt, "A park");
  EXPECT_EQ(park->negative_prompt, "lowres");
  EXPECT_FALSE(park->enable_injection);
  EXPECT_EQ(hill->controlnet_path, "/abs/controlnet");
  EXPECT_TRUE(hill->enable_injection);

  auto bad = ParseInferenceConfigs(R"({"X": {"controlnet_path": "a", "prompt": "p"}})", "/");
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(bad.status().message()), HasSubstr("controllora_path"));
  bad = ParseInferenceConfigs(
      R"({"X": {"controlnet_path": "a", "controllora_path": "b", "prompt": "p",
                "enable_injection": "yes"}})",
      "/");
  EXPECT_THAT(std::string(bad.status().message()), HasSubstr("enable_injection"));
}

// An inference_configs.json pointing at the golden checkpoint's ControlNet
// and ControlLoRA, with the checkpoint folder as the "SD1.5" base.
TEST(InferenceConfigsTest, LoadsAnEnvironmentFromAnEntry) {
  const std::string model = fs::absolute(fd::testing::GoldenPath("fd_pipeline/model")).string();
  const std::string dir = TempDir("configs");
  WriteFile(dir + "/inference_configs.json", R"({"Tiny": {"controlnet_path": ")" + model +
                                                 R"(/controlnet",
                         "controllora_path": ")" +
                                                 model +
                                                 R"(/controllora/pytorch_lora_weights.safetensors",
                         "prompt": "tiny", "enable_injection": false}})");
  auto entries = LoadInferenceConfigs(dir + "/inference_configs.json");
  ASSERT_TRUE(entries.ok()) << entries.status();
  ASSERT_EQ(entries->size(), 1u);
  auto env = LoadEnvironmentFromInferenceConfig((*entries)[0], model);
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_EQ((*env)->settings.name, "Tiny");
  EXPECT_EQ((*env)->settings.prompt, "tiny");
  EXPECT_EQ((*env)->settings.sky_mode, SkyFillMode::kNone);
  EXPECT_FALSE((*env)->lora_path.empty());

  InferenceConfigEntry missing = (*entries)[0];
  missing.controllora_path = dir + "/nope.safetensors";
  env = LoadEnvironmentFromInferenceConfig(missing, model);
  EXPECT_EQ(env.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(env.status().message()), HasSubstr("nope.safetensors"));
}

}  // namespace
}  // namespace fd::model
