// Writes the seed corpora of the fuzz targets (tests/fuzz/corpus/<target>/):
// small valid inputs of every shape each parser accepts, made with the
// project's own writers so that they follow the formats exactly.
//
//   fd_make_fuzz_seeds <corpus dir> <source dir> <golden dir>
//
// The checked-in corpus was written by this program; rerun it after a format
// changes (then commit the new seeds).
#include <zstd.h>

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "client_sdk/image_io.h"
#include "framediffuser/v1/render_service.pb.h"
#include "model/checkpoint/safetensors.h"
#include "server/image_codec.h"
#include "session/session_state.h"
#include "session/state_blob.h"

namespace {

namespace fs = std::filesystem;
namespace v1 = ::framediffuser::v1;
using fd::ImageBuffer;
using fd::PixelType;

void Check(const absl::Status& status, const char* what) {
  if (!status.ok()) {
    std::fprintf(stderr, "fd_make_fuzz_seeds: %s: %s\n", what, status.ToString().c_str());
    std::exit(1);
  }
}

void Write(const fs::path& dir, const std::string& name, const std::string& bytes) {
  fs::create_directories(dir);
  std::ofstream out(dir / name, std::ios::binary | std::ios::trunc);
  out << bytes;
  if (!out.good()) {
    std::fprintf(stderr, "fd_make_fuzz_seeds: cannot write %s\n", (dir / name).c_str());
    std::exit(1);
  }
}

std::string ReadText(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    std::fprintf(stderr, "fd_make_fuzz_seeds: cannot read %s\n", path.c_str());
    std::exit(1);
  }
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// A deterministic gradient image.
ImageBuffer Gradient(uint32_t size, uint32_t channels, PixelType type) {
  ImageBuffer image(size, size, channels, type);
  uint8_t* bytes = const_cast<uint8_t*>(image.data());
  for (size_t i = 0; i < image.num_elements(); ++i) {
    if (type == PixelType::kUint8) {
      bytes[i] = static_cast<uint8_t>(i * 37);
    } else {
      reinterpret_cast<float*>(bytes)[i] = static_cast<float>(i % 17) / 16.0f;
    }
  }
  return image;
}

// The wire form of a plane, as a client sends it: EncodeImage's bytes of a
// 3-channel gradient (the first third of them for a 1-channel plane),
// zstd-compressed with the content size set when asked.
v1::Image Wire(uint32_t size, uint32_t channels, fd::session::OutputDType dtype,
               fd::session::OutputCompression compression) {
  const PixelType type =
      dtype == fd::session::OutputDType::kUint8 ? PixelType::kUint8 : PixelType::kFloat32;
  v1::Image wire;
  Check(fd::server::EncodeImage(Gradient(size, 3, type), dtype,
                                fd::session::OutputCompression::kNone, &wire),
        "encode");
  wire.set_channels(channels);
  wire.mutable_data()->resize(wire.data().size() / 3 * channels);
  if (compression == fd::session::OutputCompression::kZstd) {
    std::string packed(ZSTD_compressBound(wire.data().size()), '\0');
    const size_t n =
        ZSTD_compress(packed.data(), packed.size(), wire.data().data(), wire.data().size(), 3);
    if (ZSTD_isError(n)) Check(absl::InternalError(ZSTD_getErrorName(n)), "zstd");
    packed.resize(n);
    wire.set_data(std::move(packed));
    wire.set_compression(v1::COMPRESSION_ZSTD);
  }
  return wire;
}

void FrameInputs(const fs::path& dir) {
  using fd::session::OutputCompression;
  using fd::session::OutputDType;
  struct Case {
    const char* name;
    OutputDType dtype;
    OutputCompression compression;
    bool metallic;
    bool sky;
    bool keyframe;
  };
  const Case cases[] = {
      {"uint8", OutputDType::kUint8, OutputCompression::kNone, true, false, false},
      {"uint8_no_metallic", OutputDType::kUint8, OutputCompression::kNone, false, false, false},
      {"float16", OutputDType::kFloat16, OutputCompression::kNone, true, false, false},
      {"float32_zstd", OutputDType::kFloat32, OutputCompression::kZstd, true, false, false},
      {"uint8_zstd_sky", OutputDType::kUint8, OutputCompression::kZstd, true, true, false},
      {"uint8_keyframe", OutputDType::kUint8, OutputCompression::kNone, true, false, true},
  };
  for (const Case& c : cases) {
    v1::FrameInput frame;
    frame.set_frame_index(5);
    v1::GBuffer* g = frame.mutable_gbuffer();
    *g->mutable_basecolor() = Wire(8, 3, c.dtype, c.compression);
    *g->mutable_normals() = Wire(8, 3, c.dtype, c.compression);
    *g->mutable_depth() = Wire(8, 1, c.dtype, c.compression);
    *g->mutable_roughness() = Wire(8, 1, c.dtype, c.compression);
    if (c.metallic) *g->mutable_metallic() = Wire(8, 1, c.dtype, c.compression);
    if (c.sky) *frame.mutable_sky() = Wire(8, 3, c.dtype, c.compression);
    if (c.keyframe) {
      *frame.mutable_keyframe() = Wire(8, 3, c.dtype, c.compression);
      *frame.mutable_keyframe_basecolor() = Wire(8, 3, c.dtype, c.compression);
    }
    // Byte 0: 8x8, sky mode client image when the frame carries a sky.
    Write(dir, c.name, std::string(1, c.sky ? '\x10' : '\x00') + frame.SerializeAsString());
  }
}

void OpenRequests(const fs::path& dir) {
  v1::RenderRequest defaults;
  defaults.mutable_open()->set_environment("street");
  Write(dir, "open_defaults", defaults.SerializeAsString());

  v1::RenderRequest full;
  v1::OpenSession* open = full.mutable_open();
  open->set_environment("street");
  open->set_width(16);
  open->set_height(16);
  open->set_seed(42);
  open->set_steps(4);
  open->set_scheduler(v1::SCHEDULER_DDIM);
  open->set_sky_mode(v1::SKY_MODE_CLIENT_IMAGE);
  open->set_output_dtype(v1::DTYPE_FLOAT16);
  open->set_output_compression(v1::COMPRESSION_ZSTD);
  open->set_max_frames_in_flight(2);
  Write(dir, "open_full", full.SerializeAsString());

  v1::RenderRequest keyframe = full;
  *keyframe.mutable_open()->mutable_keyframe() =
      Wire(16, 3, fd::session::OutputDType::kUint8, fd::session::OutputCompression::kNone);
  *keyframe.mutable_open()->mutable_keyframe_basecolor() =
      Wire(16, 3, fd::session::OutputDType::kFloat32, fd::session::OutputCompression::kZstd);
  Write(dir, "open_keyframe", keyframe.SerializeAsString());

  v1::RenderRequest resume;
  resume.mutable_resume()->set_session_id("0123456789abcdef0123456789abcdef");
  resume.mutable_resume()->set_resume_token("00000000000000000000000000000000");
  Write(dir, "resume", resume.SerializeAsString());
}

void SafetensorsFiles(const fs::path& dir) {
  const fs::path scratch = fs::temp_directory_path() / "fd_make_fuzz_seeds.safetensors";
  auto save = [&](const std::string& name, const std::map<std::string, torch::Tensor>& tensors,
                  const std::map<std::string, std::string>& metadata) {
    Check(fd::model::SaveSafetensors(scratch.string(), tensors, metadata), "safetensors");
    Write(dir, name, ReadText(scratch));
  };
  torch::manual_seed(0);
  save("f32_f16",
       {{"conv.weight", torch::randn({2, 3, 1, 1})},
        {"conv.bias", torch::randn({2}).to(torch::kHalf)}},
       {{"format", "pt"}});
  save("dtypes",
       {{"a", torch::arange(6, torch::kInt64).reshape({2, 3})},
        {"b", torch::ones({4}, torch::kUInt8)},
        {"c", torch::zeros({3}, torch::kBFloat16)},
        {"scalar", torch::tensor(1.5f)},
        {"empty", torch::zeros({0, 4})}},
       {});
  save("lora",
       {{"unet.down.lora_A.weight", torch::randn({4, 8})},
        {"unet.down.lora_B.weight", torch::zeros({8, 4})}},
       {{"rank", "4"}});
  fs::remove(scratch);
}

void JsonFiles(const fs::path& dir, const fs::path& source, const fs::path& golden) {
  const fs::path street = source / "environments/street";
  // Byte 0 picks the parser (tests/fuzz/fuzz_model_json.cc).
  Write(dir, "unet_config", std::string(1, '\0') + ReadText(street / "unet/config.json"));
  Write(dir, "controlnet_config", "\x01" + ReadText(street / "controlnet/config.json"));
  Write(dir, "vae_config", "\x02" + ReadText(street / "vae/config.json"));
  Write(dir, "clip_text_config", "\x03" + ReadText(golden / "clip/text_encoder/config.json"));
  Write(dir, "scheduler_config", "\x04" + ReadText(street / "scheduler/scheduler_config.json"));
  Write(dir, "environment",
        "\x05" + std::string(R"({"name": "street", "description": "d", "width": 128, "height": 128,
 "steps": 10, "scheduler": "unipc", "sky_mode": "previous_output", "prompt": "p",
 "lora_scale": 1.0, "conditioning_scale": 1.0, "guidance_scale": 1.0})"));
  Write(dir, "inference_configs",
        "\x06" + std::string(R"({"Tiny": {"controlnet_path": "models/tiny/controlnet",
 "controllora_path": "models/tiny/controllora/pytorch_lora_weights.safetensors",
 "prompt": "tiny", "negative_prompt": "", "enable_injection": false},
 "Other": {"controlnet_path": "/abs/cn", "controllora_path": "/abs/lora.safetensors",
 "prompt": "a street", "enable_injection": true, "gbuffer_dir": "x"}})"));
}

