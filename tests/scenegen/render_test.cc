#include <gtest/gtest.h>

#include <cmath>
#include <cstring>

#include "tests/scenegen/scenegen_test_util.h"
#include "tools/scenegen/encoding.h"
#include "tools/scenegen/renderer.h"
#include "tools/scenegen/scenes.h"

namespace fd::scenegen {
namespace {

Image8 RenderFinal(const Scene& scene, int frame, int threads = 2) {
  RenderSettings settings;
  settings.width = 64;
  settings.height = 64;
  settings.seed = 1;
  settings.threads = threads;
  const FrameBuffers b = RenderFrame(scene, scene.camera_path.At(frame), frame, settings);
  return EncodeFrame(b, {scene.lighting.exposure, scene.near_plane})[0];
}

// Consecutive frames overlap like a game camera: they differ far less than
// frames from different parts of the path.
TEST(RenderTest, ConsecutiveFramesOverlap) {
  for (const char* name : {"street", "room"}) {
    const std::shared_ptr<const Scene> scene_ptr = *SharedScene(name, 17);
    const Scene& scene = *scene_ptr;
    const int far_frame =
        static_cast<int>(0.4f * scene.camera_path.loop_length() / scene.camera_path.step());
    const Image8 f0 = RenderFinal(scene, 0);
    const Image8 f1 = RenderFinal(scene, 1);
    const Image8 f2 = RenderFinal(scene, 2);
    const Image8 far = RenderFinal(scene, far_frame);
    const double near_diff = std::max(testing::MeanAbsDiff(f0, f1), testing::MeanAbsDiff(f1, f2));
    const double far_diff = testing::MeanAbsDiff(f0, far);
    RecordProperty(std::string(name) + "_consecutive_mad", std::to_string(near_diff));
    RecordProperty(std::string(name) + "_far_mad", std::to_string(far_diff));
    EXPECT_LT(near_diff, 10.0) << name;
    EXPECT_LT(near_diff, 0.25 * far_diff) << name << " far frame " << far_frame;
  }
}

// Bit-identical float buffers for any thread count (no shared RNG state).
TEST(RenderTest, BuffersDoNotDependOnThreadCount) {
  const std::shared_ptr<const Scene> scene_ptr = *SharedScene("room", 17);
  const Scene& scene = *scene_ptr;
  RenderSettings settings;
  settings.width = 40;
  settings.height = 30;
  settings.seed = 9;
  const Camera camera = scene.camera_path.At(5);
  settings.threads = 1;
  const FrameBuffers a = RenderFrame(scene, camera, 5, settings);
  settings.threads = 3;
  const FrameBuffers b = RenderFrame(scene, camera, 5, settings);
  ASSERT_EQ(a.radiance.size(), b.radiance.size());
  EXPECT_EQ(std::memcmp(a.radiance.data(), b.radiance.data(), a.radiance.size() * sizeof(Vec3)), 0);
  EXPECT_EQ(a.view_depth, b.view_depth);
  EXPECT_EQ(a.geometry, b.geometry);
}

// The irradiance volume, too, is the same for any number of build threads.
TEST(RenderTest, SceneBuildDoesNotDependOnThreadCount) {
  const Scene one = *MakeScene("room", 5, 1);
  const Scene three = *MakeScene("room", 5, 3);
  RenderSettings settings;
  settings.width = 24;
  settings.height = 24;
  settings.threads = 2;
  const FrameBuffers a = RenderFrame(one, one.camera_path.At(0), 0, settings);
  const FrameBuffers b = RenderFrame(three, three.camera_path.At(0), 0, settings);
  EXPECT_EQ(std::memcmp(a.radiance.data(), b.radiance.data(), a.radiance.size() * sizeof(Vec3)), 0);
  EXPECT_GT(one.irradiance.valid_probe_count(), one.irradiance.probe_count() / 2);
}

// A tiny scene: a ground slab and a floating roof under a high sun. The
// ground under the roof is in shadow but still lit by the sky; the sky
// itself is brighter at the horizon than at the zenith.
TEST(RenderTest, SunCastsShadowsAndSkyFillsThem) {
  Scene scene;
  Material grey;
  grey.color_a = grey.color_b = Vec3(0.5f, 0.5f, 0.5f);
  grey.roughness_a = grey.roughness_b = 0.9f;
  const int m = scene.AddMaterial(grey);
  scene.Add(MakeBox({-50, -50, -1}, {50, 50, 0}, m));
  scene.Add(MakeBox({-1, 4, 2}, {1, 6, 2.2f}, m));  // roof over (0, 5)
  scene.lighting.sun_direction = Vec3(0, 0, 1);
  scene.probe_grid.lo = Vec3(-6, -2, 0.5f);
  scene.probe_grid.hi = Vec3(6, 10, 4.5f);
  scene.probe_grid.spacing = 1.0f;
  scene.Finalize(2);
  // A camera 1 m above the ground looking along +Y, slightly down, at the roof.
  RenderSettings settings;
  settings.width = 64;
  settings.height = 64;
  settings.threads = 2;
  settings.ao_samples = 8;
  const Camera camera = Camera::FromYawPitch({0, 0, 1.0f}, 90.0f, -12.0f, 60.0f);
  const FrameBuffers b = RenderFrame(scene, camera, 0, settings);
  // Find a lit and a shadowed ground pixel by casting the same rays.
  float lit = -1.0f;
  float shadowed = -1.0f;
  for (int y = 0; y < 64; ++y) {
    for (int x = 0; x < 64; ++x) {
      const size_t i = b.Index(x, y);
      if (!b.geometry[i] || b.normal[i].z < 0.99f) continue;
      const Ray ray = camera.PrimaryRay(x + 0.5f, y + 0.5f, 64, 64);
      Hit hit;
      ASSERT_TRUE(scene.bvh.Intersect(ray, 0.0f, 1e4f, &hit));
      const Vec3 p = ray.origin + ray.direction * hit.t;
      if (p.z > 0.5f) continue;  // the roof's top
      const bool under_roof = std::fabs(p.x) < 0.8f && p.y > 4.2f && p.y < 5.8f;
      const bool open = std::fabs(p.y - 5.0f) > 2.0f && std::fabs(p.x) < 2.0f;
      const float l = Luminance(b.radiance[i]);
      if (under_roof) shadowed = std::max(shadowed, l);
      if (open) lit = std::max(lit, l);
    }
  }
  ASSERT_GT(lit, 0.0f);
  ASSERT_GT(shadowed, 0.0f) << "sky light must reach the shadow";
  EXPECT_GT(lit, 2.0f * shadowed);
}

TEST(RenderTest, SkyIsAGradientWithASun) {
  const std::shared_ptr<const Scene> scene_ptr = *SharedScene("street", 17);
  const Scene& scene = *scene_ptr;
  const Vec3 sun = scene.lighting.sun_direction;
  const Vec3 away = Normalize(Vec3(-sun.x, -sun.y, 0.05f));
  const Vec3 sky_zenith = scene.SkyRadiance(Vec3(0, 0, 1), false);
  const Vec3 sky_horizon = scene.SkyRadiance(away, false);
  EXPECT_GT(Luminance(sky_horizon), Luminance(sky_zenith));  // brighter towards the horizon
  EXPECT_GT(sky_zenith.z, sky_zenith.x);                     // and blue overhead
  EXPECT_GT(Luminance(scene.SkyRadiance(sun, true)), 10.0f * Luminance(sky_horizon));
}

}  // namespace
}  // namespace fd::scenegen
