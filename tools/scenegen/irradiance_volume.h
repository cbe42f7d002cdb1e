// A grid of irradiance probes: precomputed diffuse light (sky, sun bounces,
// several bounces deep) for a static scene, looked up per pixel.
//
// Why: with only a few hemisphere rays per pixel, indirect light indoors
// (sun patches lighting a room) is so noisy that consecutive frames flicker.
// The scene does not change, so its diffuse light field can be computed once
// with many rays per probe and reused by every frame: indirect light becomes
// noise-free and temporally stable, as with baked light probes in games.
// Short ambient-occlusion rays per pixel (renderer.cc) add the contact detail
// the grid is too coarse for.
//
// Each probe stores an "ambient cube" (irradiance for the six axis normals,
// Valve 2006) plus the mean and mean-square distance to the surrounding
// surfaces along the six axes; lookups weight the eight surrounding probes
// trilinearly, drop probes inside geometry, favour probes in front of the
// surface and use the distance moments (a Chebyshev test, as in DDGI) to
// ignore probes behind walls.
#ifndef FD_TOOLS_SCENEGEN_IRRADIANCE_VOLUME_H_
#define FD_TOOLS_SCENEGEN_IRRADIANCE_VOLUME_H_

#include <vector>

#include "tools/scenegen/vec3.h"

namespace fd::scenegen {

struct Scene;

struct ProbeGridSpec {
  Vec3 lo;  // box covered by probes; lookups outside it use its border probes
  Vec3 hi;
  float spacing = 1.0f;  // metres between probes (rounded to fit the box)
  int rays = 64;         // rays per probe
  int bounces = 2;       // 1 = light from sun- and sky-lit surfaces only
};

class IrradianceVolume {
 public:
  // Traces the probes of `spec` in `scene` (whose BVH must be built). The
  // result depends only on scene and spec, never on `threads`.
  void Build(const Scene& scene, const ProbeGridSpec& spec, int threads);

  bool empty() const { return probes_.empty(); }
  int probe_count() const { return static_cast<int>(probes_.size()); }
  int valid_probe_count() const;

  // Irradiance arriving at surface point p with unit normal n (multiply by
  // albedo / pi for Lambert radiance). `fallback` when no probe applies.
  // Thread-safe (read-only).
  Vec3 Irradiance(const Vec3& p, const Vec3& n, const Vec3& fallback) const;

 private:
  struct Probe {
    Vec3 position;
    Vec3 cube[6];  // irradiance for normals +X, -X, +Y, -Y, +Z, -Z
    float mean[6] = {0, 0, 0, 0, 0, 0};
    float mean2[6] = {0, 0, 0, 0, 0, 0};
    bool valid = false;
  };
  int Index(int i, int j, int k) const { return (k * dims_[1] + j) * dims_[0] + i; }

  int dims_[3] = {0, 0, 0};
  Vec3 lo_;
  Vec3 cell_;
  std::vector<Probe> probes_;
};

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_IRRADIANCE_VOLUME_H_
