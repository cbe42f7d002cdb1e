#include "tools/scenegen/renderer.h"

#include <algorithm>
#include <cmath>

#include "tools/scenegen/parallel.h"
#include "tools/scenegen/random.h"
#include "tools/scenegen/shading.h"

namespace fd::scenegen {
namespace {

// Roughness floor for the sun's specular lobe: the sun is treated as a point
// light, and sharper lobes would only give single-pixel sparkles.
constexpr float kMinSunRoughness = 0.15f;

// 4x4 Bayer matrix: neighbouring pixels get distant ranks.
constexpr int kBayer4[4][4] = {{0, 8, 2, 10}, {12, 4, 14, 6}, {3, 11, 1, 9}, {15, 7, 13, 5}};

// Per-pixel terms of the first pass that the second pass combines.
struct PixelTerms {
  Vec3 direct;          // sun diffuse + specular + mirror reflection (noise-free)
  Vec3 ambient;         // volume irradiance / pi times ambient occlusion (noisy)
  Vec3 ambient_weight;  // multiplies the filtered ambient term
  Vec3 position;        // world position (filter guide)
};

// Schlick's Fresnel.
Vec3 Fresnel(const Vec3& f0, float cos_theta) {
  const float m = std::pow(1.0f - Clamp01(cos_theta), 5.0f);
  return f0 + (Vec3(1.0f, 1.0f, 1.0f) - f0) * m;
}

// Karis' analytic fit of the split-sum environment BRDF (UE4 mobile).
Vec3 EnvBrdfApprox(const Vec3& f0, float roughness, float n_dot_v) {
  const float r_x = roughness * -1.0f + 1.0f;
  const float r_y = roughness * -0.0275f + 0.0425f;
  const float r_z = roughness * -0.572f + 1.04f;
  const float r_w = roughness * 0.022f - 0.04f;
  const float a004 = std::min(r_x * r_x, std::exp2(-9.28f * n_dot_v)) * r_x + r_y;
  const float a = -1.04f * a004 + r_z;
  const float b = 1.04f * a004 + r_w;
  return f0 * a + Vec3(b, b, b);
}

// GGX (Trowbridge-Reitz) specular BRDF for a directional light.
Vec3 GgxSpecular(const Vec3& n, const Vec3& v, const Vec3& l, float roughness, const Vec3& f0) {
  const float n_dot_l = Dot(n, l);
  const float n_dot_v = std::max(Dot(n, v), 1e-4f);
  if (n_dot_l <= 0.0f) return Vec3();
  const Vec3 h = Normalize(l + v);
  const float n_dot_h = std::max(Dot(n, h), 0.0f);
  const float v_dot_h = std::max(Dot(v, h), 0.0f);
  const float r = std::max(roughness, kMinSunRoughness);
  const float alpha = r * r;
  const float alpha2 = alpha * alpha;
  const float denom = n_dot_h * n_dot_h * (alpha2 - 1.0f) + 1.0f;
  const float d = alpha2 / (kPi * denom * denom);
  const float k = (r + 1.0f) * (r + 1.0f) / 8.0f;
  const float g = (n_dot_v / (n_dot_v * (1.0f - k) + k)) * (n_dot_l / (n_dot_l * (1.0f - k) + k));
  return Fresnel(f0, v_dot_h) * (d * g / (4.0f * n_dot_v * n_dot_l));
}

class FrameRenderer {
 public:
  FrameRenderer(const Scene& scene, const Camera& camera, int frame, const RenderSettings& settings)
      : scene_(scene), camera_(camera), frame_(frame), settings_(settings) {
    const float kDegToRad = kPi / 180.0f;
    pixel_angle_ = 2.0f * std::tan(0.5f * camera.fov_y_deg * kDegToRad) / settings.height;
    const float fill = scene.lighting.secondary_fill;
    fill_irradiance_ = Vec3(fill, fill, fill) * kPi;
  }

  FrameBuffers Render() {
    const int w = settings_.width;
    const int h = settings_.height;
    FrameBuffers out;
    out.width = w;
    out.height = h;
    const size_t n = size_t(w) * h;
    out.geometry.assign(n, 0);
    out.radiance.assign(n, Vec3());
    out.base_color.assign(n, Vec3());
    out.normal.assign(n, Vec3());
    out.view_depth.assign(n, 0.0f);
    out.roughness.assign(n, 0.0f);
    out.metallic.assign(n, 0.0f);
    terms_.assign(n, PixelTerms());
    // Pass 1: trace every pixel independently.
    ParallelFor(h, settings_.threads, [&](int y) {
      for (int x = 0; x < w; ++x) ShadePixel(x, y, &out);
    });
    // Pass 2: filter the ambient term (reads all of pass 1) and combine.
    Denoise(&out);
    return out;
  }

