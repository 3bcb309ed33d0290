// The measured Cornell Box data (Cornell PCG), transcribed from its published tables.
#include "blockhash_cl/cornell_box.hpp"

#include <algorithm>
#include <cmath>

namespace bhcl::cornell {
namespace {

Vec3 sub(const Vec3& a, const Vec3& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
Vec3 cross(const Vec3& a, const Vec3& b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
float dot(const Vec3& a, const Vec3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
Vec3 normalise(Vec3 a) {
  float l = std::sqrt(dot(a, a));
  return {a[0] / l, a[1] / l, a[2] / l};
}
Vec3 centroid(const std::array<Vec3, 4>& v) {
  Vec3 c{0, 0, 0};
  for (const auto& p : v)
    for (int d = 0; d < 3; ++d) c[d] += p[d] / 4.0f;
  return c;
}

// Orients the quad's normal towards `inside` (walls) or away from `outside_of` (blocks).
Quad make(std::string name, Material m, std::array<Vec3, 4> v, const Vec3& ref, bool towards) {
  Vec3 n = normalise(cross(sub(v[1], v[0]), sub(v[2], v[0])));
  float s = dot(n, sub(ref, centroid(v)));
  if ((s < 0) == towards) n = {-n[0], -n[1], -n[2]};
  return Quad{std::move(name), m, v, n};
}

std::vector<Quad> build() {
  // The light and the room's walls, each facing the room's centre.
  struct Wall {
    const char* name;
    Material m;
    std::array<Vec3, 4> v;
  };
  const Wall walls[] = {
      {"light", Material::Light, {{{343.0f, 548.8f, 227.0f}, {343.0f, 548.8f, 332.0f}, {213.0f, 548.8f, 332.0f}, {213.0f, 548.8f, 227.0f}}}},
      {"floor", Material::White, {{{552.8f, 0.0f, 0.0f}, {0.0f, 0.0f, 0.0f}, {0.0f, 0.0f, 559.2f}, {549.6f, 0.0f, 559.2f}}}},
      {"ceiling", Material::White, {{{556.0f, 548.8f, 0.0f}, {556.0f, 548.8f, 559.2f}, {0.0f, 548.8f, 559.2f}, {0.0f, 548.8f, 0.0f}}}},
      {"back wall", Material::White, {{{549.6f, 0.0f, 559.2f}, {0.0f, 0.0f, 559.2f}, {0.0f, 548.8f, 559.2f}, {556.0f, 548.8f, 559.2f}}}},
      {"right wall", Material::Green, {{{0.0f, 0.0f, 559.2f}, {0.0f, 0.0f, 0.0f}, {0.0f, 548.8f, 0.0f}, {0.0f, 548.8f, 559.2f}}}},
      {"left wall", Material::Red, {{{552.8f, 0.0f, 0.0f}, {549.6f, 0.0f, 559.2f}, {556.0f, 548.8f, 559.2f}, {556.0f, 548.8f, 0.0f}}}},
  };
  const Vec3 room{278.0f, 274.4f, 279.6f};
  std::vector<Quad> q;
  for (const Wall& w : walls) q.push_back(make(w.name, w.m, w.v, room, true));
  // The two blocks' faces as published (a top, then four sides), each facing away from its
  // block's centre: the short block's five, then the tall block's.
  const char* block_names[2] = {"short block ", "tall block "};
  const Vec3 block_centres[2] = {{186.0f, 82.5f, 168.5f}, {368.5f, 165.0f, 351.5f}};
  const std::array<Vec3, 4> block_faces[2 * 5] = {
      // short block
      {{{130.0f, 165.0f, 65.0f}, {82.0f, 165.0f, 225.0f}, {240.0f, 165.0f, 272.0f}, {290.0f, 165.0f, 114.0f}}},
      {{{290.0f, 0.0f, 114.0f}, {290.0f, 165.0f, 114.0f}, {240.0f, 165.0f, 272.0f}, {240.0f, 0.0f, 272.0f}}},
      {{{130.0f, 0.0f, 65.0f}, {130.0f, 165.0f, 65.0f}, {290.0f, 165.0f, 114.0f}, {290.0f, 0.0f, 114.0f}}},
      {{{82.0f, 0.0f, 225.0f}, {82.0f, 165.0f, 225.0f}, {130.0f, 165.0f, 65.0f}, {130.0f, 0.0f, 65.0f}}},
      {{{240.0f, 0.0f, 272.0f}, {240.0f, 165.0f, 272.0f}, {82.0f, 165.0f, 225.0f}, {82.0f, 0.0f, 225.0f}}},
      // tall block
      {{{423.0f, 330.0f, 247.0f}, {265.0f, 330.0f, 296.0f}, {314.0f, 330.0f, 456.0f}, {472.0f, 330.0f, 406.0f}}},
      {{{423.0f, 0.0f, 247.0f}, {423.0f, 330.0f, 247.0f}, {472.0f, 330.0f, 406.0f}, {472.0f, 0.0f, 406.0f}}},
      {{{472.0f, 0.0f, 406.0f}, {472.0f, 330.0f, 406.0f}, {314.0f, 330.0f, 456.0f}, {314.0f, 0.0f, 456.0f}}},
      {{{314.0f, 0.0f, 456.0f}, {314.0f, 330.0f, 456.0f}, {265.0f, 330.0f, 296.0f}, {265.0f, 0.0f, 296.0f}}},
      {{{265.0f, 0.0f, 296.0f}, {265.0f, 330.0f, 296.0f}, {423.0f, 330.0f, 247.0f}, {423.0f, 0.0f, 247.0f}}},
  };
  const char* sides[5] = {"top", "side 1", "side 2", "side 3", "side 4"};
  for (int b = 0; b < 2; ++b)
    for (int i = 0; i < 5; ++i)
      q.push_back(make(std::string(block_names[b]) + sides[i], Material::White, block_faces[5 * b + i], block_centres[b], false));
  return q;
}

// 400..700 nm every 4 nm: white, green, red (as published).
const float kReflectance[76][3] = {
    {0.343f, 0.092f, 0.040f}, {0.445f, 0.096f, 0.046f}, {0.551f, 0.098f, 0.048f}, {0.624f, 0.097f, 0.053f},
    {0.665f, 0.098f, 0.049f}, {0.687f, 0.095f, 0.050f}, {0.708f, 0.095f, 0.053f}, {0.723f, 0.097f, 0.055f},
    {0.715f, 0.095f, 0.057f}, {0.710f, 0.094f, 0.056f}, {0.745f, 0.097f, 0.059f}, {0.758f, 0.098f, 0.057f},
    {0.739f, 0.096f, 0.061f}, {0.767f, 0.101f, 0.061f}, {0.777f, 0.103f, 0.060f}, {0.765f, 0.104f, 0.062f},
    {0.751f, 0.107f, 0.062f}, {0.745f, 0.109f, 0.062f}, {0.748f, 0.112f, 0.061f}, {0.729f, 0.115f, 0.062f},
    {0.745f, 0.125f, 0.060f}, {0.757f, 0.140f, 0.059f}, {0.753f, 0.160f, 0.057f}, {0.750f, 0.187f, 0.058f},
    {0.746f, 0.229f, 0.058f}, {0.747f, 0.285f, 0.058f}, {0.735f, 0.343f, 0.056f}, {0.732f, 0.390f, 0.055f},
    {0.739f, 0.435f, 0.056f}, {0.734f, 0.464f, 0.059f}, {0.725f, 0.472f, 0.057f}, {0.721f, 0.476f, 0.055f},
    {0.733f, 0.481f, 0.059f}, {0.725f, 0.462f, 0.059f}, {0.732f, 0.447f, 0.058f}, {0.743f, 0.441f, 0.059f},
    {0.744f, 0.426f, 0.061f}, {0.748f, 0.406f, 0.061f}, {0.728f, 0.373f, 0.063f}, {0.716f, 0.347f, 0.063f},
    {0.733f, 0.337f, 0.067f}, {0.726f, 0.314f, 0.068f}, {0.713f, 0.285f, 0.072f}, {0.740f, 0.277f, 0.080f},
    {0.754f, 0.266f, 0.090f}, {0.764f, 0.250f, 0.099f}, {0.752f, 0.230f, 0.124f}, {0.736f, 0.207f, 0.154f},
    {0.734f, 0.186f, 0.192f}, {0.741f, 0.171f, 0.255f}, {0.740f, 0.160f, 0.287f}, {0.732f, 0.148f, 0.349f},
    {0.745f, 0.141f, 0.402f}, {0.755f, 0.136f, 0.443f}, {0.751f, 0.130f, 0.487f}, {0.744f, 0.126f, 0.513f},
    {0.731f, 0.123f, 0.558f}, {0.733f, 0.121f, 0.584f}, {0.744f, 0.122f, 0.620f}, {0.731f, 0.119f, 0.606f},
    {0.712f, 0.114f, 0.609f}, {0.708f, 0.115f, 0.651f}, {0.729f, 0.117f, 0.612f}, {0.730f, 0.117f, 0.610f},
    {0.727f, 0.118f, 0.650f}, {0.707f, 0.120f, 0.638f}, {0.703f, 0.122f, 0.627f}, {0.729f, 0.128f, 0.620f},
    {0.750f, 0.132f, 0.630f}, {0.760f, 0.139f, 0.628f}, {0.751f, 0.144f, 0.642f}, {0.739f, 0.146f, 0.639f},
    {0.724f, 0.150f, 0.657f}, {0.730f, 0.152f, 0.639f}, {0.740f, 0.157f, 0.635f}, {0.737f, 0.159f, 0.642f},
};

Spectrum make_reflectance(int column) {
  Spectrum s;
  for (int i = 0; i < 76; ++i) {
    s.wavelength_nm.push_back(400.0f + 4.0f * i);
    s.value.push_back(kReflectance[i][column]);
  }
  return s;
}

float band_mean(const Spectrum& s, float lo, float hi) {
  // Trapezoid rule over 1 nm steps of the interpolated spectrum.
  double sum = 0;
  int n = 0;
  for (float nm = lo; nm <= hi; nm += 1.0f, ++n) sum += s.at(nm);
  return static_cast<float>(sum / n);
}

}  // namespace

float Quad::area() const {
  Vec3 a = cross(sub(v[1], v[0]), sub(v[2], v[0]));
  Vec3 b = cross(sub(v[2], v[0]), sub(v[3], v[0]));
  return 0.5f * (std::sqrt(dot(a, a)) + std::sqrt(dot(b, b)));
}

const std::vector<Quad>& quads() {
  static const std::vector<Quad> q = build();
  return q;
}

const Camera& camera() {
  static const Camera c;
  return c;
}

float Spectrum::at(float nm) const {
  if (nm <= wavelength_nm.front()) return value.front();
  if (nm >= wavelength_nm.back()) return value.back();
  auto it = std::upper_bound(wavelength_nm.begin(), wavelength_nm.end(), nm);
  std::size_t i = static_cast<std::size_t>(it - wavelength_nm.begin());
  float t = (nm - wavelength_nm[i - 1]) / (wavelength_nm[i] - wavelength_nm[i - 1]);
  return value[i - 1] + t * (value[i] - value[i - 1]);
}

const Spectrum& reflectance(Material m) {
  static const Spectrum white = make_reflectance(0), green = make_reflectance(1),
                        red = make_reflectance(2);
  switch (m) {
    case Material::Green: return green;
    case Material::Red: return red;
    default: return white;
  }
}

const Spectrum& light_emission() {
  static const Spectrum s{{400.0f, 500.0f, 600.0f, 700.0f}, {0.0f, 8.0f, 15.6f, 18.4f}};
  return s;
}

std::array<float, 3> rgb(Material m) {
  const Spectrum& s = m == Material::Light ? light_emission() : reflectance(m);
  std::array<float, 3> c = {band_mean(s, 600, 700), band_mean(s, 500, 600), band_mean(s, 400, 500)};
  if (m == Material::Light) {
    float mean = (c[0] + c[1] + c[2]) / 3.0f;
    for (auto& x : c) x /= mean;
  }
  return c;
}

}  // namespace bhcl::cornell
