// A renderable scene: materials, primitives (with their BVH), sun and sky
// lighting, camera path and the depth-encoding near plane.
#ifndef FD_TOOLS_SCENEGEN_SCENE_H_
#define FD_TOOLS_SCENEGEN_SCENE_H_

#include <cstdint>
#include <string>
#include <vector>

#include "tools/scenegen/camera.h"
#include "tools/scenegen/geometry.h"
#include "tools/scenegen/irradiance_volume.h"
#include "tools/scenegen/material.h"
#include "tools/scenegen/vec3.h"

namespace fd::scenegen {

// Sun + analytic sky. Radiance units are arbitrary but consistent; the
// scene's exposure maps them to display range before tone mapping.
struct Lighting {
  Vec3 sun_direction{0.0f, 0.0f, 1.0f};      // unit vector towards the sun
  Vec3 sun_irradiance{3.0f, 2.9f, 2.6f};     // on a surface facing the sun
  float sun_disk_cos = 0.9996f;              // cos of the visible disk's radius
  Vec3 sky_zenith{0.25f, 0.45f, 0.95f};      // radiance straight up
  Vec3 sky_horizon{0.75f, 0.85f, 1.0f};      // radiance at the horizon
  Vec3 ground_radiance{0.2f, 0.19f, 0.17f};  // below the horizon (no geometry)
  // Radiance assumed to arrive everywhere before the probes' first bounce
  // (and where no probe applies): stands in for light the probes do not
  // gather (higher outdoors, near zero indoors so that unlit rooms stay dark).
  float secondary_fill = 0.1f;
  float exposure = 1.0f;  // multiplies radiance before tone mapping
};

struct Scene {
  std::string name;
  std::string description;
  std::vector<Material> materials;
  std::vector<Primitive> primitives;
  Bvh bvh;
  Lighting lighting;
  // Diffuse light field (built by Finalize from probe_grid).
  ProbeGridSpec probe_grid;
  IrradianceVolume irradiance;
  CameraPath camera_path;
  // Depth is stored as near_plane / view_depth; see encoding.h.
  float near_plane = 1.0f;
  // Reach of the per-pixel ambient-occlusion rays, metres: contact shadows
  // finer than the probe grid.
  float ao_radius = 1.0f;

  int AddMaterial(Material material);
  // Adds a primitive; `tint` seeds per-object colour variation.
  void Add(Primitive primitive, uint32_t tint = 0);
  // Builds the BVH and the irradiance volume; call once after the last
  // Add(). `threads` (0 = all cores) only changes how fast.
  void Finalize(int threads = 0);

  // Sky radiance seen along unit direction dir. The sun disk is included
  // only for camera and mirror rays (diffuse sampling gets the sun from the
  // explicit sun light instead).
  Vec3 SkyRadiance(const Vec3& dir, bool include_sun_disk) const;
};

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_SCENE_H_
