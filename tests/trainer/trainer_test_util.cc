#include "tests/trainer/trainer_test_util.h"

#include <gtest/gtest.h>
#include <stdlib.h>

#include <cmath>
#include <filesystem>

#include "absl/strings/str_format.h"
#include "client_sdk/image_io.h"

namespace fd::trainer::testing {
namespace {

namespace fs = std::filesystem;
using fd::client::Image8;

void Write(const std::string& dir, const char* buffer, int frame, const Image8& image) {
  const fs::path folder = fs::path(dir) / buffer;
  fs::create_directories(folder);
  const std::string path = (folder / absl::StrFormat("%s_%04d.png", buffer, frame)).string();
  ASSERT_TRUE(fd::client::WritePng(path, image).ok()) << path;
}

uint8_t U8(double v) {
  return static_cast<uint8_t>(std::lround(std::fmin(1.0, std::fmax(0.0, v)) * 255));
}

}  // namespace

void WriteSequence(const std::string& dir, const SequenceSpec& spec) {
  const int w = spec.width, h = spec.height;
  const double phase = static_cast<double>(spec.seed % 97) * 0.37;
  for (int f = 0; f < spec.frames; ++f) {
    Image8 final_image(w, h, 3), base(w, h, 3), normals(w, h, 3), depth(w, h, 1), rough(w, h, 1),
        metal(w, h, 1);
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        const double u = (x + 2.0 * f) / w, v = static_cast<double>(y) / h;
        const bool sky = spec.sky && y < h / 6;
        const double checker =
            ((static_cast<int>(u * 4 + phase) + static_cast<int>(v * 4)) % 2) ? 0.8 : 0.35;
        const double albedo[3] = {checker, 0.5 + 0.3 * std::sin(6 * u + phase), 0.3 + 0.2 * v};
        // A soft "sun" shadow band that moves with the camera.
        const double light = 0.35 + 0.65 * (0.5 + 0.5 * std::cos(9 * u + 3 * v + phase));
        for (int c = 0; c < 3; ++c) {
          base.at(x, y, c) = sky ? 0 : U8(albedo[c]);
          final_image.at(x, y, c) = sky ? U8(0.55 + 0.15 * c + 0.1 * v) : U8(albedo[c] * light);
        }
        normals.at(x, y, 0) = U8(0.5 + 0.4 * std::sin(3 * u));
        normals.at(x, y, 1) = U8(0.8);
        normals.at(x, y, 2) = U8(0.5 + 0.4 * std::cos(3 * u));
        depth.at(x, y, 0) = sky ? 0 : U8(0.2 + 0.7 * v);
        rough.at(x, y, 0) = U8(0.3 + 0.5 * u);
        metal.at(x, y, 0) = U8(checker > 0.5 ? 0.9 : 0.1);
      }
    }
    Write(dir, "FinalImage", f, final_image);
    Write(dir, "BaseColor", f, base);
    Write(dir, "Normals", f, normals);
    Write(dir, "Depth", f, depth);
    Write(dir, "Roughness", f, rough);
    if (spec.metallic) Write(dir, "Metallic", f, metal);
  }
}

std::string MakeTempDir(const std::string& name) {
  std::string pattern = (fs::temp_directory_path() / ("fd_trainer_" + name + "_XXXXXX")).string();
  EXPECT_NE(mkdtemp(pattern.data()), nullptr);
  return pattern;
}

TrainerOptions QuickOptions(const std::string& data, const std::string& out) {
  TrainerOptions o;
  o.data_dirs = {data};
  o.out_dir = out;
  o.preset = "tiny";
  o.width = 32;
  o.height = 32;
  o.batch_size = 2;
  o.threads = 1;
  o.progress_bar = false;
  o.validation_frames = 2;
  o.selfcond_steps = 2;
  o.selfcond_count = 3;
  o.selfcond_every = 2;
  // Every stage, the decoder fine-tune (off by default) too.
  for (int s = 0; s < kStageCount; ++s) {
    o.schedule[s] = DefaultSchedule(static_cast<Stage>(s));
    o.schedule[s].steps = 3;
    o.schedule[s].warmup = 1;
  }
  return o;
}

}  // namespace fd::trainer::testing
