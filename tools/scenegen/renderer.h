// CPU ray tracer producing the G-buffer and the ground-truth radiance of one
// frame.
//
// Shading per pixel: the sun with a hard shadow ray, Lambert diffuse plus GGX
// specular (Smith masking, Schlick Fresnel); sky light and multi-bounce
// indirect light from the scene's irradiance volume (irradiance_volume.h),
// times ambient occlusion from a few short rays; a mirror ray for smooth and
// metallic surfaces (its hit is lit by sun + volume, so reflections carry no
// noise); split-sum environment specular for rough surfaces. The noisy
// occlusion term is smoothed by an edge-avoiding a-trous filter guided by
// the G-buffer, as real-time renderers do.
#ifndef FD_TOOLS_SCENEGEN_RENDERER_H_
#define FD_TOOLS_SCENEGEN_RENDERER_H_

#include <cstdint>
#include <vector>

#include "tools/scenegen/camera.h"
#include "tools/scenegen/scene.h"
#include "tools/scenegen/vec3.h"

namespace fd::scenegen {

struct RenderSettings {
  int width = 512;
  int height = 512;
  uint64_t seed = 0;
  // Worker threads (rows are split across them). The image does not depend
  // on this value: every pixel has its own random stream.
  int threads = 1;
  // Ambient-occlusion rays per pixel (reach: Scene::ao_radius).
  int ao_samples = 4;
};

// Per-pixel float buffers, row-major, top row first. Sky pixels (no
// geometry) have zero base colour, normal, depth, roughness and metallic.
struct FrameBuffers {
  int width = 0;
  int height = 0;
  std::vector<uint8_t> geometry;  // 1 where a surface was hit, 0 for sky
  std::vector<Vec3> radiance;     // linear scene radiance, before exposure
  std::vector<Vec3> base_color;   // linear albedo
  std::vector<Vec3> normal;       // world-space unit normal, facing the camera
  std::vector<float> view_depth;  // metres along the camera's forward axis
  std::vector<float> roughness;
  std::vector<float> metallic;

  size_t Index(int x, int y) const { return size_t(y) * width + x; }
};

// Renders frame `frame` (used only to seed the per-pixel random streams) of
// `scene` seen by `camera`. Thread-safe for concurrent calls on the same
// scene (the scene is read-only). Deterministic: equal inputs give equal
// buffers for any settings.threads.
FrameBuffers RenderFrame(const Scene& scene, const Camera& camera, int frame,
                         const RenderSettings& settings);

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_RENDERER_H_
