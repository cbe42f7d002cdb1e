#include "tools/scenegen/geometry.h"

#include <algorithm>
#include <cmath>
#include <numeric>

namespace fd::scenegen {
namespace {

bool IntersectBox(const Primitive& p, const Ray& ray, const Vec3& inv, float t_min, float t_max,
                  Hit* hit) {
  float t_near = -1e30f;
  float t_far = 1e30f;
  int near_axis = 0;
  int far_axis = 0;
  for (int axis = 0; axis < 3; ++axis) {
    float t0 = (p.lo[axis] - ray.origin[axis]) * inv[axis];
    float t1 = (p.hi[axis] - ray.origin[axis]) * inv[axis];
    if (t0 > t1) std::swap(t0, t1);
    if (t0 > t_near) {
      t_near = t0;
      near_axis = axis;
    }
    if (t1 < t_far) {
      t_far = t1;
      far_axis = axis;
    }
  }
  if (t_near > t_far) return false;
  // Entering the box, or (origin inside) leaving it.
  const bool entering = t_near > t_min;
  const float t = entering ? t_near : t_far;
  if (t <= t_min || t >= t_max) return false;
  const int axis = entering ? near_axis : far_axis;
  const float d = ray.direction[axis];
  const float sign = entering ? (d > 0.0f ? -1.0f : 1.0f) : (d > 0.0f ? 1.0f : -1.0f);
  hit->t = t;
  hit->normal = Vec3(axis == 0 ? sign : 0.0f, axis == 1 ? sign : 0.0f, axis == 2 ? sign : 0.0f);
  return true;
}

bool IntersectSphere(const Primitive& p, const Ray& ray, float t_min, float t_max, Hit* hit) {
  // Discriminant from the closest approach (Hearn & Baker): stays accurate
  // for small spheres seen from far away, where b*b - c would cancel.
  const Vec3 oc = ray.origin - p.lo;
  const float b = Dot(oc, ray.direction);
  const Vec3 closest = oc - ray.direction * b;
  const float disc = p.radius * p.radius - Dot(closest, closest);
  if (disc < 0.0f) return false;
  const float s = std::sqrt(disc);
  float t = -b - s;
  if (t <= t_min) t = -b + s;
  if (t <= t_min || t >= t_max) return false;
  hit->t = t;
  hit->normal = Normalize(oc + ray.direction * t);
  return true;
}

bool IntersectCylinder(const Primitive& p, const Ray& ray, float t_min, float t_max, Hit* hit) {
  const float ox = ray.origin.x - p.lo.x;
  const float oy = ray.origin.y - p.lo.y;
  const float dx = ray.direction.x;
  const float dy = ray.direction.y;
  const float dz = ray.direction.z;
  const float z_lo = p.lo.z;
  const float z_hi = p.lo.z + p.height;
  const float r2 = p.radius * p.radius;
  float best = t_max;
  bool found = false;
  const float a = dx * dx + dy * dy;
  if (a > 1e-12f) {
    // Side: the same closest-approach form as for spheres, in the XY plane
    // with the direction normalised there (t2 is distance in that plane).
    const float len = std::sqrt(a);
    const float ux = dx / len;
    const float uy = dy / len;
    const float b = ox * ux + oy * uy;
    const float cx = ox - ux * b;
    const float cy = oy - uy * b;
    const float disc = r2 - (cx * cx + cy * cy);
    if (disc >= 0.0f) {
      const float s = std::sqrt(disc);
      for (const float t2 : {-b - s, -b + s}) {
        const float t = t2 / len;
        if (t <= t_min || t >= best) continue;
        const float z = ray.origin.z + t * dz;
        if (z < z_lo || z > z_hi) continue;
        best = t;
        hit->normal = Normalize(Vec3(ox + t * dx, oy + t * dy, 0.0f));
        found = true;
        break;
      }
    }
  }
  if (std::fabs(dz) > 1e-12f) {
    for (const float zc : {z_lo, z_hi}) {
      const float t = (zc - ray.origin.z) / dz;
      if (t <= t_min || t >= best) continue;
      const float px = ox + t * dx;
      const float py = oy + t * dy;
      if (px * px + py * py > r2) continue;
      best = t;
      hit->normal = Vec3(0.0f, 0.0f, zc == z_hi ? 1.0f : -1.0f);
      found = true;
    }
  }
  if (found) hit->t = best;
  return found;
}

bool IntersectPrimitive(const Primitive& p, const Ray& ray, const Vec3& inv, float t_min,
                        float t_max, Hit* hit) {
  switch (p.shape) {
    case Shape::kBox:
      return IntersectBox(p, ray, inv, t_min, t_max, hit);
    case Shape::kSphere:
      return IntersectSphere(p, ray, t_min, t_max, hit);
    case Shape::kCylinder:
      return IntersectCylinder(p, ray, t_min, t_max, hit);
  }
  return false;
}

// Entry distance of the ray into the box, or +inf when it misses (t_min, t_max).
inline float SlabEntry(const Aabb& box, const Ray& ray, const Vec3& inv, float t_min, float t_max) {
  float t0 = (box.lo.x - ray.origin.x) * inv.x;
  float t1 = (box.hi.x - ray.origin.x) * inv.x;
  float lo = std::min(t0, t1);
  float hi = std::max(t0, t1);
  t0 = (box.lo.y - ray.origin.y) * inv.y;
  t1 = (box.hi.y - ray.origin.y) * inv.y;
  lo = std::max(lo, std::min(t0, t1));
  hi = std::min(hi, std::max(t0, t1));
  t0 = (box.lo.z - ray.origin.z) * inv.z;
  t1 = (box.hi.z - ray.origin.z) * inv.z;
  lo = std::max(lo, std::min(t0, t1));
  hi = std::min(hi, std::max(t0, t1));
  lo = std::max(lo, t_min);
  hi = std::min(hi, t_max);
  return lo <= hi ? lo : 1e30f;
}

inline float SafeInverse(float d) {
  return std::fabs(d) > 1e-20f ? 1.0f / d : std::copysign(1e30f, d);
}

Vec3 Centroid(const Aabb& b) { return (b.lo + b.hi) * 0.5f; }

float SurfaceArea(const Aabb& b) {
  const Vec3 d = Max(b.hi - b.lo, Vec3());
  return 2.0f * (d.x * d.y + d.y * d.z + d.z * d.x);
}

}  // namespace

Primitive MakeBox(const Vec3& lo, const Vec3& hi, int material) {
  Primitive p;
  p.shape = Shape::kBox;
  p.material = material;
  p.lo = Min(lo, hi);
  p.hi = Max(lo, hi);
  return p;
}

Primitive MakeSphere(const Vec3& centre, float radius, int material) {
  Primitive p;
  p.shape = Shape::kSphere;
  p.material = material;
  p.lo = centre;
  p.hi = centre;
  p.radius = radius;
  return p;
}

Primitive MakeCylinder(const Vec3& base, float radius, float height, int material) {
  Primitive p;
  p.shape = Shape::kCylinder;
  p.material = material;
  p.lo = base;
  p.hi = base;
  p.radius = radius;
  p.height = height;
  return p;
}

Aabb Bounds(const Primitive& p) {
  Aabb b;
  switch (p.shape) {
    case Shape::kBox:
      b.lo = p.lo;
      b.hi = p.hi;
      break;
    case Shape::kSphere:
      b.lo = p.lo - Vec3(p.radius, p.radius, p.radius);
      b.hi = p.lo + Vec3(p.radius, p.radius, p.radius);
      break;
    case Shape::kCylinder:
      b.lo = p.lo - Vec3(p.radius, p.radius, 0.0f);
      b.hi = p.lo + Vec3(p.radius, p.radius, p.height);
      break;
  }
  return b;
}

void Bvh::Build(const std::vector<Primitive>& primitives) {
  primitives_ = primitives;
  order_.resize(primitives_.size());
  std::iota(order_.begin(), order_.end(), 0);
  prim_boxes_.clear();
  for (const Primitive& p : primitives_) prim_boxes_.push_back(Bounds(p));
  nodes_.clear();
  if (primitives_.empty()) return;
  nodes_.reserve(2 * primitives_.size());
  nodes_.emplace_back();
  BuildInto(0, 0, static_cast<int>(order_.size()), 0);
}

// Fills node slot `index` with the subtree over order_[begin, end), split by
// the surface area heuristic (full sweep; scenes have ~1000 primitives).
// Children are allocated as a pair so the right child is always left + 1.
void Bvh::BuildInto(int index, int begin, int end, int depth) {
  Aabb box;
  for (int i = begin; i < end; ++i) box.Grow(prim_boxes_[order_[i]]);
  nodes_[index].box = box;
  const int count = end - begin;
  auto make_leaf = [&]() {
    nodes_[index].first = begin;
    nodes_[index].count = count;
  };
  // The depth cap bounds the traversal stack (kMaxDepth + 1 entries).
  if (count <= 2 || depth >= kMaxDepth) return make_leaf();

  // Cost model: traversing a node costs about one primitive test.
  constexpr float kTraversalCost = 1.0f;
  float best_cost = static_cast<float>(count);  // as a leaf, relative to SA(box)
  int best_axis = -1;
  int best_split = -1;
  std::vector<int> sorted(order_.begin() + begin, order_.begin() + end);
  std::vector<float> right_area(count);
  const float inv_area = 1.0f / std::max(SurfaceArea(box), 1e-12f);
  for (int axis = 0; axis < 3; ++axis) {
    // Ties broken by index: the tree never depends on the sort algorithm.
    std::sort(sorted.begin(), sorted.end(), [&](int a, int b) {
      const float ca = Centroid(prim_boxes_[a])[axis];
      const float cb = Centroid(prim_boxes_[b])[axis];
      return ca < cb || (ca == cb && a < b);
    });
    Aabb acc;
    for (int i = count - 1; i > 0; --i) {
      acc.Grow(prim_boxes_[sorted[i]]);
      right_area[i] = SurfaceArea(acc);
    }
    acc = Aabb();
    for (int i = 1; i < count; ++i) {  // left = [0, i), right = [i, count)
      acc.Grow(prim_boxes_[sorted[i - 1]]);
      const float cost =
          kTraversalCost + (SurfaceArea(acc) * i + right_area[i] * (count - i)) * inv_area;
      if (cost < best_cost) {
        best_cost = cost;
        best_axis = axis;
        best_split = i;
      }
    }
  }
  if (best_axis < 0) {
    if (count <= 4) return make_leaf();
    best_axis = 0;  // no split pays off, but keep leaves small: split in the middle
    best_split = count / 2;
  }
  std::sort(order_.begin() + begin, order_.begin() + end, [&](int a, int b) {
    const float ca = Centroid(prim_boxes_[a])[best_axis];
    const float cb = Centroid(prim_boxes_[b])[best_axis];
    return ca < cb || (ca == cb && a < b);
  });
  const int left = static_cast<int>(nodes_.size());
  nodes_[index].first = left;
  nodes_[index].count = 0;
  nodes_.emplace_back();
  nodes_.emplace_back();
  BuildInto(left, begin, begin + best_split, depth + 1);
  BuildInto(left + 1, begin + best_split, end, depth + 1);
}

template <bool kAnyHit>
bool Bvh::Traverse(const Ray& ray, float t_min, float t_max, Hit* hit) const {
  if (nodes_.empty()) return false;
  const Vec3 inv(SafeInverse(ray.direction.x), SafeInverse(ray.direction.y),
                 SafeInverse(ray.direction.z));
  struct Entry {
    int node;
    float t_entry;
  };
  Entry stack[kMaxDepth + 2];
  int size = 0;
  float closest = t_max;
  bool found = false;
  const float root_entry = SlabEntry(nodes_[0].box, ray, inv, t_min, closest);
  if (root_entry >= 1e30f) return false;
  stack[size++] = {0, root_entry};
  while (size > 0) {
    const Entry entry = stack[--size];
    if (entry.t_entry > closest) continue;
    const Node& node = nodes_[entry.node];
    if (node.count > 0) {
      for (int i = node.first; i < node.first + node.count; ++i) {
        Hit candidate;
        if (IntersectPrimitive(primitives_[order_[i]], ray, inv, t_min, closest, &candidate)) {
          if (kAnyHit) return true;
          closest = candidate.t;
          candidate.primitive = order_[i];
          *hit = candidate;
          found = true;
        }
      }
      continue;
    }
    const float t_left = SlabEntry(nodes_[node.first].box, ray, inv, t_min, closest);
    const float t_right = SlabEntry(nodes_[node.first + 1].box, ray, inv, t_min, closest);
    // Push the farther child first so the nearer one is visited first.
    if (t_left <= t_right) {
      if (t_right < 1e30f) stack[size++] = {node.first + 1, t_right};
      if (t_left < 1e30f) stack[size++] = {node.first, t_left};
    } else {
      if (t_left < 1e30f) stack[size++] = {node.first, t_left};
      if (t_right < 1e30f) stack[size++] = {node.first + 1, t_right};
    }
  }
  return found;
}

bool Bvh::Intersect(const Ray& ray, float t_min, float t_max, Hit* hit) const {
  return Traverse<false>(ray, t_min, t_max, hit);
}

bool Bvh::Occluded(const Ray& ray, float t_min, float t_max) const {
  Hit unused;
  return Traverse<true>(ray, t_min, t_max, &unused);
}

}  // namespace fd::scenegen