void ImageFiles(const fs::path& dir) {
  const fs::path scratch = fs::temp_directory_path() / "fd_make_fuzz_seeds";
  fs::create_directories(scratch);
  fd::client::Image8 gray(8, 8, 1), rgb(8, 8, 3), rgba(4, 4, 4);
  for (size_t i = 0; i < rgb.pixels.size(); ++i) rgb.pixels[i] = uint8_t(i * 7);
  for (size_t i = 0; i < gray.pixels.size(); ++i) gray.pixels[i] = uint8_t(i * 3);
  fd::client::ImageF exr_rgb(8, 8, 3), exr_y(8, 8, 1);
  for (size_t i = 0; i < exr_rgb.pixels.size(); ++i) exr_rgb.pixels[i] = float(i % 11) / 10;
  for (size_t i = 0; i < exr_y.pixels.size(); ++i) exr_y.pixels[i] = float(i % 5) / 4;
  fd::client::ImageF16 half(8, 8, 3);
  for (size_t i = 0; i < half.pixels.size(); ++i) half.pixels[i] = fd::client::FloatToHalf(0.25f);

  // Byte 0: even = PNG, odd = EXR (tests/fuzz/fuzz_image_file.cc).
  auto png = [&](const std::string& name, const fd::client::Image8& image) {
    Check(fd::client::WritePng((scratch / "x.png").string(), image), "png");
    Write(dir, name, "\x00" + ReadText(scratch / "x.png"));
  };
  auto exr = [&](const std::string& name, auto write) {
    Check(write((scratch / "x.exr").string()), "exr");
    Write(dir, name, "\x01" + ReadText(scratch / "x.exr"));
  };
  png("png_gray", gray);
  png("png_rgb", rgb);
  png("png_rgba", rgba);
  exr("exr_rgb_float", [&](const std::string& p) { return fd::client::WriteExr(p, exr_rgb); });
  exr("exr_y_float", [&](const std::string& p) { return fd::client::WriteExr(p, exr_y); });
  exr("exr_rgb_half", [&](const std::string& p) { return fd::client::WriteExr(p, half); });
  exr("exr_layered", [&](const std::string& p) {
    return fd::client::WriteLayeredExr(
        p, {{"BaseColor", &exr_rgb}, {"Normals", &exr_rgb}, {"Depth", &exr_y}});
  });
  fs::remove_all(scratch);
}

