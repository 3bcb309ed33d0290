// The embedded Cornell Box and the generated data sets.
#include "test_util.hpp"

#include "blockhash_cl/cornell_box.hpp"

using namespace bhcl;

namespace {

// Distance from p to the nearer of the planes of q's two triangles (the measured left wall is
// not planar).
double plane_distance(const cornell::Quad& q, const float* p) {
  double best = INFINITY;
  for (int t = 0; t < 2; ++t) {
    const auto& a = q.v[0];
    const auto& b = q.v[t == 0 ? 1 : 2];
    const auto& c = q.v[t == 0 ? 2 : 3];
    double u[3], v[3], n[3];
    for (int d = 0; d < 3; ++d) u[d] = b[d] - a[d], v[d] = c[d] - a[d];
    n[0] = u[1] * v[2] - u[2] * v[1], n[1] = u[2] * v[0] - u[0] * v[2], n[2] = u[0] * v[1] - u[1] * v[0];
    double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]), s = 0;
    for (int d = 0; d < 3; ++d) s += (double(p[d]) - a[d]) * n[d] / len;
    best = std::min(best, std::abs(s));
  }
  return best;
}
bool in_bounds(const cornell::Quad& q, const float* p, float slack) {
  for (int d = 0; d < 3; ++d) {
    float lo = INFINITY, hi = -INFINITY;
    for (const auto& v : q.v) lo = std::min(lo, v[d]), hi = std::max(hi, v[d]);
    if (p[d] < lo - slack || p[d] > hi + slack) return false;
  }
  return true;
}
const cornell::Quad* nearest_quad(const float* p, double* dist) {
  const cornell::Quad* best = nullptr;
  *dist = INFINITY;
  for (const auto& q : cornell::quads()) {
    if (q.material == cornell::Material::Light || !in_bounds(q, p, 1.0f)) continue;
    double d = plane_distance(q, p);
    if (d < *dist) *dist = d, best = &q;
  }
  return best;
}

}  // namespace

TEST_CASE("cornell box: geometry and normals as measured") {
  const auto& qs = cornell::quads();
  REQUIRE(qs.size() == 16);  // light, 5 walls, 2 x 5 block faces
  auto find = [&](const std::string& name) {
    for (const auto& q : qs)
      if (q.name == name) return q;
    FAIL("no quad " << name);
    return qs[0];
  };
  CHECK(find("floor").normal[1] == doctest::Approx(1.0));
  CHECK(find("ceiling").normal[1] == doctest::Approx(-1.0));
  CHECK(find("light").normal[1] == doctest::Approx(-1.0));
  CHECK(find("back wall").normal[2] == doctest::Approx(-1.0).epsilon(0.01));
  CHECK(find("right wall").normal[0] == doctest::Approx(1.0));
  CHECK(find("left wall").normal[0] == doctest::Approx(-1.0).epsilon(0.01));
  CHECK(find("short block top").normal[1] == doctest::Approx(1.0));
  CHECK(find("tall block top").normal[1] == doctest::Approx(1.0));
  CHECK(find("light").area() == doctest::Approx(130.0 * 105.0));
  CHECK(find("left wall").material == cornell::Material::Red);
  auto white = cornell::rgb(cornell::Material::White), red = cornell::rgb(cornell::Material::Red);
  CHECK(white[0] > 0.7f);
  CHECK(red[0] > 5 * red[2]);
  auto light = cornell::rgb(cornell::Material::Light);
  CHECK((light[0] + light[1] + light[2]) / 3 == doctest::Approx(1.0));
  CHECK(light[0] > light[2]);  // the measured light is warm
}

TEST_CASE("datasets: cornell photons lie on the surfaces, with duplicates and the light's lobe") {
  const std::size_t n = 20000;
  auto pts = datasets::cornell_photons(n, 3);
  REQUIRE(pts.size() == 3 * n);
  std::size_t under_light = 0;
  for (std::size_t i = 0; i < n; ++i) {
    double d;
    const cornell::Quad* q = nearest_quad(&pts[3 * i], &d);
    INFO("point " << i << " (" << pts[3 * i] << ", " << pts[3 * i + 1] << ", " << pts[3 * i + 2] << ")");
    REQUIRE(q != nullptr);
    REQUIRE(d < 0.05);
    float x = pts[3 * i], z = pts[3 * i + 2];
    if (std::abs(x - 278) < 100 && std::abs(z - 280) < 100) ++under_light;
  }
  // The footprint under the light is ~13 % of the floor+walls+blocks area seen from above, but
  // the cos^8 lobe puts far more points there.
  CHECK(under_light > n / 5);
  std::set<std::array<float, 3>> uniq;
  for (std::size_t i = 0; i < n; ++i) uniq.insert({pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]});
  double dup = 1.0 - double(uniq.size()) / n;
  CHECK(dup > 0.005);
  CHECK(dup < 0.02);
  CHECK(datasets::cornell_photons(100, 3) == datasets::cornell_photons(100, 3));
}

TEST_CASE("datasets: cornell queries sit 0.5 mm off a surface") {
  // Near edges and corners another surface's plane can be nearer than the 0.5 mm of the surface
  // the query was drawn on; elsewhere the nearest plane is at 0.5 mm.
  auto qs = datasets::cornell_queries(2000, 4, 0.5f);
  std::size_t at_half = 0;
  for (std::size_t i = 0; i < 2000; ++i) {
    double d;
    REQUIRE(nearest_quad(&qs[3 * i], &d) != nullptr);
    CHECK(d <= 0.5 + 1e-3);
    at_half += std::abs(d - 0.5) < 5e-3;
  }
  CHECK(at_half > 1900);
}
