// The "street" preset: a road crossing in a city block, outdoors under an
// open sky. World: Z up, metres; the main road runs along +Y, the cross road
// along X at y in [40, 50].
#include <algorithm>
#include <cmath>

#include "tools/scenegen/random.h"
#include "tools/scenegen/scenes.h"

namespace fd::scenegen {
namespace {

constexpr float kCrossLo = 40.0f;  // cross road spans y in [kCrossLo, kCrossHi]
constexpr float kCrossHi = 50.0f;
constexpr float kRoadHalf = 5.0f;   // main road spans x in [-5, 5]
constexpr float kWalkOuter = 9.0f;  // sidewalks span |x| in [5, 9]
constexpr float kLotStart = 9.5f;   // building fronts

Material Make(const char* name, Pattern pattern, Vec3 a, Vec3 b, float scale, float ra, float rb,
              float ma = 0.0f, float mb = 0.0f, float variation = 0.0f, float grime = 0.0f) {
  Material m;
  m.name = name;
  m.pattern = pattern;
  m.color_a = a;
  m.color_b = b;
  m.scale = scale;
  m.roughness_a = ra;
  m.roughness_b = rb;
  m.metallic_a = ma;
  m.metallic_b = mb;
  m.variation = variation;
  m.grime = grime;
  return m;
}

struct StreetMaterials {
  int grass, asphalt, paint, sidewalk, curb, bark, leaves_a, leaves_b, lamp_metal, lamp_glass,
      chrome, gold, red_glossy, glass, tyre, plinth, bench_wood;
  std::vector<int> facades;     // building walls
  std::vector<int> shopfronts;  // ground floors
  std::vector<int> roofs;
  std::vector<int> car_paints;
};

StreetMaterials AddMaterials(Scene* s) {
  StreetMaterials m;
  m.grass = s->AddMaterial(Make("grass", Pattern::kNoise, {0.06f, 0.16f, 0.04f},
                                {0.13f, 0.2f, 0.06f}, 1.5f, 0.95f, 0.85f, 0, 0, 0, 0.3f));
  m.asphalt = s->AddMaterial(Make("asphalt", Pattern::kNoise, {0.045f, 0.045f, 0.05f},
                                  {0.09f, 0.088f, 0.085f}, 0.35f, 0.9f, 0.75f, 0, 0, 0, 0.4f));
  m.paint = s->AddMaterial(Make("road_paint", Pattern::kNoise, {0.75f, 0.75f, 0.72f},
                                {0.6f, 0.6f, 0.56f}, 0.2f, 0.55f, 0.6f));
  m.sidewalk = s->AddMaterial(Make("sidewalk_tiles", Pattern::kTiles, {0.38f, 0.36f, 0.33f},
                                   {0.2f, 0.19f, 0.18f}, 0.6f, 0.75f, 0.9f, 0, 0, 0.12f, 0.35f));
  m.curb = s->AddMaterial(Make("curb_stone", Pattern::kNoise, {0.45f, 0.45f, 0.43f},
                               {0.32f, 0.32f, 0.31f}, 0.3f, 0.7f, 0.8f));
  m.bark = s->AddMaterial(Make("bark", Pattern::kNoise, {0.09f, 0.06f, 0.04f},
                               {0.16f, 0.11f, 0.07f}, 0.15f, 0.9f, 0.95f));
  m.leaves_a = s->AddMaterial(Make("leaves", Pattern::kNoise, {0.05f, 0.14f, 0.03f},
                                   {0.12f, 0.24f, 0.05f}, 0.3f, 0.75f, 0.85f));
  m.leaves_b = s->AddMaterial(Make("leaves_autumn", Pattern::kNoise, {0.2f, 0.12f, 0.02f},
                                   {0.35f, 0.22f, 0.04f}, 0.3f, 0.75f, 0.85f));
  m.lamp_metal = s->AddMaterial(Make("lamp_post_metal", Pattern::kSolid, {0.3f, 0.3f, 0.32f},
                                     {0.3f, 0.3f, 0.32f}, 1.0f, 0.35f, 0.35f, 1.0f, 1.0f));
  m.lamp_glass = s->AddMaterial(Make("lamp_shade", Pattern::kSolid, {0.8f, 0.78f, 0.7f},
                                     {0.8f, 0.78f, 0.7f}, 1.0f, 0.2f, 0.2f));
  m.chrome = s->AddMaterial(Make("chrome", Pattern::kSolid, {0.9f, 0.9f, 0.92f},
                                 {0.9f, 0.9f, 0.92f}, 1.0f, 0.05f, 0.05f, 1.0f, 1.0f));
  m.gold = s->AddMaterial(Make("brushed_gold", Pattern::kSolid, {1.0f, 0.72f, 0.3f},
                               {1.0f, 0.72f, 0.3f}, 1.0f, 0.3f, 0.3f, 1.0f, 1.0f));
  m.red_glossy = s->AddMaterial(Make("red_plastic", Pattern::kSolid, {0.6f, 0.04f, 0.03f},
                                     {0.6f, 0.04f, 0.03f}, 1.0f, 0.15f, 0.15f));
  m.glass = s->AddMaterial(Make("car_glass", Pattern::kSolid, {0.03f, 0.035f, 0.04f},
                                {0.03f, 0.035f, 0.04f}, 1.0f, 0.05f, 0.05f));
  m.tyre = s->AddMaterial(Make("tyre", Pattern::kSolid, {0.03f, 0.03f, 0.03f},
                               {0.03f, 0.03f, 0.03f}, 1.0f, 0.9f, 0.9f));
  m.plinth = s->AddMaterial(Make("marble_checker", Pattern::kChecker, {0.7f, 0.68f, 0.64f},
                                 {0.12f, 0.12f, 0.13f}, 0.25f, 0.2f, 0.25f));
  m.bench_wood = s->AddMaterial(Make("bench_wood", Pattern::kPlanks, {0.25f, 0.13f, 0.06f},
                                     {0.35f, 0.2f, 0.1f}, 0.12f, 0.7f, 0.7f, 0, 0, 0.2f));
  const Vec3 glass_blue{0.03f, 0.045f, 0.07f};
  m.facades = {
      s->AddMaterial(Make("red_brick", Pattern::kBricks, {0.3f, 0.09f, 0.05f}, {0.5f, 0.47f, 0.42f},
                          0.08f, 0.85f, 0.95f, 0, 0, 0.25f, 0.25f)),
      s->AddMaterial(Make("yellow_brick", Pattern::kBricks, {0.5f, 0.38f, 0.2f},
                          {0.35f, 0.33f, 0.3f}, 0.08f, 0.85f, 0.95f, 0, 0, 0.2f, 0.3f)),
      s->AddMaterial(Make("concrete_office", Pattern::kFacade, {0.42f, 0.41f, 0.38f}, glass_blue,
                          3.4f, 0.8f, 0.06f, 0, 0, 0.3f, 0.3f)),
      s->AddMaterial(Make("stucco_office", Pattern::kFacade, {0.55f, 0.45f, 0.35f}, glass_blue,
                          3.2f, 0.85f, 0.08f, 0, 0, 0.3f, 0.2f)),
      s->AddMaterial(Make("steel_glass_tower", Pattern::kFacade, {0.5f, 0.52f, 0.55f},
                          {0.04f, 0.06f, 0.08f}, 3.8f, 0.35f, 0.04f, 1.0f, 0.0f, 0.2f, 0.0f)),
  };
  m.shopfronts = {
      s->AddMaterial(Make("dark_tiles", Pattern::kTiles, {0.08f, 0.09f, 0.1f}, {0.3f, 0.3f, 0.3f},
                          0.5f, 0.3f, 0.8f, 0, 0, 0.1f)),
      s->AddMaterial(Make("shop_facade", Pattern::kFacade, {0.25f, 0.05f, 0.04f}, glass_blue, 4.0f,
                          0.6f, 0.05f, 0, 0, 0.4f)),
  };
  m.roofs = {
      s->AddMaterial(Make("roof_gravel", Pattern::kNoise, {0.2f, 0.19f, 0.18f},
                          {0.3f, 0.29f, 0.27f}, 0.5f, 0.95f, 0.9f)),
      s->AddMaterial(Make("roof_metal", Pattern::kChecker, {0.35f, 0.36f, 0.38f},
                          {0.3f, 0.31f, 0.33f}, 1.5f, 0.45f, 0.5f, 1.0f, 1.0f)),
  };
  m.car_paints = {
      s->AddMaterial(
          Make("car_red", Pattern::kSolid, {0.5f, 0.03f, 0.02f}, {}, 1, 0.25f, 0.25f, 0.7f, 0.7f)),
      s->AddMaterial(
          Make("car_blue", Pattern::kSolid, {0.03f, 0.1f, 0.4f}, {}, 1, 0.25f, 0.25f, 0.7f, 0.7f)),
      s->AddMaterial(
          Make("car_silver", Pattern::kSolid, {0.6f, 0.6f, 0.62f}, {}, 1, 0.3f, 0.3f, 1.0f, 1.0f)),
      s->AddMaterial(Make("car_white", Pattern::kSolid, {0.75f, 0.75f, 0.73f}, {}, 1, 0.2f, 0.2f)),
      s->AddMaterial(
          Make("car_green", Pattern::kSolid, {0.05f, 0.2f, 0.08f}, {}, 1, 0.3f, 0.3f, 0.6f, 0.6f)),
  };
  return m;
}

void AddTree(Scene* s, const StreetMaterials& m, PixelRng& rng, float x, float y) {
  const float height = rng.Uniform(2.6f, 3.6f);
  s->Add(MakeCylinder({x, y, 0.15f}, rng.Uniform(0.14f, 0.22f), height, m.bark));
  const int leaves = rng.NextFloat() < 0.25f ? m.leaves_b : m.leaves_a;
  const uint32_t tint = static_cast<uint32_t>(rng.NextU64());
  const float r = rng.Uniform(1.4f, 2.0f);
  s->Add(MakeSphere({x, y, 0.15f + height + 0.6f * r}, r, leaves), tint);
  for (int i = 0; i < 2; ++i) {
    const float a = rng.Uniform(0.0f, 6.2831853f);
    const float rr = r * rng.Uniform(0.55f, 0.75f);
    s->Add(MakeSphere({x + 0.7f * r * std::cos(a), y + 0.7f * r * std::sin(a),
                       0.15f + height + 0.4f * r + rng.Uniform(0.0f, 0.6f) * r},
                      rr, leaves),
           tint + i + 1);
  }
}

void AddLampPost(Scene* s, const StreetMaterials& m, float x, float y) {
  s->Add(MakeCylinder({x, y, 0.15f}, 0.09f, 4.8f, m.lamp_metal));
  s->Add(MakeCylinder({x, y, 0.15f}, 0.16f, 0.5f, m.lamp_metal));
  s->Add(MakeSphere({x, y, 5.15f}, 0.28f, m.lamp_glass));
}

void AddCar(Scene* s, const StreetMaterials& m, PixelRng& rng, float x, float y) {
  const int paint = m.car_paints[rng.NextU64() % m.car_paints.size()];
  const float length = rng.Uniform(3.9f, 4.6f);
  const float half_l = 0.5f * length;
  const float half_w = 0.88f;
  // Body, cabin (glass) and roof, along Y.
  s->Add(MakeBox({x - half_w, y - half_l, 0.32f}, {x + half_w, y + half_l, 1.0f}, paint));
  const float cabin_lo = y - half_l + 0.3f * length;
  const float cabin_hi = y + half_l - 0.22f * length;
  s->Add(MakeBox({x - half_w + 0.08f, cabin_lo, 1.0f}, {x + half_w - 0.08f, cabin_hi, 1.42f},
                 m.glass));
  s->Add(MakeBox({x - half_w + 0.06f, cabin_lo + 0.1f, 1.42f},
                 {x + half_w - 0.06f, cabin_hi - 0.05f, 1.5f}, paint));
  for (const float wy : {y - half_l + 0.75f, y + half_l - 0.75f}) {
    for (const float wx : {x - half_w - 0.02f, x + half_w - 0.24f}) {
      s->Add(MakeBox({wx, wy - 0.33f, 0.0f}, {wx + 0.26f, wy + 0.33f, 0.66f}, m.tyre));
    }
  }
}

// One building with a ground-floor shopfront, a cornice and a roof slab.
// Footprint x in [x0, x1], y in [y0, y1].
void AddBuilding(Scene* s, const StreetMaterials& m, PixelRng& rng, float x0, float x1, float y0,
                 float y1) {
  const float height =
      rng.NextFloat() < 0.2f ? rng.Uniform(24.0f, 40.0f) : rng.Uniform(7.0f, 20.0f);
  const int facade = m.facades[rng.NextU64() % m.facades.size()];
  const uint32_t tint = static_cast<uint32_t>(rng.NextU64());
  s->Add(MakeBox({x0, y0, 0.0f}, {x1, y1, height}, facade), tint);
  if (rng.NextFloat() < 0.6f) {
    // Shopfront: slightly proud of the facade, 3.6 m tall.
    const int shop = m.shopfronts[rng.NextU64() % m.shopfronts.size()];
    s->Add(MakeBox({x0 - 0.12f, y0 - 0.12f, 0.0f}, {x1 + 0.12f, y1 + 0.12f, 3.6f}, shop), tint);
  }
  const int roof = m.roofs[rng.NextU64() % m.roofs.size()];
  s->Add(MakeBox({x0 - 0.25f, y0 - 0.25f, height}, {x1 + 0.25f, y1 + 0.25f, height + 0.45f}, roof));
}

// Buildings along one block edge: lots from `from` to `to` along Y (when
// along_y) or X, fronts at `front`, extending `depth_sign` away from the road.
void AddBlockEdge(Scene* s, const StreetMaterials& m, PixelRng& rng, bool along_y, float from,
                  float to, float front, float depth_sign) {
  const float dir = to > from ? 1.0f : -1.0f;
  float pos = from;
  while ((to - pos) * dir > 4.0f) {
    const float width = std::min(rng.Uniform(8.0f, 16.0f), (to - pos) * dir);
    const float depth = rng.Uniform(10.0f, 16.0f);
    const float setback = rng.NextFloat() < 0.3f ? rng.Uniform(0.5f, 2.0f) : 0.0f;
    const float a = pos;
    const float b = pos + dir * width;
    const float f = front + depth_sign * setback;
    const float g = front + depth_sign * (setback + depth);
    if (along_y) {
      AddBuilding(s, m, rng, std::min(f, g), std::max(f, g), std::min(a, b), std::max(a, b));
    } else {
      AddBuilding(s, m, rng, std::min(a, b), std::max(a, b), std::min(f, g), std::max(f, g));
    }
    // Occasional gap between buildings.
    pos = b + dir * (rng.NextFloat() < 0.25f ? rng.Uniform(2.0f, 5.0f) : 0.0f);
  }
}

}  // namespace

Scene BuildStreetScene(uint64_t seed, int threads) {
  Scene s;
  s.name = "street";
  s.description = "outdoor street crossing with buildings, trees, cars and open sky";
  PixelRng rng(HashInts(seed, 0x57EE7ull));
  const StreetMaterials m = AddMaterials(&s);

  // Ground, roads, markings.
  s.Add(MakeBox({-400.0f, -400.0f, -1.0f}, {400.0f, 400.0f, 0.0f}, m.grass));
  s.Add(MakeBox({-kRoadHalf, -400.0f, -1.0f}, {kRoadHalf, 400.0f, 0.01f}, m.asphalt));
  s.Add(MakeBox({-400.0f, kCrossLo, -1.0f}, {400.0f, kCrossHi, 0.012f}, m.asphalt));
  for (float y = -200.0f; y < 200.0f; y += 6.0f) {
    if (y + 3.0f > kCrossLo - 3.0f && y < kCrossHi + 3.0f) continue;
    s.Add(MakeBox({-0.08f, y, 0.0f}, {0.08f, y + 3.0f, 0.02f}, m.paint));
  }
  for (float x = -4.4f; x < 4.5f; x += 1.1f) {  // zebra crossings
    s.Add(MakeBox({x, kCrossLo - 3.2f, 0.0f}, {x + 0.55f, kCrossLo - 0.4f, 0.02f}, m.paint));
    s.Add(MakeBox({x, kCrossHi + 0.4f, 0.0f}, {x + 0.55f, kCrossHi + 3.2f, 0.02f}, m.paint));
  }
  for (float y = -200.0f; y < 200.0f; y += 6.0f) {  // cross-road centre line
    const float yy = 0.5f * (kCrossLo + kCrossHi);
    if (std::fabs(y) < kWalkOuter + 4.0f) continue;
    s.Add(MakeBox({y, yy - 0.08f, 0.0f}, {y + 3.0f, yy + 0.08f, 0.022f}, m.paint));
  }

  // Sidewalks with curbs, in the four quadrants around the crossing.
  for (const float side : {-1.0f, 1.0f}) {
    const float x_in = side * kRoadHalf;
    const float x_out = side * kWalkOuter;
    for (const auto& [y0, y1] :
         {std::pair{-400.0f, kCrossLo - 4.0f}, std::pair{kCrossHi + 4.0f, 400.0f}}) {
      s.Add(MakeBox({std::min(x_in, x_out), y0, 0.0f}, {std::max(x_in, x_out), y1, 0.15f},
                    m.sidewalk));
      s.Add(MakeBox({x_in - 0.15f, y0, 0.0f}, {x_in + 0.15f, y1, 0.17f}, m.curb));
    }
    // Along the cross road.
    for (const auto& [ya, yb] :
         {std::pair{kCrossLo - 4.0f, kCrossLo}, std::pair{kCrossHi, kCrossHi + 4.0f}}) {
      const float near_x = side * kRoadHalf;
      const float far_x = side * 400.0f;
      s.Add(MakeBox({std::min(near_x, far_x), ya, 0.0f}, {std::max(near_x, far_x), yb, 0.15f},
                    m.sidewalk));
    }
  }

  // Buildings: four quadrants, each with a main-road edge and a cross-road edge.
  for (const float side : {-1.0f, 1.0f}) {
    const float front = side * kLotStart;
    AddBlockEdge(&s, m, rng, true, kCrossLo - 4.5f, -160.0f, front, side);
    AddBlockEdge(&s, m, rng, true, kCrossHi + 4.5f, 200.0f, front, side);
    AddBlockEdge(&s, m, rng, false, side * 26.0f, side * 180.0f, kCrossLo - 4.5f, -1.0f);
    AddBlockEdge(&s, m, rng, false, side * 26.0f, side * 180.0f, kCrossHi + 4.5f, 1.0f);
  }

  // Street furniture along both main sidewalks.
  for (const float side : {-1.0f, 1.0f}) {
    for (float y = -150.0f; y < 190.0f; y += 12.0f) {
      if (y > kCrossLo - 6.0f && y < kCrossHi + 6.0f) continue;
      const float jitter = rng.Uniform(-1.5f, 1.5f);
      if (rng.NextFloat() < 0.85f) AddTree(&s, m, rng, side * 7.6f, y + jitter);
      if (static_cast<int>(std::floor(y / 12.0f)) % 2 == 0) {
        AddLampPost(&s, m, side * 5.6f, y + 6.0f);
      }
      if (rng.NextFloat() < 0.45f) AddCar(&s, m, rng, side * 3.7f, y + rng.Uniform(3.0f, 9.0f));
      if (rng.NextFloat() < 0.3f) {  // bench
        const float by = y + rng.Uniform(2.0f, 10.0f);
        s.Add(MakeBox({side * 8.3f - 0.25f, by - 0.9f, 0.15f},
                      {side * 8.3f + 0.25f, by + 0.9f, 0.6f}, m.bench_wood));
      }
    }
  }

  // A small plaza with sculptures near the start of the walk: a chrome
  // sphere, a gold sphere and a glossy red ball on checkered plinths.
  const float plaza_y = rng.Uniform(-12.0f, -4.0f);
  s.Add(MakeBox({-8.6f, plaza_y - 0.8f, 0.15f}, {-7.0f, plaza_y + 0.8f, 0.9f}, m.plinth));
  s.Add(MakeSphere({-7.8f, plaza_y, 1.6f}, 0.7f, m.chrome));
  s.Add(MakeBox({7.0f, plaza_y + 8.0f, 0.15f}, {8.4f, plaza_y + 9.4f, 0.7f}, m.plinth));
  s.Add(MakeSphere({7.7f, plaza_y + 8.7f, 1.25f}, 0.55f, m.gold));
  s.Add(MakeSphere({-6.2f, plaza_y + 3.0f, 0.55f}, 0.4f, m.red_glossy));
  for (float y = plaza_y - 3.0f; y < plaza_y + 12.0f; y += 1.5f) {  // bollards
    s.Add(MakeCylinder({-5.45f, y, 0.15f}, 0.1f, 0.9f, m.lamp_metal));
  }

  Lighting& l = s.lighting;
  l.sun_direction = Normalize(Vec3(0.62f, -0.42f, 0.62f));
  l.sun_irradiance = Vec3(3.3f, 3.05f, 2.7f);
  l.sky_zenith = Vec3(0.16f, 0.32f, 0.8f);
  l.sky_horizon = Vec3(0.62f, 0.74f, 0.92f);
  l.ground_radiance = Vec3(0.12f, 0.12f, 0.11f);
  l.secondary_fill = 0.12f;
  l.exposure = 1.0f;
  s.near_plane = 2.0f;
  s.ao_radius = 1.5f;
  // Probes over the part of town the camera sees up close; farther surfaces
  // use the border probes, which mostly see sky.
  s.probe_grid.lo = Vec3(-30.0f, -70.0f, 0.5f);
  s.probe_grid.hi = Vec3(55.0f, 60.0f, 18.5f);
  s.probe_grid.spacing = 3.0f;
  s.probe_grid.rays = 64;
  s.probe_grid.bounces = 2;

  // Walk north along the road, turn right into the cross road and fly up,
  // turn around above it, glide back over the crossing and south along the
  // main road, then turn to face north again at the start.
  s.camera_path = CameraPath(
      {
          {{-2.0f, -30.0f, 1.7f}, 90.0f, 0.0f},
          {{-2.2f, -12.0f, 1.7f}, 96.0f, 1.0f},
          {{-1.6f, 8.0f, 1.7f}, 84.0f, -1.0f},
          {{-1.0f, 28.0f, 1.75f}, 88.0f, 0.0f},
          {{0.5f, 42.0f, 1.8f}, 50.0f, -2.0f},
          {{12.0f, 45.5f, 2.4f}, 5.0f, -3.0f},
          {{30.0f, 45.0f, 6.0f}, -10.0f, -8.0f},
          {{44.0f, 45.0f, 11.0f}, -100.0f, -25.0f},
          {{28.0f, 45.5f, 11.0f}, -180.0f, -20.0f},
          {{6.0f, 45.0f, 9.0f}, -130.0f, -18.0f},
          {{0.0f, 25.0f, 7.0f}, -90.0f, -12.0f},
          {{-1.5f, -20.0f, 4.0f}, -90.0f, -5.0f},
          {{-3.0f, -48.0f, 2.0f}, 0.0f, 0.0f},
      },
      /*step=*/0.12f, /*fov_y_deg=*/60.0f);
  s.Finalize(threads);
  return s;
}

}  // namespace fd::scenegen
