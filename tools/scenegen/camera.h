// Pinhole camera and smooth, looping camera paths.
//
// A path is a closed Catmull-Rom spline through key poses (position, yaw,
// pitch), walked at constant speed: frame k is at distance k * step along the
// loop, where turning counts as distance too (kTurnMetresPerRadian), so a turn
// on the spot also takes several frames. Frame k is therefore the same pose no
// matter how many frames are generated, and consecutive frames overlap like
// a game camera moving at walking pace.
#ifndef FD_TOOLS_SCENEGEN_CAMERA_H_
#define FD_TOOLS_SCENEGEN_CAMERA_H_

#include <vector>

#include "tools/scenegen/vec3.h"

namespace fd::scenegen {

struct Camera {
  Vec3 position;
  Vec3 forward;            // unit view direction
  Vec3 right;              // unit, horizontal
  Vec3 up;                 // unit, completes the right-handed frame
  float yaw_deg = 0.0f;    // heading in the XY plane, counter-clockwise from +X
  float pitch_deg = 0.0f;  // elevation above the horizon
  float fov_y_deg = 60.0f;

  // Builds the frame from position, yaw and pitch (Z up).
  static Camera FromYawPitch(const Vec3& position, float yaw_deg, float pitch_deg, float fov_y_deg);
  // Ray through the image-plane point (px, py) in pixels, (0, 0) = top-left
  // corner of the image, for an image of width x height pixels.
  Ray PrimaryRay(float px, float py, int width, int height) const;
};

struct CameraKey {
  Vec3 position;
  float yaw_deg = 0.0f;
  float pitch_deg = 0.0f;
};

class CameraPath {
 public:
  // How many metres of travel one radian of turning counts as.
  static constexpr float kTurnMetresPerRadian = 2.0f;

  CameraPath() = default;
  // keys: at least 2 key poses of a closed loop (the last connects back to
  // the first; yaw is unwrapped so consecutive keys differ by < 180 deg).
  // step: path distance per frame in metres.
  CameraPath(std::vector<CameraKey> keys, float step, float fov_y_deg);

  Camera At(int frame) const;
  float step() const { return step_; }
  float loop_length() const { return total_length_; }

 private:
  CameraKey Evaluate(int segment, float u) const;

  std::vector<CameraKey> keys_;
  float step_ = 0.1f;
  float fov_y_deg_ = 60.0f;
  // Arc-length table: cumulative_[segment * kSamples + i] is the distance at
  // parameter u = i / kSamples of that segment.
  static constexpr int kSamples = 64;
  std::vector<float> cumulative_;
  float total_length_ = 0.0f;
};

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_CAMERA_H_