 private:
  // Irradiance / pi from the volume (sky light and indirect bounces).
  Vec3 AmbientOverPi(const Vec3& p, const Vec3& n) const {
    return scene_.irradiance.Irradiance(p, n, fill_irradiance_) / kPi;
  }

  // Radiance towards the camera from a mirror ray: sun + volume light on the
  // surface it hits, or the sky with the sun disk.
  Vec3 TraceMirror(const Ray& ray) const {
    Hit hit;
    if (!scene_.bvh.Intersect(ray, 0.0f, kMaxDistance, &hit)) {
      return scene_.SkyRadiance(ray.direction, /*include_sun_disk=*/true);
    }
    const SurfaceHit h = ResolveSecondaryHit(scene_, ray, hit);
    return DiffuseAlbedo(h.surface) *
           (SunOverPi(scene_, h.origin, h.normal) + AmbientOverPi(h.position, h.normal));
  }

  // Fraction of the hemisphere not blocked within ao_radius, from
  // cosine-weighted rays stratified across each 4x4 pixel block
  // (interleaved sampling: the block's pixels use disjoint strata, so the
  // filter's neighbourhood averages a well-spread set of directions). A hit
  // at distance t blocks 1 - t / radius, which keeps the term smooth.
  float AmbientOcclusion(int x, int y, const Vec3& origin, const Vec3& n, PixelRng& rng) const {
    const int samples = std::max(1, settings_.ao_samples);
    const float radius = scene_.ao_radius;
    const int block_rank = kBayer4[y & 3][x & 3];
    const int strata_u = 4 * samples;  // strata along cos^2(elevation) ...
    const int strata_v = 4;            // ... and along azimuth
    float open = 0.0f;
    for (int k = 0; k < samples; ++k) {
      const int stratum = block_rank * samples + k;
      const float u1 = (static_cast<float>(stratum % strata_u) + rng.NextFloat()) / strata_u;
      const float u2 = (static_cast<float>(stratum / strata_u) + rng.NextFloat()) / strata_v;
      Hit hit;
      const Ray ray{origin, CosineSample(n, u1, u2)};
      open += scene_.bvh.Intersect(ray, 0.0f, radius, &hit) ? hit.t / radius : 1.0f;
    }
    return open / samples;
  }

  void ShadePixel(int x, int y, FrameBuffers* out) {
    const size_t i = out->Index(x, y);
    const Ray ray = camera_.PrimaryRay(x + 0.5f, y + 0.5f, settings_.width, settings_.height);
    Hit hit;
    if (!scene_.bvh.Intersect(ray, 0.0f, kMaxDistance, &hit)) {
      out->radiance[i] = scene_.SkyRadiance(ray.direction, /*include_sun_disk=*/true);
      return;
    }
    const Primitive& prim = scene_.primitives[hit.primitive];
    const Vec3 p = ray.origin + ray.direction * hit.t;
    Vec3 n = hit.normal;
    if (Dot(n, ray.direction) > 0.0f) n = -n;
    const Vec3 v = -ray.direction;
    const float n_dot_v = std::max(Dot(n, v), 1e-4f);
    const float footprint = hit.t * pixel_angle_ / std::max(n_dot_v, 0.2f);
    const SurfaceSample s =
        EvaluateMaterial(scene_.materials[prim.material], p, n, footprint, prim.tint);

    out->geometry[i] = 1;
    out->base_color[i] = s.albedo;
    out->normal[i] = n;
    out->view_depth[i] = hit.t * Dot(ray.direction, camera_.forward);
    out->roughness[i] = s.roughness;
    out->metallic[i] = s.metallic;

    PixelRng rng(settings_.seed, static_cast<uint64_t>(frame_), i);
    const Lighting& l = scene_.lighting;
    const Vec3 origin = p + n * RayEpsilon(hit.t);
    const Vec3 f0 = Lerp(Vec3(0.04f, 0.04f, 0.04f), s.albedo, s.metallic);
    const Vec3 diffuse_color = s.albedo * ((1.0f - s.metallic) * 0.96f);
    PixelTerms& terms = terms_[i];
    terms.position = p;

    // Sun: hard shadow, Lambert + GGX.
    const float n_dot_l = Dot(n, l.sun_direction);
    if (n_dot_l > 0.0f && !scene_.bvh.Occluded(Ray{origin, l.sun_direction}, 0.0f, kMaxDistance)) {
      terms.direct += (diffuse_color / kPi + GgxSpecular(n, v, l.sun_direction, s.roughness, f0)) *
                      l.sun_irradiance * n_dot_l;
    }

    // Sky and bounce light from the volume, occluded locally.
    terms.ambient = AmbientOverPi(p, n) * AmbientOcclusion(x, y, origin, n, rng);

    // Environment specular: a mirror ray for smooth surfaces, the ambient
    // light for rough ones (split-sum weights).
    const Vec3 env_brdf = EnvBrdfApprox(f0, s.roughness, n_dot_v);
    const float mirror = 1.0f - SmoothStep(0.1f, 0.6f, s.roughness);
    if (mirror > 0.0f) {
      const Vec3 r = Normalize(ray.direction - n * (2.0f * Dot(ray.direction, n)));
      terms.direct += env_brdf * TraceMirror(Ray{origin, r}) * mirror;
    }
    terms.ambient_weight = diffuse_color + env_brdf * (1.0f - mirror);
  }

