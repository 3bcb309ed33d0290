#include "surface_area.hpp"

#include <algorithm>
#include <array>
#include <chrono>

#include "blockhash_cl/error.hpp"
#include "embree_scene.hpp"
#include "parallel.hpp"

namespace bhcl::render {
namespace {

constexpr float kPlaneCos = 0.99863f;    // cos 3 degrees
constexpr float kPlaneTol = 5e-3f;       // of the scene diagonal (the measured left wall: 3.2 mm of 964)
constexpr int kRings = 16, kSectors = 16;  // the disc pattern: 256 equal-area samples
constexpr std::uint16_t kOrth = 5, kDiag = 7, kFar = 65535;  // chamfer weights: 7/5 < sqrt 2 (never over)

// The disc pattern: sample s at radius rho[s] (of the disc's radius) and angle th[s]; ring i holds
// the area between sqrt(i / R) and sqrt((i + 1) / R), its samples at its area midpoint, odd rings
// turned by half a sector.
struct DiscPattern {
  std::array<float, kRings * kSectors> x{}, y{}, rho{};
  DiscPattern() {
    for (int i = 0; i < kRings; ++i)
      for (int j = 0; j < kSectors; ++j) {
        const int s = i * kSectors + j;
        rho[s] = std::sqrt((i + 0.5f) / kRings);
        const float th = 2 * kPi * (j + 0.5f * (i & 1) + 0.25f) / kSectors;
        x[s] = rho[s] * std::cos(th);
        y[s] = rho[s] * std::sin(th);
      }
  }
};
const DiscPattern& pattern() {
  static const DiscPattern p;
  return p;
}

// Triangle t's corners in a plane's (u, v) coordinates and twice its signed area there (0:
// degenerate): what the raster's cover test and the exact edge equations both start from.
struct PlaneTriangle {
  float a[3], b[3];
  float area2;
};
PlaneTriangle project_triangle(const Scene& scene, std::uint32_t t, Vec3 u, Vec3 v) {
  const auto& tri = scene.triangles[t];
  PlaneTriangle pt{};
  for (int k = 0; k < 3; ++k) {
    pt.a[k] = dot(scene.vertices[tri[k]], u);
    pt.b[k] = dot(scene.vertices[tri[k]], v);
  }
  pt.area2 = (pt.a[1] - pt.a[0]) * (pt.b[2] - pt.b[0]) - (pt.a[2] - pt.a[0]) * (pt.b[1] - pt.b[0]);
  return pt;
}

Vec3 any_perpendicular(Vec3 n) {
  const Vec3 a = std::fabs(n.x) < 0.6f ? Vec3{1, 0, 0} : (std::fabs(n.y) < 0.6f ? Vec3{0, 1, 0} : Vec3{0, 0, 1});
  return normalize(cross(n, a));
}

}  // namespace

SurfaceAreaMap::SurfaceAreaMap(const EmbreeScene& es, int threads) : es_(&es) {
  const auto t0 = std::chrono::steady_clock::now();
  group_planes(es);
  // One cell size for every plane: diagonal / 1024, coarser if all planes' rasters would pass
  // kMaxCells (the memory is bounded before anything is allocated).
  const Scene& scene = es.scene();
  h_ = scene.diagonal() / 1024.0f;
  for (int attempt = 0; attempt < 64; ++attempt) {
    std::size_t total = 0;
    for (Plane& p : planes_) {
      float amin = INFINITY, amax = -INFINITY, bmin = INFINITY, bmax = -INFINITY;
      for (std::uint32_t t : p.tris)
        for (std::uint32_t vi : scene.triangles[t]) {
          const Vec3 v = scene.vertices[vi];
          amin = std::min(amin, dot(v, p.u));
          amax = std::max(amax, dot(v, p.u));
          bmin = std::min(bmin, dot(v, p.v));
          bmax = std::max(bmax, dot(v, p.v));
        }
      p.a0 = amin - h_;
      p.b0 = bmin - h_;
      p.nu = static_cast<int>(std::ceil((amax - amin) / h_)) + 2;
      p.nv = static_cast<int>(std::ceil((bmax - bmin) / h_)) + 2;
      total += static_cast<std::size_t>(p.nu) * static_cast<std::size_t>(p.nv);
    }
    cells_ = total;
    if (total <= kMaxCells) break;
    h_ *= std::sqrt(static_cast<float>(total) / kMaxCells) * 1.01f;
  }
  if (cells_ > kMaxCells)
    throw Error("render: the surface rasters of the boundary correction need " + std::to_string(cells_) +
                " cells, more than " + std::to_string(kMaxCells));
  for (Plane& p : planes_) rasterise(es, p, threads);
  build_s_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Diffuse triangles into planes: the first plane (in triangle order) whose normal is within 3
// degrees and from which every vertex is within kPlaneTol diagonals, else a new one.
void SurfaceAreaMap::group_planes(const EmbreeScene& es) {
  const Scene& scene = es.scene();
  const float tol = kPlaneTol * scene.diagonal();
  plane_of_.assign(scene.triangles.size(), -1);
  for (std::uint32_t t = 0; t < scene.triangles.size(); ++t) {
    if (!scene.material_of(t).is_diffuse() || !(scene.triangle_area(t) > 0)) continue;
    const Vec3 n = scene.geometric_normal(t);
    const auto& tri = scene.triangles[t];
    int found = -1;
    for (std::size_t g = 0; g < planes_.size() && found < 0; ++g) {
      const Plane& p = planes_[g];
      if (dot(n, p.n) < kPlaneCos) continue;
      bool near = true;
      for (std::uint32_t vi : tri) near = near && std::fabs(dot(scene.vertices[vi], p.n) - p.d) <= tol;
      if (near) found = static_cast<int>(g);
    }
    if (found < 0) {
      Plane p;
      p.n = n;
      p.u = any_perpendicular(n);
      p.v = cross(n, p.u);
      p.d = dot(scene.vertices[tri[0]], n);
      planes_.push_back(std::move(p));
      found = static_cast<int>(planes_.size()) - 1;
    }
    planes_[found].tris.push_back(t);
    plane_of_[t] = found;
  }
}

// Which cells of plane p lie on its triangles (cell centres, projected along the plane's normal),
// and the medium on their front side: one ray along the triangle's normal from the point on it.
void SurfaceAreaMap::rasterise(const EmbreeScene& es, Plane& p, int threads) {
  const Scene& scene = es.scene();
  const std::size_t n = static_cast<std::size_t>(p.nu) * p.nv;
  p.code.assign(n, kOff);
  std::vector<std::uint32_t> cover(n, ~0u);  // the triangle covering each cell
  for (std::uint32_t t : p.tris) {
    const PlaneTriangle pt = project_triangle(scene, t, p.u, p.v);
    const float *a = pt.a, *b = pt.b, area2 = pt.area2;
    if (area2 == 0) continue;
    const int i0 = std::max(0, static_cast<int>((std::min({a[0], a[1], a[2]}) - p.a0) / h_) - 1);
    const int i1 = std::min(p.nu - 1, static_cast<int>((std::max({a[0], a[1], a[2]}) - p.a0) / h_) + 1);
    const int j0 = std::max(0, static_cast<int>((std::min({b[0], b[1], b[2]}) - p.b0) / h_) - 1);
    const int j1 = std::min(p.nv - 1, static_cast<int>((std::max({b[0], b[1], b[2]}) - p.b0) / h_) + 1);
    for (int j = j0; j <= j1; ++j)
      for (int i = i0; i <= i1; ++i) {
        const float ca = p.a0 + (i + 0.5f) * h_, cb = p.b0 + (j + 0.5f) * h_;
        bool inside = true;
        for (int k = 0; k < 3 && inside; ++k) {
          const int k1 = (k + 1) % 3;
          const float e = (a[k1] - a[k]) * (cb - b[k]) - (ca - a[k]) * (b[k1] - b[k]);
          inside = (area2 > 0 ? e : -e) >= 0;
        }
        if (inside) cover[static_cast<std::size_t>(j) * p.nu + i] = t;
      }
  }
  parallel_chunks(static_cast<std::size_t>(p.nv), 8, threads, [&](std::size_t, std::size_t jb, std::size_t je) {
    for (std::size_t j = jb; j < je; ++j)
      for (int i = 0; i < p.nu; ++i) {
        const std::size_t c = j * p.nu + i;
        if (cover[c] != ~0u) p.code[c] = medium_by_ray(p, cover[c], p.a0 + (i + 0.5f) * h_, p.b0 + (j + 0.5f) * h_);
      }
  });
  es.check("boundary correction rasters");
  chamfer(p);
  mark_edges(p);
}

void SurfaceAreaMap::mark_edges(Plane& p) const {
  p.edge.assign(p.code.size(), 0);
  for (int j = 0; j < p.nv; ++j)
    for (int i = 0; i < p.nu; ++i) {
      const std::uint8_t c = p.at(i, j);
      std::uint8_t e = 0, on = c;
      for (int k = 0; k < 4; ++k) {
        const std::uint8_t o = p.at(i + (k == 0) - (k == 1), j + (k == 2) - (k == 3));
        if ((o == kOff) != (c == kOff)) e |= kEdgeCover;
        if (o != kOff && c != kOff && o != c) e |= kEdgeMedium;
        if (on == kOff) on = o;
      }
      p.edge[static_cast<std::size_t>(j) * p.nu + i] = static_cast<std::uint8_t>(e | (on << 2));
    }
  const Scene& scene = es_->scene();
  p.edges.clear();
  for (std::uint32_t t : p.tris) {
    const PlaneTriangle pt = project_triangle(scene, t, p.u, p.v);
    const float *ta = pt.a, *tb = pt.b, area2 = pt.area2;
    const float sg = area2 > 0 ? 1.0f : area2 < 0 ? -1.0f : 0.0f;  // 0: degenerate, never inside
    std::array<float, 9> e{};
    for (int k = 0; k < 3; ++k) {
      const int k1 = (k + 1) % 3;
      // (ta1 - ta0)(b - tb0) - (a - ta0)(tb1 - tb0) >= 0 inside (counter-clockwise)
      e[3 * k] = -sg * (tb[k1] - tb[k]);
      e[3 * k + 1] = sg * (ta[k1] - ta[k]);
      e[3 * k + 2] = sg * ((tb[k1] - tb[k]) * ta[k] - (ta[k1] - ta[k]) * tb[k]);
    }
    if (sg == 0) e[2] = -1;  // a degenerate triangle holds nothing
    p.edges.push_back(e);
  }
  p.sub_of.assign(p.code.size(), ~0u);
  p.sub.clear();
  for (std::size_t c = 0; c < p.code.size(); ++c) {
    if (!(p.edge[c] & kEdgeMedium)) continue;
    const int i = static_cast<int>(c % p.nu), j = static_cast<int>(c / p.nu);
    p.sub_of[c] = static_cast<std::uint32_t>(p.sub.size());
    for (int sj = 0; sj < 4; ++sj)
      for (int si = 0; si < 4; ++si) {
        const float a = p.a0 + (i + (si + 0.5f) / 4) * h_, b = p.b0 + (j + (sj + 0.5f) / 4) * h_;
        const std::uint32_t t = holder_of(p, a, b);
        p.sub.push_back(t == ~0u ? kOff : medium_by_ray(p, t, a, b));
      }
  }
}

std::uint32_t SurfaceAreaMap::holder_of(const Plane& p, float a, float b) {
  for (std::size_t k = 0; k < p.edges.size(); ++k) {
    const std::array<float, 9>& e = p.edges[k];
    if (e[0] * a + e[1] * b + e[2] >= 0 && e[3] * a + e[4] * b + e[5] >= 0 && e[6] * a + e[7] * b + e[8] >= 0)
      return p.tris[k];
  }
  return ~0u;
}

// The medium on the front side of triangle tri at plane coordinates (a, b): the point on the
// triangle itself (a plane's triangles may lie up to kPlaneTol off its plane), then one ray along
// that triangle's normal (rasterise's per cell, mark_edges' per sub-cell).
std::uint8_t SurfaceAreaMap::medium_by_ray(const Plane& p, std::uint32_t tri, float a, float b) const {
  const Scene& scene = es_->scene();
  const Vec3 nt = scene.geometric_normal(tri);
  const Vec3 on_plane = p.n * p.d + p.u * a + p.v * b;
  const float s = (dot(scene.vertices[scene.triangles[tri][0]], nt) - dot(on_plane, nt)) / dot(p.n, nt);
  const Vec3 x = on_plane + p.n * s;
  EmbreeScene::Hit hit;
  if (es_->intersect(x + nt * es_->ray_epsilon(), nt, 0.0f, INFINITY, hit) &&
      dot(scene.geometric_normal(hit.prim), nt) > 0)
    return scene.material_of(hit.prim).type == MaterialType::Glass ? kGlass : kClosed;
  return kAir;
}

std::uint8_t SurfaceAreaMap::code_at(const Plane& p, float a, float b) const {
  const int i = static_cast<int>(std::floor((a - p.a0) / h_)), j = static_cast<int>(std::floor((b - p.b0) / h_));
  if (i < 0 || j < 0 || i >= p.nu || j >= p.nv) return kOff;
  const std::size_t c = static_cast<std::size_t>(j) * p.nu + i;
  const std::uint8_t e = p.edge[c];
  if (!(e & (kEdgeCover | kEdgeMedium)) || p.tris.size() > kExactTriangles) return p.code[c];
  if (e & kEdgeMedium) {
    const int si = std::min(3, std::max(0, static_cast<int>(((a - p.a0) / h_ - i) * 4)));
    const int sj = std::min(3, std::max(0, static_cast<int>(((b - p.b0) / h_ - j) * 4)));
    return p.sub[p.sub_of[c] + static_cast<std::size_t>(sj) * 4 + si];
  }
  const std::uint32_t holder = holder_of(p, a, b);
  if (holder == ~0u) return kOff;
  const std::uint8_t own = p.code[c];
  return own != kOff ? own : static_cast<std::uint8_t>(e >> 2);
}

// dist: 0 on a cell with a 4-neighbour (or the raster's border) of another code, else the chamfer
// distance (5 a cell orthogonally, 7 diagonally) to such a cell.
void SurfaceAreaMap::chamfer(Plane& p) {
  const int nu = p.nu, nv = p.nv;
  p.dist.assign(static_cast<std::size_t>(nu) * nv, kFar);
  auto idx = [nu](int i, int j) { return static_cast<std::size_t>(j) * nu + i; };
  for (int j = 0; j < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      const std::uint8_t c = p.at(i, j);
      if (p.at(i - 1, j) != c || p.at(i + 1, j) != c || p.at(i, j - 1) != c || p.at(i, j + 1) != c) p.dist[idx(i, j)] = 0;
    }
  auto relax = [&](int i, int j, int di, int dj, std::uint16_t w) {
    const int a = i + di, b = j + dj;
    if (a < 0 || b < 0 || a >= nu || b >= nv) return;
    const std::uint32_t d = static_cast<std::uint32_t>(p.dist[idx(a, b)]) + w;
    std::uint16_t& here = p.dist[idx(i, j)];
    if (d < here) here = static_cast<std::uint16_t>(d);
  };
  for (int j = 0; j < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      relax(i, j, -1, 0, kOrth);
      relax(i, j, 0, -1, kOrth);
      relax(i, j, -1, -1, kDiag);
      relax(i, j, 1, -1, kDiag);
    }
  for (int j = nv - 1; j >= 0; --j)
    for (int i = nu - 1; i >= 0; --i) {
      relax(i, j, 1, 0, kOrth);
      relax(i, j, 0, 1, kOrth);
      relax(i, j, 1, 1, kDiag);
      relax(i, j, -1, 1, kDiag);
    }
}

float SurfaceAreaMap::factor(std::uint32_t prim, bool back, Vec3 x, bool in_glass, float r2,
                             DensityFilter filter) const {
  if (back || !(r2 > 0) || prim >= plane_of_.size() || plane_of_[prim] < 0) return 1.0f;
  const Plane& p = planes_[static_cast<std::size_t>(plane_of_[prim])];
  const float a = dot(x, p.u), b = dot(x, p.v), r = std::sqrt(r2);
  const int i = static_cast<int>(std::floor((a - p.a0) / h_)), j = static_cast<int>(std::floor((b - p.b0) / h_));
  if (i < 0 || j < 0 || i >= p.nu || j >= p.nv) return 1.0f;
  // Farther than r from every cell of another kind (1.5 cells for the point's place in its cell
  // and the boundary cell's own half): the whole disc is on the surface.
  const float clear = (p.dist[static_cast<std::size_t>(j) * p.nu + i] / float(kOrth) - 1.5f) * h_;
  if (clear > r) return 1.0f;
  const std::uint8_t want = in_glass ? kGlass : kAir;
  const DiscPattern& d = pattern();
  float all = 0, in = 0;
  for (std::size_t s = 0; s < d.x.size(); ++s) {
    const float w = filter_weight(filter, d.rho[s] * d.rho[s], 1.0f, 1.0f);
    all += w;
    if (code_at(p, a + r * d.x[s], b + r * d.y[s]) == want) in += w;
  }
  if (!(in > 0)) return 1.0f;
  return std::min(kMaxFactor, all / in);
}

}  // namespace bhcl::render
