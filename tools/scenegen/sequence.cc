#include "tools/scenegen/sequence.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "tools/scenegen/parallel.h"
#include "tools/scenegen/renderer.h"
#include "tools/scenegen/scenes.h"

namespace fd::scenegen {
namespace {

using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

// Rounds to 6 decimals so scene.json stays readable (values are metres and
// degrees; finer digits carry no information).
double Round6(float v) { return std::round(static_cast<double>(v) * 1e6) / 1e6; }

nlohmann::json VecJson(const Vec3& v) { return {Round6(v.x), Round6(v.y), Round6(v.z)}; }

nlohmann::json EncodingJson() {
  return {
      {"FinalImage",
       "8-bit sRGB RGB: ACES filmic tone map (Narkowicz fit) of exposure * linear radiance, then "
       "the sRGB transfer function"},
      {"BaseColor", "8-bit RGB: sRGB-encoded linear albedo; sky pixels (0,0,0)"},
      {"Normals",
       "8-bit RGB: world-space unit normal n (right-handed, Z up), round((n*0.5+0.5)*255); "
       "sky pixels (0,0,0)"},
      {"Depth",
       "8-bit gray: inverse depth round(255*min(1, near_plane/d)), d = view depth in metres "
       "along the camera axis; 0 = no geometry (sky); geometry is clamped to >= 10, i.e. "
       "surfaces farther than near_plane*25.5 are stored as 10"},
      {"Roughness", "8-bit gray: round(255*roughness), linear; sky 0"},
      {"Metallic", "8-bit gray: round(255*metallic), linear; sky 0"},
      {"exr",
       "float32 EXR beside each PNG (same folder, .exr): FinalImage = exposure * linear "
       "radiance before tone mapping; BaseColor = linear albedo; Normals = raw n in [-1,1]; "
       "Depth = near_plane/d unclamped (metric depth = near_plane/value); Roughness, Metallic "
       "linear; sky 0; channels R,G,B or Y"},
      {"sky_test",
       "sky pixels have all BaseColor channels < 10 and Depth < 10 (they are exactly 0); no "
       "geometry pixel does"},
  };
}

nlohmann::json CameraJson(const Camera& c) {
  return {{"position", VecJson(c.position)}, {"forward", VecJson(c.forward)},
          {"right", VecJson(c.right)},       {"up", VecJson(c.up)},
          {"yaw_deg", Round6(c.yaw_deg)},    {"pitch_deg", Round6(c.pitch_deg)},
          {"fov_y_deg", Round6(c.fov_y_deg)}};
}

absl::Status ValidateOptions(const GeneratorOptions& o) {
  if (o.out_dir.empty()) return absl::InvalidArgumentError("out_dir must not be empty");
  const std::vector<SceneInfo>& catalog = SceneCatalog();
  if (std::none_of(catalog.begin(), catalog.end(),
                   [&](const SceneInfo& info) { return info.name == o.scene; })) {
    return MakeScene(o.scene, 0).status();  // the error naming the known scenes
  }
  if (o.frames < 1) {
    return absl::InvalidArgumentError(absl::StrCat("frames must be >= 1, got ", o.frames));
  }
  if (o.start_frame < 0 || o.start_frame > kMaxFrameIndex - o.frames) {
    return absl::InvalidArgumentError(absl::StrCat("start_frame + frames must be within 0..",
                                                   kMaxFrameIndex, ", got ", o.start_frame, " + ",
                                                   o.frames));
  }
  if (o.width < 1 || o.height < 1 || o.width > 16384 || o.height > 16384) {
    return absl::InvalidArgumentError(
        absl::StrCat("size must be within 1..16384 per side, got ", o.width, "x", o.height));
  }
  if (o.threads < 0) {
    return absl::InvalidArgumentError(absl::StrCat("threads must be >= 0, got ", o.threads));
  }
  return absl::OkStatus();
}

absl::Status WriteManifest(const GeneratorOptions& o, const Scene& scene,
                           const std::vector<Camera>& cameras) {
  nlohmann::json frames = nlohmann::json::array();
  for (size_t i = 0; i < cameras.size(); ++i) {
    frames.push_back(
        {{"index", o.start_frame + static_cast<int>(i)}, {"camera", CameraJson(cameras[i])}});
  }
  std::vector<std::string> buffers(kBufferNames.begin(), kBufferNames.end());
  const nlohmann::json manifest = {
      {"generator", "framediffuser-scenegen"},
      {"manifest_version", 1},
      {"arguments",
       {{"scene", o.scene},
        {"frames", o.frames},
        {"start", o.start_frame},
        {"width", o.width},
        {"height", o.height},
        {"seed", o.seed},
        {"format", OutputFormatName(o.format)}}},
      {"layout",
       {{"buffers", buffers},
        {"png", o.format != OutputFormat::kExr},
        {"exr", o.format != OutputFormat::kPng},
        {"file_pattern", "<Buffer>/<Buffer>_<frame, 4 digits>.<png|exr>"}}},
      {"coordinates",
       "world: right-handed, Z up, metres; camera yaw counter-clockwise from +X, pitch above the "
       "horizon; image row 0 is the top"},
      {"encoding", EncodingJson()},
      {"scene",
       {{"name", scene.name},
        {"description", scene.description},
        {"near_plane", Round6(scene.near_plane)},
        {"far_plane_for_depth_byte_10", Round6(scene.near_plane * 25.5f)},
        {"exposure", Round6(scene.lighting.exposure)},
        {"sun_direction", VecJson(scene.lighting.sun_direction)},
        {"camera_step_per_frame", Round6(scene.camera_path.step())},
        {"primitives", scene.primitives.size()},
        {"materials", scene.materials.size()}}},
      {"frames", frames},
  };
  const std::string path = (std::filesystem::path(o.out_dir) / "scene.json").string();
  std::ofstream file(path, std::ios::binary | std::ios::trunc);
  file << manifest.dump(2) << "\n";
  file.close();
  if (!file) return absl::InternalError(absl::StrCat("cannot write ", path));
  return absl::OkStatus();
}

}  // namespace

const char* OutputFormatName(OutputFormat format) {
  switch (format) {
    case OutputFormat::kPng:
      return "png";
    case OutputFormat::kExr:
      return "exr";
    case OutputFormat::kBoth:
      return "both";
  }
  return "png";
}

std::string BufferFileName(Buffer buffer, int frame, const std::string& extension) {
  return absl::StrFormat("%s_%04d.%s", kBufferNames[static_cast<int>(buffer)], frame, extension);
}

std::string BufferPath(const std::string& out_dir, Buffer buffer, int frame,
                       const std::string& extension) {
  return (std::filesystem::path(out_dir) / kBufferNames[static_cast<int>(buffer)] /
          BufferFileName(buffer, frame, extension))
      .string();
}

int ResolveThreads(int requested) {
  if (requested > 0) return requested;
  return std::max(1u, std::thread::hardware_concurrency());
}

absl::StatusOr<GenerationStats> GenerateSequence(const GeneratorOptions& options,
                                                 const std::function<void(int)>& progress) {
  if (absl::Status s = ValidateOptions(options); !s.ok()) return s;
  for (const char* name : kBufferNames) {
    const std::filesystem::path dir = std::filesystem::path(options.out_dir) / name;
    std::error_code ec;
    std::filesystem::create_directories(dir, ec);
    if (ec) {
      return absl::InternalError(
          absl::StrCat("cannot create folder ", dir.string(), ": ", ec.message()));
    }
  }
  absl::StatusOr<std::shared_ptr<const Scene>> scene_or =
      SharedScene(options.scene, options.seed, ResolveThreads(options.threads));
  if (!scene_or.ok()) return scene_or.status();
  const Scene& scene = **scene_or;

  RenderSettings settings;
  settings.width = options.width;
  settings.height = options.height;
  settings.seed = options.seed;
  settings.threads = ResolveThreads(options.threads);
  const EncodingParams params{scene.lighting.exposure, scene.near_plane};
  const bool png = options.format != OutputFormat::kExr;
  const bool exr = options.format != OutputFormat::kPng;

  GenerationStats stats;
  std::vector<Camera> cameras;
  for (int frame = options.start_frame; frame < options.start_frame + options.frames; ++frame) {
    const Clock::time_point render_start = Clock::now();
    const Camera camera = scene.camera_path.At(frame);
    cameras.push_back(camera);
    const FrameBuffers buffers = RenderFrame(scene, camera, frame, settings);
    EncodedFrame encoded;
    FloatFrame floats;
    if (png) encoded = EncodeFrame(buffers, params);
    if (exr) floats = FloatFrameFromBuffers(buffers, params);
    stats.render_seconds += Seconds(render_start);

    // One task per file; files are independent, so write them in parallel.
    const Clock::time_point write_start = Clock::now();
    const int files_per_format = kNumBuffers;
    const int files = (png ? files_per_format : 0) + (exr ? files_per_format : 0);
    std::vector<absl::Status> results(files);
    ParallelFor(files, settings.threads, [&](int task) {
      const bool is_png = png && task < files_per_format;
      const int k = task % files_per_format;
      const Buffer buffer = static_cast<Buffer>(k);
      results[task] = is_png
                          ? WritePng(BufferPath(options.out_dir, buffer, frame, "png"), encoded[k])
                          : WriteExr(BufferPath(options.out_dir, buffer, frame, "exr"), floats[k]);
    });
    for (const absl::Status& s : results) {
      if (!s.ok()) return s;
    }
    stats.write_seconds += Seconds(write_start);
    ++stats.frames;
    if (progress) progress(frame);
  }
  if (absl::Status s = WriteManifest(options, scene, cameras); !s.ok()) return s;
  return stats;
}

}  // namespace fd::scenegen