  // One pass of an edge-avoiding a-trous wavelet filter (Dammertz et al.
  // 2010): a 5x5 B3-spline kernel with taps `step` pixels apart, weighted by
  // normal similarity and by each tap's distance to the centre pixel's
  // tangent plane, so light never bleeds across edges.
  void FilterPass(const FrameBuffers& b, const std::vector<Vec3>& src, int step, int y,
                  std::vector<Vec3>* dst) const {
    static constexpr float kKernel[5] = {1.0f, 4.0f, 6.0f, 4.0f, 1.0f};
    for (int x = 0; x < b.width; ++x) {
      const size_t i = b.Index(x, y);
      if (!b.geometry[i]) continue;
      const Vec3 n = b.normal[i];
      const Vec3 p = terms_[i].position;
      const float plane_sigma = 0.02f + 2.0f * step * b.view_depth[i] * pixel_angle_;
      Vec3 sum;
      float weight_sum = 0.0f;
      for (int dy = -2; dy <= 2; ++dy) {
        const int yy = y + dy * step;
        if (yy < 0 || yy >= b.height) continue;
        for (int dx = -2; dx <= 2; ++dx) {
          const int xx = x + dx * step;
          if (xx < 0 || xx >= b.width) continue;
          const size_t j = b.Index(xx, yy);
          if (!b.geometry[j]) continue;
          const float n_dot = Dot(n, b.normal[j]);
          if (n_dot <= 0.5f) continue;
          const float plane = std::fabs(Dot(n, terms_[j].position - p)) / plane_sigma;
          if (plane >= 3.0f) continue;
          float wn = n_dot * n_dot;
          wn *= wn;
          wn *= wn;  // (n.n')^8
          const float w = kKernel[dx + 2] * kKernel[dy + 2] * wn * (1.0f - plane / 3.0f);
          sum += src[j] * w;
          weight_sum += w;
        }
      }
      (*dst)[i] = weight_sum > 0.0f ? sum / weight_sum : src[i];
    }
  }

  void Denoise(FrameBuffers* out) {
    const size_t n = terms_.size();
    std::vector<Vec3> ambient(n);
    std::vector<Vec3> scratch(n);
    for (size_t i = 0; i < n; ++i) ambient[i] = terms_[i].ambient;
    for (const int step : {1, 2}) {
      ParallelFor(out->height, settings_.threads,
                  [&](int y) { FilterPass(*out, ambient, step, y, &scratch); });
      ambient.swap(scratch);
    }
    for (size_t i = 0; i < n; ++i) {
      if (!out->geometry[i]) continue;
      out->radiance[i] = terms_[i].direct + terms_[i].ambient_weight * ambient[i];
    }
  }

  const Scene& scene_;
  const Camera& camera_;
  const int frame_;
  const RenderSettings& settings_;
  float pixel_angle_ = 0.0f;
  Vec3 fill_irradiance_;
  std::vector<PixelTerms> terms_;
};

}  // namespace

FrameBuffers RenderFrame(const Scene& scene, const Camera& camera, int frame,
                         const RenderSettings& settings) {
  return FrameRenderer(scene, camera, frame, settings).Render();
}

}  // namespace fd::scenegen
