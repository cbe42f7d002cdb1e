#include "tools/scenegen/irradiance_volume.h"

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "tools/scenegen/parallel.h"
#include "tools/scenegen/random.h"
#include "tools/scenegen/scene.h"
#include "tools/scenegen/shading.h"

namespace fd::scenegen {
namespace {

// Probes with more rays than this hitting back faces sit inside geometry.
constexpr float kMaxBackFaceFraction = 0.2f;
constexpr float kGoldenAngle = 2.39996323f;

const Vec3 kAxes[6] = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}};

// What one probe ray saw; traced once, re-shaded for every bounce.
struct RayRecord {
  enum Kind : uint8_t { kSky, kFront, kBack };
  Kind kind = kSky;
  Vec3 position;  // hit point (kFront)
  Vec3 normal;    // facing the probe (kFront)
  Vec3 albedo;    // diffuse albedo (kFront)
  Vec3 radiance;  // kSky: sky radiance; kFront: sun irradiance / pi
};

// Direction of ray r of n around probe `index`: a spherical Fibonacci set,
// rotated about Z by a per-probe angle so neighbouring probes do not share
// the same gaps (which would show as banding).
Vec3 ProbeRayDirection(int index, int r, int n) {
  const float phase = 6.2831853f * HashToUnitFloat(HashInts(0x9B0BEull, uint64_t(index)));
  const float z = 1.0f - (2.0f * r + 1.0f) / n;
  const float radius = std::sqrt(std::max(0.0f, 1.0f - z * z));
  const float phi = r * kGoldenAngle + phase;
  return Vec3(radius * std::cos(phi), radius * std::sin(phi), z);
}

// Weighted sum of an ambient cube for unit normal n.
template <typename T>
T CubeEval(const T cube[6], const Vec3& n) {
  return cube[n.x >= 0.0f ? 0 : 1] * (n.x * n.x) + cube[n.y >= 0.0f ? 2 : 3] * (n.y * n.y) +
         cube[n.z >= 0.0f ? 4 : 5] * (n.z * n.z);
}

}  // namespace

int IrradianceVolume::valid_probe_count() const {
  return static_cast<int>(
      std::count_if(probes_.begin(), probes_.end(), [](const Probe& p) { return p.valid; }));
}

void IrradianceVolume::Build(const Scene& scene, const ProbeGridSpec& spec, int threads) {
  lo_ = spec.lo;
  float extent[3];
  for (int a = 0; a < 3; ++a) {
    extent[a] = std::max(spec.hi[a] - spec.lo[a], 1e-3f);
    dims_[a] = std::max(2, static_cast<int>(std::lround(extent[a] / spec.spacing)) + 1);
  }
  cell_ = Vec3(extent[0] / (dims_[0] - 1), extent[1] / (dims_[1] - 1), extent[2] / (dims_[2] - 1));
  const int count = dims_[0] * dims_[1] * dims_[2];
  probes_.assign(count, Probe());
  const int rays = std::max(6, spec.rays);
  const float max_distance = 4.0f * std::max(cell_.x, std::max(cell_.y, cell_.z));
  std::vector<RayRecord> records(size_t(count) * rays);

  // Pass 1: trace every probe's rays once; classify probes and record the
  // distance moments used to reject probes behind walls.
  ParallelFor(count, threads, [&](int index) {
    Probe& probe = probes_[index];
    const int i = index % dims_[0];
    const int j = (index / dims_[0]) % dims_[1];
    const int k = index / (dims_[0] * dims_[1]);
    probe.position = lo_ + Vec3(i * cell_.x, j * cell_.y, k * cell_.z);
    int back_faces = 0;
    float weight[6] = {0, 0, 0, 0, 0, 0};
    for (int r = 0; r < rays; ++r) {
      const Ray ray{probe.position, ProbeRayDirection(index, r, rays)};
      RayRecord& rec = records[size_t(index) * rays + r];
      Hit hit;
      float distance = max_distance;
      if (!scene.bvh.Intersect(ray, 0.0f, kMaxDistance, &hit)) {
        rec.kind = RayRecord::kSky;
        rec.radiance = scene.SkyRadiance(ray.direction, /*include_sun_disk=*/false);
      } else {
        const SurfaceHit h = ResolveSecondaryHit(scene, ray, hit);
        distance = std::min(hit.t, max_distance);
        if (h.back_face) {
          rec.kind = RayRecord::kBack;
          ++back_faces;
        } else {
          rec.kind = RayRecord::kFront;
          rec.position = h.position;
          rec.normal = h.normal;
          rec.albedo = DiffuseAlbedo(h.surface);
          rec.radiance = SunOverPi(scene, h.origin, h.normal);
        }
      }
      for (int f = 0; f < 6; ++f) {
        const float c = Dot(ray.direction, kAxes[f]);
        if (c <= 0.0f) continue;
        const float w = c * c;
        weight[f] += w;
        probe.mean[f] += w * distance;
        probe.mean2[f] += w * distance * distance;
      }
    }
    for (int f = 0; f < 6; ++f) {
      if (weight[f] <= 0.0f) continue;
      probe.mean[f] /= weight[f];
      probe.mean2[f] /= weight[f];
    }
    probe.valid = back_faces <= kMaxBackFaceFraction * rays;
  });

  // Which neighbouring probes see each other (link from index to index + 1
  // along each axis): smoothing only mixes probes in the same space.
  std::vector<uint8_t> linked[3];
  const int strides[3] = {1, dims_[0], dims_[0] * dims_[1]};
  for (int a = 0; a < 3; ++a) {
    linked[a].assign(count, 0);
    ParallelFor(count, threads, [&](int index) {
      const int coord =
          a == 0 ? index % dims_[0] : (a == 1 ? (index / dims_[0]) % dims_[1] : index / strides[2]);
      if (coord + 1 >= dims_[a]) return;
      const Probe& from = probes_[index];
      const Probe& to = probes_[index + strides[a]];
      if (!from.valid || !to.valid) return;
      const Vec3 offset = to.position - from.position;
      const float length = Length(offset);
      linked[a][index] = !scene.bvh.Occluded(Ray{from.position, offset / length}, 0.0f, length);
    });
  }
  // Separable [1 2 1] smoothing of the cubes along linked neighbours: probes
  // see small sun patches with few rays each, and the smoothing removes that
  // probe-to-probe noise (the light field is smooth at the grid's scale).
  auto smooth = [&]() {
    for (int a = 0; a < 3; ++a) {
      std::vector<Probe> source = probes_;
      ParallelFor(count, threads, [&](int index) {
        if (!source[index].valid) return;
        Vec3 sum[6];
        float weight = 2.0f;
        for (int f = 0; f < 6; ++f) sum[f] = source[index].cube[f] * 2.0f;
        if (index - strides[a] >= 0 && linked[a][index - strides[a]]) {
          for (int f = 0; f < 6; ++f) sum[f] += source[index - strides[a]].cube[f];
          weight += 1.0f;
        }
        if (linked[a][index]) {
          for (int f = 0; f < 6; ++f) sum[f] += source[index + strides[a]].cube[f];
          weight += 1.0f;
        }
        for (int f = 0; f < 6; ++f) probes_[index].cube[f] = sum[f] / weight;
      });
    }
  };

  // Bounces: shade the recorded hits with the previous bounce's volume (the
  // scene's fill radiance before the first) and gather ambient cubes.
  const float fill = scene.lighting.secondary_fill;
  const Vec3 fill_irradiance = Vec3(fill, fill, fill) * kPi;
  const float solid_angle = 4.0f * kPi / rays;
  for (int bounce = 0; bounce < std::max(1, spec.bounces); ++bounce) {
    const IrradianceVolume previous = *this;
    ParallelFor(count, threads, [&](int index) {
      Probe& probe = probes_[index];
      for (Vec3& face : probe.cube) face = Vec3();
      if (!probe.valid) return;
      for (int r = 0; r < rays; ++r) {
        const RayRecord& rec = records[size_t(index) * rays + r];
        Vec3 radiance;
        if (rec.kind == RayRecord::kSky) {
          radiance = rec.radiance;
        } else if (rec.kind == RayRecord::kFront) {
          const Vec3 incoming =
              bounce == 0 ? fill_irradiance
                          : previous.Irradiance(rec.position, rec.normal, fill_irradiance);
          radiance = rec.albedo * (rec.radiance + incoming / kPi);
        } else {
          continue;
        }
        const Vec3 dir = ProbeRayDirection(index, r, rays);
        for (int f = 0; f < 6; ++f) {
          const float c = Dot(dir, kAxes[f]);
          if (c > 0.0f) probe.cube[f] += radiance * (c * solid_angle);
        }
      }
    });
    smooth();
  }
}

