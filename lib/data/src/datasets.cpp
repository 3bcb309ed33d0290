#include "blockhash_cl/datasets.hpp"

#include <algorithm>

#include <array>
#include <cmath>
#include <random>

#include "blockhash_cl/cornell_box.hpp"

#include "blockhash_cl/error.hpp"

namespace bhcl::datasets {

std::vector<float> uniform(std::size_t n, std::uint64_t seed, float lo, float hi) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(lo, hi);
  std::vector<float> xyz(3 * n);
  for (auto& v : xyz) v = u(rng);
  return xyz;
}

std::vector<float> clustered(std::size_t n, std::uint64_t seed, int clusters, float sigma,
                             std::uint64_t centre_seed) {
  std::mt19937_64 crng(centre_seed);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::vector<float> centres(3 * static_cast<std::size_t>(clusters));
  for (auto& c : centres) c = u(crng);
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> g(0.0f, sigma);
  std::uniform_int_distribution<int> pick(0, clusters - 1);
  std::vector<float> xyz(3 * n);
  for (std::size_t i = 0; i < n; ++i) {
    int c = pick(rng);
    for (int d = 0; d < 3; ++d) xyz[3 * i + d] = centres[3 * c + d] + g(rng);
  }
  return xyz;
}

std::vector<float> with_duplicates(std::size_t n, std::uint64_t seed, double fraction) {
  std::vector<float> xyz = uniform(n, seed);
  std::mt19937_64 rng(seed ^ 0x9e3779b97f4a7c15ull);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  for (std::size_t i = 1; i < n; ++i) {
    if (u(rng) < fraction) {
      std::size_t src = std::uniform_int_distribution<std::size_t>(0, i - 1)(rng);
      for (int d = 0; d < 3; ++d) xyz[3 * i + d] = xyz[3 * src + d];
    }
  }
  return xyz;
}

void offset(std::vector<float>& xyz, double dx, double dy, double dz) {
  for (std::size_t i = 0; i + 2 < xyz.size(); i += 3) {
    xyz[i] = static_cast<float>(xyz[i] + dx);
    xyz[i + 1] = static_cast<float>(xyz[i + 1] + dy);
    xyz[i + 2] = static_cast<float>(xyz[i + 2] + dz);
  }
}

