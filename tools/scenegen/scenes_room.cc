// The "room" preset: an interior lit by the low sun through two east windows
// and a south door, with a windowless back room behind an inner door that
// stays dark (the paper's Hillside case, where the model struggles). World:
// Z up, metres; main room x in [0, 8], y in [0, 6], back room x in [0, 5],
// y in [6.2, 11], ceiling at z = 3.
#include <cmath>

#include "tools/scenegen/random.h"
#include "tools/scenegen/scenes.h"

namespace fd::scenegen {
namespace {

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

// A wall slab from (x0, y0) to (x1, y1) (one of them thin), floor to ceiling,
// minus rectangular openings given as [a0, a1] along the wall's long axis and
// [z0, z1] in height.
struct Opening {
  float a0, a1, z0, z1;
};

void AddWall(Scene* s, float x0, float y0, float x1, float y1, float height,
             std::initializer_list<Opening> openings, int material, uint32_t tint) {
  const bool along_x = (x1 - x0) > (y1 - y0);
  const float lo = along_x ? x0 : y0;
  const float hi = along_x ? x1 : y1;
  auto box = [&](float a0, float a1, float z0, float z1) {
    if (a1 - a0 <= 1e-4f || z1 - z0 <= 1e-4f) return;
    if (along_x) {
      s->Add(MakeBox({a0, y0, z0}, {a1, y1, z1}, material), tint);
    } else {
      s->Add(MakeBox({x0, a0, z0}, {x1, a1, z1}, material), tint);
    }
  };
  float cursor = lo;
  for (const Opening& o : openings) {
    box(cursor, o.a0, 0.0f, height);  // solid part before the opening
    box(o.a0, o.a1, 0.0f, o.z0);      // sill
    box(o.a0, o.a1, o.z1, height);    // lintel
    cursor = o.a1;
  }
  box(cursor, hi, 0.0f, height);
}

}  // namespace

Scene BuildRoomScene(uint64_t seed, int threads) {
  Scene s;
  s.name = "room";
  s.description = "sunlit room with windows and a door, and a dark windowless back room";
  PixelRng rng(HashInts(seed, 0x2004ull));

  const int gravel = s.AddMaterial(Make("garden_gravel", Pattern::kNoise, {0.18f, 0.17f, 0.14f},
                                        {0.3f, 0.28f, 0.22f}, 0.4f, 0.95f, 0.9f));
  const int lawn = s.AddMaterial(Make("lawn", Pattern::kNoise, {0.06f, 0.15f, 0.04f},
                                      {0.12f, 0.2f, 0.05f}, 1.0f, 0.95f, 0.9f));
  const int planks = s.AddMaterial(Make("oak_floor", Pattern::kPlanks, {0.32f, 0.17f, 0.07f},
                                        {0.45f, 0.27f, 0.12f}, 0.18f, 0.35f, 0.45f, 0, 0, 0.25f));
  const int concrete = s.AddMaterial(Make("concrete_floor", Pattern::kNoise, {0.28f, 0.27f, 0.25f},
                                          {0.4f, 0.39f, 0.36f}, 0.6f, 0.8f, 0.6f, 0, 0, 0, 0.4f));
  const int plaster = s.AddMaterial(Make("plaster", Pattern::kNoise, {0.62f, 0.58f, 0.5f},
                                         {0.7f, 0.66f, 0.58f}, 0.8f, 0.85f, 0.9f, 0, 0, 0, 0.15f));
  const int brick =
      s.AddMaterial(Make("brick_wall", Pattern::kBricks, {0.35f, 0.12f, 0.07f},
                         {0.55f, 0.52f, 0.46f}, 0.075f, 0.8f, 0.95f, 0, 0, 0.3f, 0.2f));
  const int exterior =
      s.AddMaterial(Make("exterior_render", Pattern::kTiles, {0.5f, 0.47f, 0.42f},
                         {0.4f, 0.38f, 0.34f}, 1.2f, 0.9f, 0.9f, 0, 0, 0.05f, 0.3f));
  const int ceiling = s.AddMaterial(Make("ceiling", Pattern::kSolid, {0.72f, 0.71f, 0.68f},
                                         {0.72f, 0.71f, 0.68f}, 1.0f, 0.9f, 0.9f));
  const int frame = s.AddMaterial(Make("window_frame_steel", Pattern::kSolid, {0.12f, 0.12f, 0.13f},
                                       {0.12f, 0.12f, 0.13f}, 1.0f, 0.4f, 0.4f, 1.0f, 1.0f));
  const int rug = s.AddMaterial(Make("rug", Pattern::kChecker, {0.45f, 0.08f, 0.06f},
                                     {0.6f, 0.5f, 0.3f}, 0.3f, 0.95f, 0.95f));
  const int wood = s.AddMaterial(Make("walnut", Pattern::kPlanks, {0.14f, 0.07f, 0.035f},
                                      {0.2f, 0.1f, 0.05f}, 0.25f, 0.3f, 0.4f, 0, 0, 0.2f));
  const int chrome = s.AddMaterial(Make("chrome", Pattern::kSolid, {0.9f, 0.9f, 0.92f},
                                        {0.9f, 0.9f, 0.92f}, 1.0f, 0.05f, 0.05f, 1.0f, 1.0f));
  const int copper = s.AddMaterial(Make("copper", Pattern::kSolid, {0.95f, 0.6f, 0.45f},
                                        {0.95f, 0.6f, 0.45f}, 1.0f, 0.35f, 0.35f, 1.0f, 1.0f));
  const int fabric = s.AddMaterial(Make("sofa_fabric", Pattern::kNoise, {0.08f, 0.15f, 0.25f},
                                        {0.12f, 0.2f, 0.32f}, 0.05f, 1.0f, 0.95f));
  const int ceramic = s.AddMaterial(Make("glazed_ceramic", Pattern::kSolid, {0.75f, 0.72f, 0.6f},
                                         {0.75f, 0.72f, 0.6f}, 1.0f, 0.12f, 0.12f));
  const int crate =
      s.AddMaterial(Make("crate_wood", Pattern::kPlanks, {0.3f, 0.2f, 0.1f}, {0.38f, 0.27f, 0.14f},
                         0.15f, 0.85f, 0.9f, 0, 0, 0.3f, 0.3f));
  const int rust = s.AddMaterial(Make("rusty_barrel", Pattern::kNoise, {0.25f, 0.1f, 0.04f},
                                      {0.45f, 0.45f, 0.47f}, 0.3f, 0.9f, 0.4f, 0.1f, 0.9f));
  const Vec3 book_colors[] = {{0.4f, 0.05f, 0.05f},
                              {0.05f, 0.2f, 0.1f},
                              {0.1f, 0.1f, 0.35f},
                              {0.5f, 0.4f, 0.1f},
                              {0.3f, 0.3f, 0.3f}};
  int books[5];
  for (int i = 0; i < 5; ++i) {
    books[i] = s.AddMaterial(
        Make("book", Pattern::kSolid, book_colors[i], book_colors[i], 1.0f, 0.7f, 0.7f));
  }

  // Outside: gravel yard and lawn.
  s.Add(MakeBox({-60.0f, -60.0f, -1.0f}, {60.0f, 60.0f, -0.05f}, lawn));
  s.Add(MakeBox({-3.0f, -8.0f, -1.0f}, {12.0f, -0.2f, -0.04f}, gravel));
  s.Add(MakeBox({8.2f, -8.0f, -1.0f}, {12.0f, 12.0f, -0.04f}, gravel));

  // Floors and ceilings.
  s.Add(MakeBox({-0.2f, -0.2f, -0.3f}, {8.2f, 6.1f, 0.0f}, planks));
  s.Add(MakeBox({-0.2f, 6.1f, -0.3f}, {5.2f, 11.2f, 0.0f}, concrete));
  s.Add(MakeBox({-0.2f, -0.2f, 3.0f}, {8.2f, 6.2f, 3.3f}, ceiling));
  s.Add(MakeBox({-0.2f, 6.2f, 3.0f}, {5.2f, 11.2f, 3.3f}, ceiling));

  // Walls. South wall has the garden door, east wall two windows, the
  // dividing brick wall the inner door to the dark room.
  const float kH = 3.0f;
  const uint32_t wall_tint = static_cast<uint32_t>(rng.NextU64());
  AddWall(&s, -0.2f, -0.2f, 8.2f, 0.0f, kH, {{1.0f, 2.2f, 0.0f, 2.25f}, {4.8f, 6.6f, 1.05f, 2.45f}},
          plaster, wall_tint);
  AddWall(&s, 8.0f, -0.2f, 8.2f, 6.2f, kH, {{1.0f, 2.6f, 0.85f, 2.45f}, {3.4f, 5.0f, 0.85f, 2.45f}},
          plaster, wall_tint);
  // The dark room's only daylight: a small west-facing window (sky, no sun).
  AddWall(&s, -0.2f, -0.2f, 0.0f, 11.2f, kH, {{9.6f, 10.2f, 1.9f, 2.35f}}, plaster, wall_tint);
  AddWall(&s, -0.2f, 6.0f, 8.2f, 6.2f, kH, {{0.6f, 1.8f, 0.0f, 2.3f}}, brick, wall_tint);
  AddWall(&s, 5.0f, 6.2f, 5.2f, 11.2f, kH, {}, plaster, wall_tint);
  AddWall(&s, -0.2f, 11.0f, 5.2f, 11.2f, kH, {}, plaster, wall_tint);
  // Outer skin of the exterior walls, seen from the garden.
  s.Add(MakeBox({5.2f, 6.2f, 0.0f}, {8.2f, 6.25f, kH}, exterior));
  // Window mullions and transoms.
  for (const float yc : {1.8f, 4.2f}) {
    s.Add(MakeBox({8.02f, yc - 0.03f, 0.85f}, {8.18f, yc + 0.03f, 2.45f}, frame));
    s.Add(MakeBox({8.02f, yc - 0.8f, 1.62f}, {8.18f, yc + 0.8f, 1.68f}, frame));
  }
  s.Add(MakeBox({5.67f, -0.18f, 1.05f}, {5.73f, -0.02f, 2.45f}, frame));
  // Door frames.
  s.Add(MakeBox({0.95f, -0.22f, 0.0f}, {1.0f, 0.02f, 2.3f}, wood));
  s.Add(MakeBox({2.2f, -0.22f, 0.0f}, {2.25f, 0.02f, 2.3f}, wood));

  // Furniture in the sunlit room.
  const float table_x = 4.6f + rng.Uniform(-0.2f, 0.2f);
  const float table_y = 3.0f + rng.Uniform(-0.2f, 0.2f);
  s.Add(MakeBox({3.0f, 1.8f, 0.0f}, {6.2f, 4.2f, 0.012f}, rug));
  s.Add(MakeBox({table_x - 0.8f, table_y - 0.45f, 0.72f}, {table_x + 0.8f, table_y + 0.45f, 0.77f},
                wood));
  for (const float dx : {-0.72f, 0.72f}) {
    for (const float dy : {-0.38f, 0.38f}) {
      s.Add(MakeCylinder({table_x + dx, table_y + dy, 0.0f}, 0.035f, 0.72f, frame));
    }
  }
  s.Add(MakeSphere({table_x - 0.3f, table_y, 0.92f}, 0.15f, chrome));
  s.Add(MakeCylinder({table_x + 0.35f, table_y + 0.1f, 0.77f}, 0.09f, 0.28f, ceramic));
  s.Add(MakeSphere({table_x + 0.35f, table_y - 0.22f, 0.85f}, 0.08f, copper));
  // Bookshelf on the west wall with coloured books.
  s.Add(MakeBox({0.0f, 1.0f, 0.0f}, {0.4f, 3.0f, 2.0f}, wood));
  for (int shelf = 0; shelf < 3; ++shelf) {
    const float z = 0.35f + 0.55f * shelf;
    float y = 1.08f;
    while (y < 2.85f) {
      const float width = rng.Uniform(0.03f, 0.07f);
      const float height = rng.Uniform(0.22f, 0.32f);
      s.Add(MakeBox({0.4f, y, z}, {0.43f, y + width, z + height}, books[rng.NextU64() % 5]));
      y += width + 0.005f;
    }
  }
  // Sofa along the south wall.
  s.Add(MakeBox({3.2f, 0.1f, 0.0f}, {6.0f, 1.0f, 0.45f}, fabric));
  s.Add(MakeBox({3.2f, 0.0f, 0.45f}, {6.0f, 0.3f, 0.95f}, fabric));
  s.Add(MakeBox({3.0f, 0.0f, 0.0f}, {3.25f, 1.0f, 0.65f}, fabric));
  s.Add(MakeBox({5.95f, 0.0f, 0.0f}, {6.2f, 1.0f, 0.65f}, fabric));
  // Floor lamp (copper shade on a chrome pole) in the north-east corner.
  s.Add(MakeCylinder({7.3f, 5.4f, 0.0f}, 0.18f, 0.04f, chrome));
  s.Add(MakeCylinder({7.3f, 5.4f, 0.0f}, 0.025f, 1.6f, chrome));
  s.Add(MakeSphere({7.3f, 5.4f, 1.7f}, 0.22f, copper));

  // The dark room: crates along its walls, a barrel and a sphere, clear of
  // the camera's way in (x in [1, 3.2]).
  for (int i = 0; i < 4; ++i) {
    const float size = rng.Uniform(0.5f, 0.9f);
    const float x = i < 2 ? rng.Uniform(3.7f, 4.4f) : rng.Uniform(0.5f, 0.8f);
    const float y = i < 2 ? 7.0f + 2.2f * i + rng.Uniform(0.0f, 0.8f) : rng.Uniform(9.6f, 10.4f);
    s.Add(MakeBox({x - 0.5f * size, y - 0.5f * size, 0.0f},
                  {x + 0.5f * size, y + 0.5f * size, size}, crate),
          static_cast<uint32_t>(rng.NextU64()));
  }
  s.Add(MakeCylinder({4.4f, 10.4f, 0.0f}, 0.3f, 0.9f, rust));
  s.Add(MakeSphere({1.9f, 10.5f, 0.4f}, 0.4f, ceramic));

  Lighting& l = s.lighting;
  l.sun_direction = Normalize(Vec3(0.82f, -0.38f, 0.42f));
  l.sun_irradiance = Vec3(3.4f, 3.0f, 2.5f);
  l.sky_zenith = Vec3(0.16f, 0.3f, 0.75f);
  l.sky_horizon = Vec3(0.6f, 0.7f, 0.88f);
  l.ground_radiance = Vec3(0.1f, 0.1f, 0.08f);
  // Indoors nearly all light arrives by the traced paths; little fill.
  l.secondary_fill = 0.01f;
  l.exposure = 3.0f;
  s.near_plane = 0.4f;
  s.ao_radius = 0.6f;
  // Probes through both rooms and a margin of garden outside the openings.
  s.probe_grid.lo = Vec3(-1.0f, -1.2f, 0.2f);
  s.probe_grid.hi = Vec3(9.4f, 11.6f, 2.8f);
  s.probe_grid.spacing = 0.4f;
  s.probe_grid.rays = 128;
  s.probe_grid.bounces = 3;

  // Look from the sunlit room across the sun patches to the dark doorway,
  // walk into the dark room, turn around in it, come back out and look at
  // the windows.
  s.camera_path = CameraPath(
      {
          {{6.7f, 1.3f, 1.6f}, 139.0f, -10.0f},
          {{3.5f, 3.0f, 1.6f}, 115.0f, -6.0f},
          {{1.4f, 4.8f, 1.6f}, 95.0f, -4.0f},
          {{1.2f, 7.0f, 1.6f}, 80.0f, -6.0f},
          {{2.2f, 8.8f, 1.6f}, 20.0f, -8.0f},
          {{3.0f, 9.0f, 1.6f}, -60.0f, -8.0f},
          {{2.0f, 8.0f, 1.6f}, -110.0f, -6.0f},
          {{1.3f, 5.8f, 1.6f}, -80.0f, -4.0f},
          {{3.5f, 3.5f, 1.7f}, -20.0f, 0.0f},
          {{6.0f, 2.0f, 1.6f}, 40.0f, -5.0f},
      },
      /*step=*/0.05f, /*fov_y_deg=*/65.0f);
  s.Finalize(threads);
  return s;
}

}  // namespace fd::scenegen
