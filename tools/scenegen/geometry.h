// Scene primitives (axis-aligned boxes, spheres, Z-axis cylinders) and a
// bounding volume hierarchy for ray queries.
//
// The world is right-handed with Z up, in metres. Axis-aligned shapes are
// enough for streets and rooms and keep intersection code short and fast.
#ifndef FD_TOOLS_SCENEGEN_GEOMETRY_H_
#define FD_TOOLS_SCENEGEN_GEOMETRY_H_

#include <cstdint>
#include <vector>

#include "tools/scenegen/vec3.h"

namespace fd::scenegen {

enum class Shape : uint8_t { kBox, kSphere, kCylinder };

struct Primitive {
  Shape shape = Shape::kBox;
  int material = 0;   // index into Scene::materials
  uint32_t tint = 0;  // per-object hash for colour variation in patterns
  Vec3 lo;            // box: min corner; sphere: centre; cylinder: base centre
  Vec3 hi;            // box: max corner; unused otherwise
  float radius = 0.0f;
  float height = 0.0f;  // cylinder only
};

Primitive MakeBox(const Vec3& lo, const Vec3& hi, int material);
Primitive MakeSphere(const Vec3& centre, float radius, int material);
// Capped cylinder standing on `base` (its bottom centre), axis +Z.
Primitive MakeCylinder(const Vec3& base, float radius, float height, int material);

struct Aabb {
  Vec3 lo{1e30f, 1e30f, 1e30f};
  Vec3 hi{-1e30f, -1e30f, -1e30f};
  void Grow(const Aabb& o) {
    lo = Min(lo, o.lo);
    hi = Max(hi, o.hi);
  }
};
Aabb Bounds(const Primitive& p);

struct Hit {
  float t = 0.0f;
  Vec3 normal;  // geometric outward normal, unit length
  int primitive = -1;
};

// Ray query structure over a primitive list. Immutable after Build(), so
// concurrent queries from many threads are safe.
class Bvh {
 public:
  // Copies the primitives; primitive indices in Hit refer to `primitives`.
  void Build(const std::vector<Primitive>& primitives);

  // Closest hit with t in (t_min, t_max); false when nothing is hit.
  bool Intersect(const Ray& ray, float t_min, float t_max, Hit* hit) const;
  // True when anything blocks the ray in (t_min, t_max) (shadow rays).
  bool Occluded(const Ray& ray, float t_min, float t_max) const;

 private:
  struct Node {
    Aabb box;
    int first = 0;  // leaf: first index into order_; inner: left child (right = first + 1)
    int count = 0;  // leaf: number of primitives; inner: 0
  };
  static constexpr int kMaxDepth = 60;
  void BuildInto(int index, int begin, int end, int depth);
  template <bool kAnyHit>
  bool Traverse(const Ray& ray, float t_min, float t_max, Hit* hit) const;

  std::vector<Primitive> primitives_;
  std::vector<int> order_;
  std::vector<Aabb> prim_boxes_;
  std::vector<Node> nodes_;
};

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_GEOMETRY_H_
