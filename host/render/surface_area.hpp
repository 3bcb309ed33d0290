// Boundary-corrected density estimates: the area of an estimate's disc that lies on the surface its
// gather point is on.
//
// A density estimate divides the photons' power found within r by pi r^2, the area of a disc that
// is wholly on the surface. Within r of a wall, a corner, the foot of a block or the footprint of
// the glass (whose photons are keyed apart, photon.hpp) part of that disc is off the surface, or on
// a part of it no photon reaches, and the estimate is low: by 1/2 at a straight edge, 3/4 at a
// right-angled corner. The bias shrinks only with r (progressive passes: r_64 / r_1 = 0.53), so on
// the Cornell boxes it held the worst 16x16 tile at -3.7 % (the room's top corners) after 64 passes
// (issue 41). The correction, as the literature's boundary corrections do: count only the photons
// on the gather point's own surface (PhotonMap: same orientation class, surface_class below) and
// divide by the filter's integral over the part of the disc on that surface.
//
// The surfaces: the scene's diffuse triangles grouped into planes (normals within 3 degrees, every
// vertex within 0.5 % of the scene diagonal of the plane: the measured Cornell left wall is 3.2 mm
// off planar). Each plane gets a raster of cells (diagonal / 1024, or coarser so that all planes
// fit kMaxCells) that says per cell whether it is on one of the plane's triangles and, if so, in
// which medium its front side lies: air, inside glass, or closed off (the first surface a ray along
// the normal meets is the back of an opaque surface: the floor under the mirror block, the ceiling
// above the light; no photon lands there). A chamfer distance to the nearest cell of another kind
// lets most queries (farther than r from every boundary) skip the disc: factor 1. The others test
// a fixed stratified pattern of the disc (16 equal-area rings x 16 sectors) against the raster and
// weight each sample by the filter. Cell centres alone would move every boundary by up to half a
// cell (0.47 mm on the Cornell box: 5-7 % of a 10 mm disc's area at a wall), so a sample that falls
// in a cell at a boundary is resolved: tested exactly against the plane's triangles (planes of up to
// kExactTriangles), and at a boundary between media (a block's foot, the glass's footprint, the
// light's outline) looked up on 4 x 4 sub-cells traced at build (a ray per sample at every query
// was 40 % of a pass).
//
// Back-side queries, planes of other scenes smaller than a few cells, and tessellated curved
// surfaces are outside its model (factor 1 where no plane raster covers the point; on a curved mesh
// each facet is its own plane and the correction would be wrong: use --boundary none there).
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

#include "density.hpp"
#include "vec.hpp"

namespace bhcl::render {

class EmbreeScene;

// The orientation class of a unit normal n (on the side the light arrives from): its largest
// component's axis and sign, 0..5. Photons and queries of different classes are on different
// surfaces (at a right-angled corner always); two planes of one class within one disc of each
// other are not separated (not in the shipped scenes).
inline int surface_class(Vec3 n) {
  const float ax = std::fabs(n.x), ay = std::fabs(n.y), az = std::fabs(n.z);
  if (ax >= ay && ax >= az) return n.x >= 0 ? 0 : 1;
  if (ay >= az) return n.y >= 0 ? 2 : 3;
  return n.z >= 0 ? 4 : 5;
}
// The class as a unit axis vector: dot > 0 exactly for one class (the fused estimate's facing test
// then keeps only the query's class, PhotonMap::estimate).
inline Vec3 surface_class_vector(int c) {
  Vec3 v{0, 0, 0};
  const float s = (c & 1) ? -1.0f : 1.0f;
  if (c < 2) v.x = s;
  else if (c < 4) v.y = s;
  else v.z = s;
  return v;
}

class SurfaceAreaMap {
 public:
  static constexpr std::size_t kMaxCells = std::size_t(1) << 24;  // all planes: 48 MiB
  static constexpr float kMaxFactor = 16.0f;  // a sliver of a disc on the surface: noise, not signal

  // Groups es's diffuse triangles into planes and rasterises them (one ray per covered cell).
  // threads: 0 = every CPU.
  SurfaceAreaMap(const EmbreeScene& es, int threads);

  // The filter's integral over the whole disc over its integral over the part of the disc on the
  // query's surface: the factor the estimate sum w Phi / (norm_w pi r^2) is multiplied by. x is the
  // gather point (not medium-keyed), prim its triangle, back whether it is on the triangle's back
  // side, in_glass its medium, r2 the disc's squared radius. 1 where the disc is wholly on the
  // surface, where no plane covers prim, on a back side, or for r2 <= 0.
  float factor(std::uint32_t prim, bool back, Vec3 x, bool in_glass, float r2, DensityFilter filter) const;

  std::size_t planes() const { return planes_.size(); }
  std::size_t cells() const { return cells_; }
  float cell_size() const { return h_; }
  double build_seconds() const { return build_s_; }

  // Cell codes.
  static constexpr std::uint8_t kOff = 0, kAir = 1, kGlass = 2, kClosed = 3;

 private:
  struct Plane {
    Vec3 n, u, v;        // front normal, in-plane axes
    float d = 0;         // dot(n, x) on the plane
    float a0 = 0, b0 = 0;  // raster origin in (u, v)
    int nu = 0, nv = 0;
    std::vector<std::uint8_t> code;  // nu * nv
    // Per cell: kEdgeCover (it or a 4-neighbour is off the triangles while the other is on), kEdgeMedium
    // (two on-cells of different media meet there), and in bits 2-3 the medium of a covered
    // neighbour (for an off cell that a sample finds on a triangle after all).
    std::vector<std::uint8_t> edge;
    // Cells at a boundary between media: their codes on 4 x 4 sub-cells (one ray each, at build),
    // sub_of[cell] the first of its 16 in `sub` (~0u: none).
    std::vector<std::uint32_t> sub_of;
    std::vector<std::uint8_t> sub;
    // Per triangle its three edges in (u, v) as a u + b v + c >= 0 inside (tris order).
    std::vector<std::array<float, 9>> edges;
    std::vector<std::uint16_t> dist;  // chamfer distance to another code, in 1/2 cells (saturating)
    std::vector<std::uint32_t> tris;
    std::uint8_t at(int i, int j) const {
      return (i < 0 || j < 0 || i >= nu || j >= nv) ? kOff : code[static_cast<std::size_t>(j) * nu + i];
    }
  };
  static constexpr std::uint8_t kEdgeCover = 1, kEdgeMedium = 2;
  static constexpr std::size_t kExactTriangles = 32;  // planes of more triangles use the raster alone
  // The code at plane coordinates (a, b): the raster's, except in cells at a boundary, where the
  // triangles are tested exactly and (at a medium boundary) a ray is cast.
  std::uint8_t code_at(const Plane& p, float a, float b) const;
  std::uint8_t medium_by_ray(const Plane& p, std::uint32_t tri, float a, float b) const;
  // The plane's triangle that holds (a, b) exactly, ~0u: none.
  static std::uint32_t holder_of(const Plane& p, float a, float b);
  void mark_edges(Plane& p) const;
  void group_planes(const EmbreeScene& es);
  void rasterise(const EmbreeScene& es, Plane& p, int threads);
  static void chamfer(Plane& p);

  const EmbreeScene* es_ = nullptr;
  std::vector<Plane> planes_;
  std::vector<std::int32_t> plane_of_;  // per triangle, -1: none
  float h_ = 1;
  std::size_t cells_ = 0;
  double build_s_ = 0;
};

}  // namespace bhcl::render
