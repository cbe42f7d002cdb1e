// Procedural materials: base colour patterns (checkers, bricks, tiles, planks,
// noise, building facades) with roughness and metallic per pattern part.
//
// Patterns are evaluated in world space and band-limited by the pixel
// footprint, so distant textures fade to their average instead of aliasing
// (which would make consecutive frames flicker).
#ifndef FD_TOOLS_SCENEGEN_MATERIAL_H_
#define FD_TOOLS_SCENEGEN_MATERIAL_H_

#include <cstdint>
#include <string>

#include "tools/scenegen/vec3.h"

namespace fd::scenegen {

enum class Pattern : uint8_t {
  kSolid,    // part A everywhere
  kChecker,  // squares of side `scale` alternating A / B
  kBricks,   // running-bond bricks (A) of height `scale`, mortar (B)
  kTiles,    // square tiles (A) of side `scale`, grout (B)
  kPlanks,   // floor planks of width `scale`, colour varying between A and B
  kNoise,    // fBm blend between A and B at feature size `scale`
  kFacade,   // wall (A) with a grid of windows (B), storey height `scale`
};

struct Material {
  std::string name;
  Pattern pattern = Pattern::kSolid;
  Vec3 color_a{0.5f, 0.5f, 0.5f};  // linear albedo, part A
  Vec3 color_b{0.5f, 0.5f, 0.5f};  // linear albedo, part B
  float scale = 1.0f;              // pattern period in metres
  float roughness_a = 0.5f;
  float roughness_b = 0.5f;
  float metallic_a = 0.0f;
  float metallic_b = 0.0f;
  float variation = 0.0f;  // per-cell (brick, tile, plank) brightness jitter, 0..1
  float grime = 0.0f;      // low-frequency noise darkening, 0..1
};

// Surface properties at a point, all in [0, 1]; albedo is linear.
struct SurfaceSample {
  Vec3 albedo;
  float roughness = 0.5f;
  float metallic = 0.0f;
};

// Evaluates `material` at world point p with unit normal n. `footprint` is
// the pixel's width on the surface in metres (larger = blurrier); `tint` is a
// per-object hash that shifts cell colours. Pure function, thread-safe.
SurfaceSample EvaluateMaterial(const Material& material, const Vec3& p, const Vec3& n,
                               float footprint, uint32_t tint);

// Smooth 3D value noise in [0, 1] and its fractal sum (octaves stop where
// they would alias at the given footprint, in units of the noise period).
float ValueNoise(const Vec3& p);
float FilteredFbm(const Vec3& p, float footprint, int max_octaves);

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_MATERIAL_H_
