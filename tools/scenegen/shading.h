// Shading helpers shared by the frame renderer and the irradiance volume.
#ifndef FD_TOOLS_SCENEGEN_SHADING_H_
#define FD_TOOLS_SCENEGEN_SHADING_H_

#include "tools/scenegen/geometry.h"
#include "tools/scenegen/material.h"
#include "tools/scenegen/vec3.h"

namespace fd::scenegen {

struct Scene;

inline constexpr float kPi = 3.14159265358979f;
inline constexpr float kMaxDistance = 5000.0f;

// Offset that lifts ray origins off the surface they start on.
inline float RayEpsilon(float t) { return 2e-3f + 1e-5f * t; }

// Cosine-weighted direction around unit n from two uniforms in [0, 1).
Vec3 CosineSample(const Vec3& n, float u1, float u2);

// A surface reached by a ray, faced towards the ray, with its material
// evaluated at a wide footprint (secondary rays see average textures).
struct SurfaceHit {
  Vec3 position;
  Vec3 origin;  // position nudged off the surface, for rays leaving it
  Vec3 normal;
  SurfaceSample surface;
  bool back_face = false;  // the ray hit the inside of a closed shape
};
SurfaceHit ResolveSecondaryHit(const Scene& scene, const Ray& ray, const Hit& hit);

// Sun irradiance / pi at a surface point (casts the shadow ray).
Vec3 SunOverPi(const Scene& scene, const Vec3& origin, const Vec3& normal);

// Albedo for diffuse scattering: metals reflect rather than scatter, but keep
// some colour so they are not black in secondary light.
inline Vec3 DiffuseAlbedo(const SurfaceSample& s) { return s.albedo * (1.0f - 0.5f * s.metallic); }

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_SHADING_H_
