#include "tools/scenegen/camera.h"

#include <gtest/gtest.h>

#include <cmath>

#include "tools/scenegen/scenes.h"

namespace fd::scenegen {
namespace {

constexpr float kRadToDeg = 57.2957795f;

TEST(CameraTest, FrameIsOrthonormalAndRaysPointForward) {
  const Camera c = Camera::FromYawPitch({1, 2, 3}, 30.0f, -10.0f, 60.0f);
  EXPECT_NEAR(Length(c.forward), 1.0f, 1e-5f);
  EXPECT_NEAR(Length(c.right), 1.0f, 1e-5f);
  EXPECT_NEAR(Length(c.up), 1.0f, 1e-5f);
  EXPECT_NEAR(Dot(c.forward, c.right), 0.0f, 1e-5f);
  EXPECT_NEAR(Dot(c.forward, c.up), 0.0f, 1e-5f);
  EXPECT_NEAR(c.right.z, 0.0f, 1e-6f);  // no roll
  EXPECT_GT(c.up.z, 0.0f);
  const Ray centre = c.PrimaryRay(32.0f, 32.0f, 64, 64);
  EXPECT_NEAR(Dot(centre.direction, c.forward), 1.0f, 1e-5f);
  // Top-left pixel looks up and to the left.
  const Ray corner = c.PrimaryRay(0.0f, 0.0f, 64, 64);
  EXPECT_GT(Dot(corner.direction, c.up), 0.0f);
  EXPECT_LT(Dot(corner.direction, c.right), 0.0f);
}

// Consecutive frames move by about one step (position plus turning), never
// jump, including across the loop's seam.
TEST(CameraTest, PathsAreSmoothAndLoop) {
  for (const char* name : {"street", "room"}) {
    const std::shared_ptr<const Scene> scene_ptr = *SharedScene(name, 17);
    const Scene& scene = *scene_ptr;
    const CameraPath& path = scene.camera_path;
    const int loop_frames = static_cast<int>(path.loop_length() / path.step());
    ASSERT_GT(loop_frames, 100) << name;
    Camera previous = path.At(0);
    for (int k = 1; k <= loop_frames + 50; ++k) {
      const Camera c = path.At(k);
      const float moved = Length(c.position - previous.position);
      float yaw = std::fmod(std::fabs(c.yaw_deg - previous.yaw_deg), 360.0f);
      yaw = std::min(yaw, 360.0f - yaw);
      const float turned = std::hypot(yaw, c.pitch_deg - previous.pitch_deg);
      ASSERT_LT(moved, 1.2f * path.step()) << name << " frame " << k;
      ASSERT_LT(turned, 1.2f * path.step() / CameraPath::kTurnMetresPerRadian * kRadToDeg)
          << name << " frame " << k;
      previous = c;
    }
  }
}

}  // namespace
}  // namespace fd::scenegen
