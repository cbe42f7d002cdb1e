#include "tools/scenegen/shading.h"

#include <algorithm>
#include <cmath>

#include "tools/scenegen/scene.h"

namespace fd::scenegen {

Vec3 CosineSample(const Vec3& n, float u1, float u2) {
  const float r = std::sqrt(u1);
  const float phi = 2.0f * kPi * u2;
  Vec3 t;
  Vec3 b;
  OrthonormalBasis(n, &t, &b);
  return Normalize(t * (r * std::cos(phi)) + b * (r * std::sin(phi)) +
                   n * std::sqrt(std::max(0.0f, 1.0f - u1)));
}

SurfaceHit ResolveSecondaryHit(const Scene& scene, const Ray& ray, const Hit& hit) {
  const Primitive& prim = scene.primitives[hit.primitive];
  SurfaceHit h;
  h.position = ray.origin + ray.direction * hit.t;
  h.back_face = Dot(hit.normal, ray.direction) > 0.0f;
  h.normal = h.back_face ? -hit.normal : hit.normal;
  h.surface = EvaluateMaterial(scene.materials[prim.material], h.position, h.normal,
                               0.05f + 0.05f * hit.t, prim.tint);
  h.origin = h.position + h.normal * RayEpsilon(hit.t);
  return h;
}

Vec3 SunOverPi(const Scene& scene, const Vec3& origin, const Vec3& normal) {
  const Lighting& l = scene.lighting;
  const float n_dot_l = Dot(normal, l.sun_direction);
  if (n_dot_l <= 0.0f || scene.bvh.Occluded(Ray{origin, l.sun_direction}, 0.0f, kMaxDistance)) {
    return Vec3();
  }
  return l.sun_irradiance * (n_dot_l / kPi);
}

}  // namespace fd::scenegen