void StateBlobs(const fs::path& dir) {
  fd::session::SessionSettings settings;
  settings.environment = "street";
  settings.width = settings.height = 8;
  settings.seed = 3;
  settings.steps = 4;
  absl::StatusOr<fd::session::SessionState> fresh =
      fd::session::SessionState::StartFromGBufferOnly(settings);
  Check(fresh.status(), "state");
  absl::StatusOr<std::string> blob = fd::session::ExportState(*fresh);
  Check(blob.status(), "export");
  Write(dir, "gbuffer_only", *blob);

  absl::StatusOr<fd::session::SessionState> keyed = fd::session::SessionState::StartFromKeyframe(
      settings, Gradient(8, 3, PixelType::kUint8), ImageBuffer());
  Check(keyed.status(), "keyframe state");
  blob = fd::session::ExportState(*keyed);
  Check(blob.status(), "export");
  Write(dir, "keyframe", *blob);

  Check(fresh->CommitFrame(7, Gradient(8, 3, PixelType::kUint8), Gradient(8, 3, PixelType::kUint8)),
        "commit");
  blob = fd::session::ExportState(*fresh);
  Check(blob.status(), "export");
  Write(dir, "after_a_frame", *blob);
}

void Prompts(const fs::path& dir) {
  Write(dir, "ascii", "A photorealistic scene, street at dusk; 4k photo!");
  Write(dir, "unicode",
        "Caf\xc3\xa9 \xe6\x97\xa5\xe6\x9c\xac\xe8\xaa\x9e \xf0\x9f\x98\x80 na\xc3\xafve");
  Write(dir, "html_and_space", "&amp; &lt;b&gt;bold&lt;/b&gt;\t\n  spaced   out 's 't 're");
  Write(dir, "invalid_utf8", std::string("bad \xff\xfe\xc3( bytes \xed\xa0\x80", 20));
  Write(dir, "numbers", "1234567890 3.14159 1e-3 v2.0");
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 4) {
    std::fprintf(stderr, "usage: %s <corpus dir> <source dir> <golden dir>\n", argv[0]);
    return 2;
  }
  const fs::path corpus = argv[1];
  FrameInputs(corpus / "frame_input");
  OpenRequests(corpus / "open_settings");
  SafetensorsFiles(corpus / "safetensors");
  JsonFiles(corpus / "model_json", argv[2], argv[3]);
  ImageFiles(corpus / "image_file");
  StateBlobs(corpus / "state_blob");
  Prompts(corpus / "clip_tokenizer");
  std::printf("fd_make_fuzz_seeds: wrote %s\n", corpus.c_str());
  return 0;
}
