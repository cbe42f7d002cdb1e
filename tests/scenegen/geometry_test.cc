#include "tools/scenegen/geometry.h"

#include <gtest/gtest.h>

#include <cmath>

#include "tools/scenegen/random.h"
#include "tools/scenegen/scenes.h"

namespace fd::scenegen {
namespace {

Bvh BuildOne(const Primitive& p) {
  Bvh bvh;
  bvh.Build({p});
  return bvh;
}

TEST(GeometryTest, BoxHitFromOutsideAndInside) {
  const Bvh bvh = BuildOne(MakeBox({-1, -1, -1}, {1, 1, 1}, 0));
  Hit hit;
  ASSERT_TRUE(bvh.Intersect(Ray{{-5, 0, 0}, {1, 0, 0}}, 0.0f, 100.0f, &hit));
  EXPECT_FLOAT_EQ(hit.t, 4.0f);
  EXPECT_FLOAT_EQ(hit.normal.x, -1.0f);
  EXPECT_EQ(hit.primitive, 0);
  // From inside the ray leaves through the far face.
  ASSERT_TRUE(bvh.Intersect(Ray{{0, 0, 0}, {0, 0, 1}}, 0.0f, 100.0f, &hit));
  EXPECT_FLOAT_EQ(hit.t, 1.0f);
  EXPECT_FLOAT_EQ(hit.normal.z, 1.0f);
  EXPECT_FALSE(bvh.Intersect(Ray{{-5, 3, 0}, {1, 0, 0}}, 0.0f, 100.0f, &hit));
  EXPECT_FALSE(bvh.Intersect(Ray{{-5, 0, 0}, {1, 0, 0}}, 0.0f, 3.5f, &hit));  // beyond t_max
}

TEST(GeometryTest, SphereAndCylinderHits) {
  Hit hit;
  const Bvh sphere = BuildOne(MakeSphere({0, 0, 2}, 0.5f, 0));
  ASSERT_TRUE(sphere.Intersect(Ray{{0, 0, 0}, {0, 0, 1}}, 0.0f, 100.0f, &hit));
  EXPECT_NEAR(hit.t, 1.5f, 1e-5f);
  EXPECT_NEAR(hit.normal.z, -1.0f, 1e-5f);

  const Bvh cylinder = BuildOne(MakeCylinder({0, 0, 0}, 1.0f, 2.0f, 0));
  ASSERT_TRUE(cylinder.Intersect(Ray{{-3, 0, 1}, {1, 0, 0}}, 0.0f, 100.0f, &hit));  // side
  EXPECT_NEAR(hit.t, 2.0f, 1e-5f);
  EXPECT_NEAR(hit.normal.x, -1.0f, 1e-5f);
  ASSERT_TRUE(cylinder.Intersect(Ray{{0.5f, 0, 5}, {0, 0, -1}}, 0.0f, 100.0f, &hit));  // cap
  EXPECT_NEAR(hit.t, 3.0f, 1e-5f);
  EXPECT_NEAR(hit.normal.z, 1.0f, 1e-5f);
  EXPECT_FALSE(cylinder.Intersect(Ray{{-3, 0, 2.5f}, {1, 0, 0}}, 0.0f, 100.0f, &hit));
  EXPECT_TRUE(cylinder.Occluded(Ray{{-3, 0, 1}, {1, 0, 0}}, 0.0f, 100.0f));
}

// The BVH must return exactly what testing every primitive would.
TEST(GeometryTest, BvhMatchesBruteForceOnStreetScene) {
  const std::shared_ptr<const Scene> scene_ptr = *SharedScene("street", 17);
  const Scene& scene = *scene_ptr;
  std::vector<Bvh> singles(scene.primitives.size());
  for (size_t i = 0; i < scene.primitives.size(); ++i) singles[i].Build({scene.primitives[i]});
  PixelRng rng(99);
  int hits = 0;
  for (int r = 0; r < 400; ++r) {
    const Vec3 origin(rng.Uniform(-20, 20), rng.Uniform(-40, 60), rng.Uniform(0.5f, 20));
    const Vec3 dir = Normalize(Vec3(rng.Uniform(-1, 1), rng.Uniform(-1, 1), rng.Uniform(-1, 1)));
    const Ray ray{origin, dir};
    float best = 1e4f;
    int best_prim = -1;
    for (size_t i = 0; i < singles.size(); ++i) {
      Hit h;
      if (singles[i].Intersect(ray, 0.0f, best, &h)) {
        best = h.t;
        best_prim = static_cast<int>(i);
      }
    }
    Hit hit;
    const bool found = scene.bvh.Intersect(ray, 0.0f, 1e4f, &hit);
    ASSERT_EQ(found, best_prim >= 0) << "ray " << r;
    EXPECT_EQ(scene.bvh.Occluded(ray, 0.0f, 1e4f), found) << "ray " << r;
    if (found) {
      ++hits;
      EXPECT_FLOAT_EQ(hit.t, best) << "ray " << r;
    }
  }
  EXPECT_GT(hits, 100);  // the rays actually exercised the tree
}

}  // namespace
}  // namespace fd::scenegen
