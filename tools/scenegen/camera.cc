#include "tools/scenegen/camera.h"

#include <algorithm>
#include <cmath>
#include <utility>

namespace fd::scenegen {
namespace {

constexpr float kDegToRad = 3.14159265358979f / 180.0f;

// Uniform Catmull-Rom interpolation between p1 and p2.
template <typename T>
T CatmullRom(const T& p0, const T& p1, const T& p2, const T& p3, float u) {
  const float u2 = u * u;
  const float u3 = u2 * u;
  return (p1 * 2.0f + (p2 - p0) * u + (p0 * 2.0f - p1 * 5.0f + p2 * 4.0f - p3) * u2 +
          (p3 - p0 + p1 * 3.0f - p2 * 3.0f) * u3) *
         0.5f;
}

float PoseDistance(const CameraKey& a, const CameraKey& b) {
  const float turn = std::hypot(b.yaw_deg - a.yaw_deg, b.pitch_deg - a.pitch_deg) * kDegToRad;
  return Length(b.position - a.position) + CameraPath::kTurnMetresPerRadian * turn;
}

}  // namespace

Camera Camera::FromYawPitch(const Vec3& position, float yaw_deg, float pitch_deg, float fov_y_deg) {
  Camera c;
  c.position = position;
  c.yaw_deg = yaw_deg;
  c.pitch_deg = pitch_deg;
  c.fov_y_deg = fov_y_deg;
  const float yaw = yaw_deg * kDegToRad;
  const float pitch = pitch_deg * kDegToRad;
  c.forward =
      Vec3(std::cos(pitch) * std::cos(yaw), std::cos(pitch) * std::sin(yaw), std::sin(pitch));
  c.right = Vec3(std::sin(yaw), -std::cos(yaw), 0.0f);
  c.up = Cross(c.right, c.forward);
  return c;
}

Ray Camera::PrimaryRay(float px, float py, int width, int height) const {
  const float tan_half = std::tan(0.5f * fov_y_deg * kDegToRad);
  const float aspect = static_cast<float>(width) / static_cast<float>(height);
  const float sx = (2.0f * px / width - 1.0f) * tan_half * aspect;
  const float sy = (1.0f - 2.0f * py / height) * tan_half;
  return Ray{position, Normalize(forward + right * sx + up * sy)};
}

CameraPath::CameraPath(std::vector<CameraKey> keys, float step, float fov_y_deg)
    : keys_(std::move(keys)), step_(step), fov_y_deg_(fov_y_deg) {
  const int segments = static_cast<int>(keys_.size());
  cumulative_.assign(size_t(segments) * kSamples + 1, 0.0f);
  float total = 0.0f;
  for (int s = 0; s < segments; ++s) {
    CameraKey previous = Evaluate(s, 0.0f);
    for (int i = 1; i <= kSamples; ++i) {
      const CameraKey current = Evaluate(s, static_cast<float>(i) / kSamples);
      total += PoseDistance(previous, current);
      cumulative_[size_t(s) * kSamples + i] = total;
      previous = current;
    }
  }
  total_length_ = total;
}

CameraKey CameraPath::Evaluate(int segment, float u) const {
  const int n = static_cast<int>(keys_.size());
  auto key = [&](int i) -> const CameraKey& { return keys_[((i % n) + n) % n]; };
  // Yaw is unwrapped across the loop seam: keys after the last one continue
  // from its yaw, so closing a full turn does not spin back.
  auto yaw = [&](int i) {
    const int wraps = static_cast<int>(std::floor(static_cast<float>(i) / n));
    const float loop_turn = keys_.back().yaw_deg - keys_.front().yaw_deg;
    // A path that turns a net 360 deg per loop continues turning; otherwise
    // the seam is bridged directly.
    const float per_loop = std::round(loop_turn / 360.0f) * 360.0f;
    return key(i).yaw_deg + wraps * per_loop;
  };
  const CameraKey& k0 = key(segment - 1);
  const CameraKey& k1 = key(segment);
  const CameraKey& k2 = key(segment + 1);
  const CameraKey& k3 = key(segment + 2);
  CameraKey out;
  out.position = CatmullRom(k0.position, k1.position, k2.position, k3.position, u);
  out.yaw_deg = CatmullRom(yaw(segment - 1), yaw(segment), yaw(segment + 1), yaw(segment + 2), u);
  out.pitch_deg = CatmullRom(k0.pitch_deg, k1.pitch_deg, k2.pitch_deg, k3.pitch_deg, u);
  return out;
}

Camera CameraPath::At(int frame) const {
  // Double precision keeps long sequences exact: frame 100000 is 10 km away.
  double wrapped = std::fmod(static_cast<double>(frame) * step_, double{total_length_});
  if (wrapped < 0.0) wrapped += total_length_;
  const float s = static_cast<float>(wrapped);
  // First table entry with cumulative distance >= s.
  const auto it = std::lower_bound(cumulative_.begin(), cumulative_.end(), s);
  const size_t index =
      std::max<size_t>(1, std::min<size_t>(it - cumulative_.begin(), cumulative_.size() - 1));
  const float d0 = cumulative_[index - 1];
  const float d1 = cumulative_[index];
  const float local = d1 > d0 ? (s - d0) / (d1 - d0) : 0.0f;
  const int segment = static_cast<int>((index - 1) / kSamples);
  const float u = (static_cast<float>((index - 1) % kSamples) + local) / kSamples;
  const CameraKey pose = Evaluate(segment, u);
  return Camera::FromYawPitch(pose.position, pose.yaw_deg, pose.pitch_deg, fov_y_deg_);
}

}  // namespace fd::scenegen