namespace {

using cornell::Vec3;

// Surfaces that receive photons: everything but the light.
struct SurfaceSampler {
  std::vector<const cornell::Quad*> quads;
  std::vector<double> cdf;  // by area
  SurfaceSampler() {
    double total = 0;
    for (const auto& q : cornell::quads()) {
      if (q.material == cornell::Material::Light) continue;
      quads.push_back(&q);
      total += q.area();
      cdf.push_back(total);
    }
    for (auto& c : cdf) c /= total;
  }
  // A point uniform by area on a uniformly-by-area chosen quad. n: the unit normal of the
  // triangle it lies on (quads are split in (0,1,2) and (0,2,3); the measured left wall is not
  // planar), oriented like the quad's normal.
  void sample(std::mt19937_64& rng, Vec3& p, Vec3& n) const {
    std::uniform_real_distribution<double> u(0.0, 1.0);
    std::size_t i = std::lower_bound(cdf.begin(), cdf.end(), u(rng)) - cdf.begin();
    i = std::min(i, quads.size() - 1);
    const cornell::Quad& q = *quads[i];
    double c1[3], c2[3];
    auto tri = [](const Vec3& a, const Vec3& b, const Vec3& c, double* cr) {
      double ux = b[0] - a[0], uy = b[1] - a[1], uz = b[2] - a[2];
      double vx = c[0] - a[0], vy = c[1] - a[1], vz = c[2] - a[2];
      cr[0] = uy * vz - uz * vy, cr[1] = uz * vx - ux * vz, cr[2] = ux * vy - uy * vx;
      return 0.5 * std::sqrt(cr[0] * cr[0] + cr[1] * cr[1] + cr[2] * cr[2]);
    };
    double a1 = tri(q.v[0], q.v[1], q.v[2], c1), a2 = tri(q.v[0], q.v[2], q.v[3], c2);
    bool first = u(rng) * (a1 + a2) < a1;
    const Vec3& A = q.v[0];
    const Vec3& B = first ? q.v[1] : q.v[2];
    const Vec3& C = first ? q.v[2] : q.v[3];
    const double* cr = first ? c1 : c2;
    double len = std::sqrt(cr[0] * cr[0] + cr[1] * cr[1] + cr[2] * cr[2]);
    double sgn = (cr[0] * q.normal[0] + cr[1] * q.normal[1] + cr[2] * q.normal[2]) < 0 ? -1 : 1;
    for (int d = 0; d < 3; ++d) n[d] = static_cast<float>(sgn * cr[d] / len);
    double r1 = std::sqrt(u(rng)), r2 = u(rng);
    for (int d = 0; d < 3; ++d)
      p[d] = static_cast<float>((1 - r1) * A[d] + r1 * (1 - r2) * B[d] + r1 * r2 * C[d]);
  }
};

// Nearest hit of a ray with the non-light quads (two triangles each, Moller-Trumbore).
bool first_hit(const Vec3& o, const Vec3& d, Vec3& hit) {
  double best = INFINITY;
  for (const auto& q : cornell::quads()) {
    if (q.material == cornell::Material::Light) continue;
    for (int t = 0; t < 2; ++t) {
      const Vec3& a = q.v[0];
      const Vec3& b = q.v[t == 0 ? 1 : 2];
      const Vec3& c = q.v[t == 0 ? 2 : 3];
      double e1[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
      double e2[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
      double pv[3] = {d[1] * e2[2] - d[2] * e2[1], d[2] * e2[0] - d[0] * e2[2], d[0] * e2[1] - d[1] * e2[0]};
      double det = e1[0] * pv[0] + e1[1] * pv[1] + e1[2] * pv[2];
      if (std::abs(det) < 1e-12) continue;
      double inv = 1.0 / det;
      double tv[3] = {o[0] - a[0], o[1] - a[1], o[2] - a[2]};
      double u = (tv[0] * pv[0] + tv[1] * pv[1] + tv[2] * pv[2]) * inv;
      if (u < 0 || u > 1) continue;
      double qv[3] = {tv[1] * e1[2] - tv[2] * e1[1], tv[2] * e1[0] - tv[0] * e1[2], tv[0] * e1[1] - tv[1] * e1[0]};
      double v = (d[0] * qv[0] + d[1] * qv[1] + d[2] * qv[2]) * inv;
      if (v < 0 || u + v > 1) continue;
      double s = (e2[0] * qv[0] + e2[1] * qv[1] + e2[2] * qv[2]) * inv;
      if (s > 1e-3 && s < best) best = s;
    }
  }
  if (!std::isfinite(best)) return false;
  for (int k = 0; k < 3; ++k) hit[k] = static_cast<float>(o[k] + best * d[k]);
  return true;
}

// The cos^8 half of the photon-like set: rays from just under the light's centre.
bool lobe_point(std::mt19937_64& rng, Vec3& p) {
  std::uniform_real_distribution<double> u(0.0, 1.0);
  double cos_t = std::pow(u(rng), 1.0 / 9.0);  // pdf ~ cos^8(theta) on the hemisphere
  double sin_t = std::sqrt(std::max(0.0, 1.0 - cos_t * cos_t));
  double phi = 2.0 * M_PI * u(rng);
  Vec3 o = {278.0f, 548.0f, 279.5f};
  Vec3 d = {static_cast<float>(sin_t * std::cos(phi)), static_cast<float>(-cos_t),
            static_cast<float>(sin_t * std::sin(phi))};
  return first_hit(o, d, p);
}

// n points on one generator seeded with `seed`, point i drawn by draw(rng, u, i, xyz, p, normal)
// into xyz[3 i ..] (p and normal: a surface sample's scratch).
template <class Draw>
std::vector<float> draw_points(std::size_t n, std::uint64_t seed, Draw draw) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<float> xyz(3 * n);
  for (std::size_t i = 0; i < n; ++i) {
    Vec3 p, normal;
    draw(rng, u, i, xyz, p, normal);
  }
  return xyz;
}

}  // namespace

std::vector<float> cornell_photons(std::size_t n, std::uint64_t seed) {
  static const SurfaceSampler sampler;
  return draw_points(n, seed, [&](std::mt19937_64& rng, std::uniform_real_distribution<double>& u, std::size_t i,
                                  std::vector<float>& xyz, Vec3& p, Vec3& normal) {
    if (i > 0 && u(rng) < 0.01) {  // an exact duplicate of an earlier point
      std::size_t src = std::uniform_int_distribution<std::size_t>(0, i - 1)(rng);
      for (int d = 0; d < 3; ++d) xyz[3 * i + d] = xyz[3 * src + d];
      return;
    }
    if (u(rng) < 0.5 || !lobe_point(rng, p)) sampler.sample(rng, p, normal);
    for (int d = 0; d < 3; ++d) xyz[3 * i + d] = p[d];
  });
}

std::vector<float> cornell_queries(std::size_t n, std::uint64_t seed, float offset_mm) {
  static const SurfaceSampler sampler;
  return draw_points(n, seed, [&](std::mt19937_64& rng, std::uniform_real_distribution<double>&, std::size_t i,
                                  std::vector<float>& xyz, Vec3& p, Vec3& normal) {
    sampler.sample(rng, p, normal);
    for (int d = 0; d < 3; ++d) xyz[3 * i + d] = p[d] + offset_mm * normal[d];
  });
}

std::vector<float> by_name(const std::string& name, std::size_t n, std::uint64_t seed) {
  if (name == "uniform") return uniform(n, seed);
  if (name == "clustered") return clustered(n, seed);
  if (name == "duplicates") return with_duplicates(n, seed, 0.10);
  if (name == "cornell") return cornell_photons(n, seed);
  throw Error("unknown data set '" + name + "' (uniform, clustered, duplicates, cornell)");
}

std::vector<float> queries_by_name(const std::string& name, std::size_t n, std::uint64_t seed) {
  if (name == "cornell") return cornell_queries(n, seed, 0.5f);
  return by_name(name, n, seed);
}

}  // namespace bhcl::datasets
