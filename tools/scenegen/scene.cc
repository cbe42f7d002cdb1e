#include "tools/scenegen/scene.h"

#include <algorithm>
#include <cmath>
#include <thread>
#include <utility>

namespace fd::scenegen {

int Scene::AddMaterial(Material material) {
  materials.push_back(std::move(material));
  return static_cast<int>(materials.size()) - 1;
}

void Scene::Add(Primitive primitive, uint32_t tint) {
  primitive.tint = tint;
  primitives.push_back(primitive);
}

void Scene::Finalize(int threads) {
  bvh.Build(primitives);
  if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  irradiance.Build(*this, probe_grid, threads);
}

Vec3 Scene::SkyRadiance(const Vec3& dir, bool include_sun_disk) const {
  const Lighting& l = lighting;
  const float elevation = dir.z;
  Vec3 sky;
  if (elevation >= 0.0f) {
    const float t = std::pow(1.0f - elevation, 4.0f);
    sky = Lerp(l.sky_zenith, l.sky_horizon, t);
  } else {
    sky = Lerp(l.sky_horizon * 0.6f, l.ground_radiance, SmoothStep(0.0f, 0.15f, -elevation));
  }
  // Forward-scattering glow around the sun.
  const float cos_sun = Dot(dir, l.sun_direction);
  if (cos_sun > 0.0f) {
    const float glow = std::pow(cos_sun, 24.0f) * 0.35f + std::pow(cos_sun, 400.0f) * 1.5f;
    sky += l.sun_irradiance * (glow * (elevation >= 0.0f ? 1.0f : 0.2f));
  }
  if (include_sun_disk && cos_sun > l.sun_disk_cos) {
    // Bright enough to saturate after tone mapping, bounded to avoid fireflies.
    sky += l.sun_irradiance * 12.0f;
  }
  return sky;
}

}  // namespace fd::scenegen