Vec3 IrradianceVolume::Irradiance(const Vec3& surface_point, const Vec3& n,
                                  const Vec3& fallback) const {
  if (probes_.empty()) return fallback;
  // Look up from half a cell in front of the surface (DDGI's normal bias):
  // probes just beside the point then pass the visibility test smoothly
  // instead of only the nearest one, which would show the grid.
  const float min_cell = std::min(cell_.x, std::min(cell_.y, cell_.z));
  const Vec3 p = surface_point + n * (0.5f * min_cell);
  const float variance_floor = 0.01f * min_cell * min_cell;
  int base[3];
  float frac[3];
  for (int a = 0; a < 3; ++a) {
    const float g = std::clamp((p[a] - lo_[a]) / cell_[a], 0.0f, float(dims_[a] - 1));
    base[a] = std::min(static_cast<int>(g), dims_[a] - 2);
    frac[a] = g - base[a];
  }
  Vec3 sum;
  float weight_sum = 0.0f;
  for (int corner = 0; corner < 8; ++corner) {
    const int di = corner & 1;
    const int dj = (corner >> 1) & 1;
    const int dk = (corner >> 2) & 1;
    const Probe& probe = probes_[Index(base[0] + di, base[1] + dj, base[2] + dk)];
    if (!probe.valid) continue;
    float w = (di ? frac[0] : 1.0f - frac[0]) * (dj ? frac[1] : 1.0f - frac[1]) *
              (dk ? frac[2] : 1.0f - frac[2]);
    const Vec3 offset = probe.position - p;
    const float distance = Length(offset);
    if (distance > 1e-4f) {
      const Vec3 to_probe = offset / distance;
      // Favour probes in front of the surface.
      const float facing = 0.5f * (Dot(to_probe, n) + 1.0f);
      w *= facing * facing + 0.02f;
      // Chebyshev visibility: is p farther from the probe than the surfaces
      // the probe saw in that direction?
      const Vec3 from_probe = -to_probe;
      const float mean = CubeEval(probe.mean, from_probe);
      if (distance > mean) {
        const float variance =
            std::max(CubeEval(probe.mean2, from_probe) - mean * mean, variance_floor);
        const float excess = distance - mean;
        const float chebyshev = variance / (variance + excess * excess);
        w *= std::max(chebyshev * chebyshev * chebyshev, 1e-4f);
      }
    }
    sum += CubeEval(probe.cube, n) * w;
    weight_sum += w;
  }
  return weight_sum > 1e-12f ? sum / weight_sum : fallback;
}

}  // namespace fd::scenegen
