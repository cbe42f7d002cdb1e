#include "tools/scenegen/material.h"

#include <cmath>

namespace fd::scenegen {
namespace {

// 32-bit integer hash (Chris Wellons' lowbias32): cheap enough for noise.
inline uint32_t Hash32(uint32_t x) {
  x ^= x >> 16;
  x *= 0x7feb352du;
  x ^= x >> 15;
  x *= 0x846ca68bu;
  x ^= x >> 16;
  return x;
}

inline uint32_t HashCell(int a, int b, int c, uint32_t salt) {
  return Hash32(static_cast<uint32_t>(a) * 0x8da6b343u ^
                Hash32(static_cast<uint32_t>(b) * 0xd8163841u ^
                       Hash32(static_cast<uint32_t>(c) * 0xcb1ab31fu ^ salt)));
}

inline float UnitFromHash(uint32_t h) { return static_cast<float>(h >> 8) * (1.0f / 16777216.0f); }

inline float Fract(float x) { return x - std::floor(x); }

// Texture-space coordinates on the plane most facing the normal; v points up
// on walls so bricks and windows stand upright.
void PlanarCoords(const Vec3& p, const Vec3& n, float* u, float* v, bool* horizontal) {
  const float ax = std::fabs(n.x);
  const float ay = std::fabs(n.y);
  const float az = std::fabs(n.z);
  *horizontal = az >= ax && az >= ay;
  if (*horizontal) {
    *u = p.x;
    *v = p.y;
  } else if (ax >= ay) {
    *u = p.y;
    *v = p.z;
  } else {
    *u = p.x;
    *v = p.z;
  }
}

// Coverage of lines of half-width `half_width` repeating every `period`
// (metres) at coordinate c, box-filtered by footprint w.
float LineMask(float c, float period, float half_width, float w) {
  const float d = std::fabs(c - period * std::round(c / period));
  const float sharp = 1.0f - SmoothStep(half_width - 0.5f * w, half_width + 0.5f * w + 1e-6f, d);
  const float average = std::min(1.0f, 2.0f * half_width / period);
  return Lerp(sharp, average, SmoothStep(0.25f * period, 0.75f * period, w));
}

// Inigo Quilez' analytically box-filtered checkerboard (cell size 1).
float FilteredChecker(float u, float v, float w) {
  w = std::max(w, 1e-4f);
  auto integral = [w](float x) {
    return 2.0f *
           (std::fabs(Fract((x - 0.5f * w) * 0.5f) - 0.5f) -
            std::fabs(Fract((x + 0.5f * w) * 0.5f) - 0.5f)) /
           w;
  };
  return 0.5f - 0.5f * integral(u) * integral(v);
}

// Filtered indicator of x in [lo, hi] within a unit cell (x in [0, 1)).
float PulseMask(float x, float lo, float hi, float w) {
  return SmoothStep(lo - 0.5f * w, lo + 0.5f * w + 1e-6f, x) *
         (1.0f - SmoothStep(hi - 0.5f * w, hi + 0.5f * w + 1e-6f, x));
}

struct PatternResult {
  float mask = 0.0f;        // 0 = part A, 1 = part B
  float brightness = 1.0f;  // multiplicative per-cell jitter
};

PatternResult Bricks(const Material& m, float u, float v, float w, uint32_t tint, bool tiles) {
  const float h = m.scale;
  const float width = tiles ? h : 2.0f * h;
  const float row = std::floor(v / h);
  const bool odd = (static_cast<int64_t>(row) & 1) != 0;
  const float uu = u + (!tiles && odd ? 0.5f * width : 0.0f);
  const float col = std::floor(uu / width);
  const float half_width = (tiles ? 0.03f : 0.06f) * h;
  const float mortar = std::max(LineMask(v, h, half_width, w), LineMask(uu, width, half_width, w));
  const float fade = SmoothStep(0.25f * h, 0.75f * h, w);
  const float jitter =
      UnitFromHash(HashCell(static_cast<int>(row), static_cast<int>(col), 17, tint)) - 0.5f;
  return {mortar, 1.0f + 2.0f * m.variation * jitter * (1.0f - fade)};
}

PatternResult Planks(const Material& m, float u, float v, float w, uint32_t tint) {
  const float width = m.scale;
  const float length = 6.0f * width;
  const float row = std::floor(v / width);
  const float offset = UnitFromHash(HashCell(static_cast<int>(row), 0, 29, tint)) * length;
  const float uu = u + offset;
  const float col = std::floor(uu / length);
  const float fade = SmoothStep(0.25f * width, 0.75f * width, w);
  const float pick = UnitFromHash(HashCell(static_cast<int>(row), static_cast<int>(col), 31, tint));
  // Grain: noise stretched along the plank.
  const float grain = FilteredFbm(Vec3(uu * 0.7f, v * 12.0f, row * 3.1f), w * 12.0f, 3);
  const float seam =
      std::max(LineMask(v, width, 0.004f, w), LineMask(uu, length, 0.004f, w)) * (1.0f - fade);
  const float mask = Lerp(pick, 0.5f, fade);
  return {mask, (1.0f + 2.0f * m.variation * (grain - 0.5f)) * (1.0f - 0.6f * seam)};
}

PatternResult Facade(const Material& m, float u, float v, float w, uint32_t tint, bool horizontal) {
  if (horizontal) return {0.0f, 1.0f};  // roofs and soffits have no windows
  const float storey = m.scale;
  const float bay = 0.9f * m.scale;
  const float cu = Fract(u / bay);
  const float cv = Fract(v / storey);
  const float wu = w / bay;
  const float sharp = PulseMask(cu, 0.22f, 0.78f, wu) * PulseMask(cv, 0.3f, 0.82f, w / storey);
  const float fade = SmoothStep(0.2f, 0.6f, wu);
  const float jitter = UnitFromHash(HashCell(static_cast<int>(std::floor(u / bay)),
                                             static_cast<int>(std::floor(v / storey)), 41, tint)) -
                       0.5f;
  const float mask = Lerp(sharp, 0.56f * 0.52f, fade);
  return {mask, 1.0f + 2.0f * m.variation * jitter * mask * (1.0f - fade)};
}

}  // namespace

float ValueNoise(const Vec3& p) {
  const float fx = std::floor(p.x);
  const float fy = std::floor(p.y);
  const float fz = std::floor(p.z);
  const int ix = static_cast<int>(fx);
  const int iy = static_cast<int>(fy);
  const int iz = static_cast<int>(fz);
  float tx = p.x - fx;
  float ty = p.y - fy;
  float tz = p.z - fz;
  tx = tx * tx * (3.0f - 2.0f * tx);
  ty = ty * ty * (3.0f - 2.0f * ty);
  tz = tz * tz * (3.0f - 2.0f * tz);
  auto corner = [&](int dx, int dy, int dz) {
    return UnitFromHash(HashCell(ix + dx, iy + dy, iz + dz, 0x9e3779b9u));
  };
  const float x00 = Lerp(corner(0, 0, 0), corner(1, 0, 0), tx);
  const float x10 = Lerp(corner(0, 1, 0), corner(1, 1, 0), tx);
  const float x01 = Lerp(corner(0, 0, 1), corner(1, 0, 1), tx);
  const float x11 = Lerp(corner(0, 1, 1), corner(1, 1, 1), tx);
  return Lerp(Lerp(x00, x10, ty), Lerp(x01, x11, ty), tz);
}

float FilteredFbm(const Vec3& p, float footprint, int max_octaves) {
  float sum = 0.0f;
  float total = 0.0f;
  float amplitude = 1.0f;
  float frequency = 1.0f;
  for (int i = 0; i < max_octaves; ++i) {
    // An octave fades to its mean (0.5) as its period approaches the footprint.
    const float keep = 1.0f - SmoothStep(0.25f, 0.5f, frequency * footprint);
    if (keep <= 0.0f) {
      sum += amplitude * 0.5f;
    } else {
      const Vec3 q = p * frequency + Vec3(17.1f * i, 31.7f * i, 47.3f * i);
      sum += amplitude * Lerp(0.5f, ValueNoise(q), keep);
    }
    total += amplitude;
    amplitude *= 0.5f;
    frequency *= 2.0f;
  }
  return sum / total;
}

SurfaceSample EvaluateMaterial(const Material& m, const Vec3& p, const Vec3& n, float footprint,
                               uint32_t tint) {
  float u = 0.0f;
  float v = 0.0f;
  bool horizontal = false;
  PlanarCoords(p, n, &u, &v, &horizontal);
  const float w = std::max(footprint, 1e-4f);
  PatternResult r;
  switch (m.pattern) {
    case Pattern::kSolid:
      break;
    case Pattern::kChecker:
      r.mask = FilteredChecker(u / m.scale, v / m.scale, w / m.scale);
      break;
    case Pattern::kBricks:
      r = Bricks(m, u, v, w, tint, /*tiles=*/false);
      break;
    case Pattern::kTiles:
      r = Bricks(m, u, v, w, tint, /*tiles=*/true);
      break;
    case Pattern::kPlanks:
      r = Planks(m, u, v, w, tint);
      break;
    case Pattern::kNoise:
      r.mask = SmoothStep(0.3f, 0.7f, FilteredFbm(p / m.scale, w / m.scale, 5));
      break;
    case Pattern::kFacade:
      r = Facade(m, u, v, w, tint, horizontal);
      break;
  }
  SurfaceSample s;
  s.albedo = Lerp(m.color_a, m.color_b, r.mask) * r.brightness;
  s.roughness = Lerp(m.roughness_a, m.roughness_b, r.mask);
  s.metallic = Lerp(m.metallic_a, m.metallic_b, r.mask);
  if (m.grime > 0.0f) {
    const float g = FilteredFbm(p * (1.0f / 2.5f), w / 2.5f, 4);
    s.albedo = s.albedo * (1.0f - m.grime * SmoothStep(0.35f, 0.8f, g));
    s.roughness = std::min(1.0f, s.roughness + 0.2f * m.grime * g);
  }
  s.albedo = Vec3(Clamp01(s.albedo.x), Clamp01(s.albedo.y), Clamp01(s.albedo.z));
  s.roughness = Clamp01(s.roughness);
  s.metallic = Clamp01(s.metallic);
  return s;
}

}  // namespace fd::scenegen
