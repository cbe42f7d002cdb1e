// Small 3-vector math for the scene generator's ray tracer.
//
// Plain value type, header-only so the inner loops inline. Single precision:
// scenes are a few hundred metres across, where float is accurate to ~0.1 mm.
#ifndef FD_TOOLS_SCENEGEN_VEC3_H_
#define FD_TOOLS_SCENEGEN_VEC3_H_

#include <algorithm>
#include <cmath>

namespace fd::scenegen {

struct Vec3 {
  float x = 0.0f;
  float y = 0.0f;
  float z = 0.0f;

  constexpr Vec3() = default;
  constexpr Vec3(float x_in, float y_in, float z_in) : x(x_in), y(y_in), z(z_in) {}

  constexpr float operator[](int axis) const { return axis == 0 ? x : (axis == 1 ? y : z); }
  Vec3& operator+=(const Vec3& o) {
    x += o.x;
    y += o.y;
    z += o.z;
    return *this;
  }
  Vec3& operator*=(float s) {
    x *= s;
    y *= s;
    z *= s;
    return *this;
  }
};

constexpr Vec3 operator+(const Vec3& a, const Vec3& b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
constexpr Vec3 operator-(const Vec3& a, const Vec3& b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
constexpr Vec3 operator-(const Vec3& a) { return {-a.x, -a.y, -a.z}; }
constexpr Vec3 operator*(const Vec3& a, float s) { return {a.x * s, a.y * s, a.z * s}; }
constexpr Vec3 operator*(float s, const Vec3& a) { return {a.x * s, a.y * s, a.z * s}; }
// Component-wise product (colours).
constexpr Vec3 operator*(const Vec3& a, const Vec3& b) { return {a.x * b.x, a.y * b.y, a.z * b.z}; }
constexpr Vec3 operator/(const Vec3& a, float s) { return {a.x / s, a.y / s, a.z / s}; }

constexpr float Dot(const Vec3& a, const Vec3& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
constexpr Vec3 Cross(const Vec3& a, const Vec3& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline float Length(const Vec3& a) { return std::sqrt(Dot(a, a)); }
inline Vec3 Normalize(const Vec3& a) {
  const float len = Length(a);
  return len > 0.0f ? a / len : Vec3(0.0f, 0.0f, 1.0f);
}
inline Vec3 Min(const Vec3& a, const Vec3& b) {
  return {std::min(a.x, b.x), std::min(a.y, b.y), std::min(a.z, b.z)};
}
inline Vec3 Max(const Vec3& a, const Vec3& b) {
  return {std::max(a.x, b.x), std::max(a.y, b.y), std::max(a.z, b.z)};
}
constexpr Vec3 Lerp(const Vec3& a, const Vec3& b, float t) { return a + (b - a) * t; }
constexpr float Lerp(float a, float b, float t) { return a + (b - a) * t; }
constexpr float Clamp01(float v) { return v < 0.0f ? 0.0f : (v > 1.0f ? 1.0f : v); }
inline float SmoothStep(float edge0, float edge1, float v) {
  const float t = Clamp01((v - edge0) / (edge1 - edge0));
  return t * t * (3.0f - 2.0f * t);
}
// Luminance with Rec. 709 weights (linear light).
constexpr float Luminance(const Vec3& c) { return 0.2126f * c.x + 0.7152f * c.y + 0.0722f * c.z; }

// Any unit vector perpendicular to the unit vector n (Duff et al. 2017, branchless ONB).
inline void OrthonormalBasis(const Vec3& n, Vec3* tangent, Vec3* bitangent) {
  const float sign = std::copysign(1.0f, n.z);
  const float a = -1.0f / (sign + n.z);
  const float b = n.x * n.y * a;
  *tangent = Vec3(1.0f + sign * n.x * n.x * a, sign * b, -sign * n.x);
  *bitangent = Vec3(b, sign + n.y * n.y * a, -n.y);
}

struct Ray {
  Vec3 origin;
  Vec3 direction;  // unit length
};

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_VEC3_H_
