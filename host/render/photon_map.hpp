// A photon map: the records, their positions in a kNN index of any method (make_index), and the
// radiance estimate from the k nearest photons.
//
// Density estimate: at a diffuse point x with albedo kd and normal n (on the viewer's side), from
// the k nearest photons p and a disc of radius r (density.hpp: the k-th distance by default, or
// the maximum radius when fewer are found):
//     L(x) = (kd / pi) * sum_p w(d_p / r) Phi_p / (norm_w pi r^2)
// with the filter w (Jensen's cone filter by default); photons arriving from behind the surface
// (dot(dir_p, n) <= 0) are skipped. Units: Phi is radiance x mm^2 (photon_trace.hpp) and r is in
// mm, so L is radiance.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/density_query.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/knn.hpp"
#include "density.hpp"
#include "photon.hpp"

namespace bhcl::render {

class PhotonMap {
 public:
  PhotonMap(std::string name, std::vector<PhotonRecord> records, float power_scale);

  // (Re)builds the kNN index over the positions with any method make_index knows; the records
  // stay, so several methods can answer queries on the same photons. No-op for an empty map.
  void build_index(const std::string& method, std::shared_ptr<Runtime> runtime,
                   const MethodOptions& options = {});

  const std::string& name() const { return name_; }
  std::size_t size() const { return records_.size(); }
  bool empty() const { return records_.empty(); }
  const std::vector<PhotonRecord>& records() const { return records_; }
  const std::vector<float>& positions() const { return positions_; }
  float power_scale() const { return power_scale_; }
  const Index* index() const { return index_.get(); }
  double build_seconds() const { return build_seconds_; }

  // Answers all queries (n x 3) in ONE call of the index. Throws if no index was built.
  QueryStats query(const float* xyz, std::size_t n, const SearchParams& params, KnnResult& out) const;

  // The next photon set's index: when `previous` holds a block-hashing index, it is rebuilt over
  // this map's positions (BlockHashIndex::rebuild reuses its host and device arrays: no
  // reallocation while the photon count does not grow) and moved here; otherwise (another method,
  // no index) a fresh build_index. Progressive passes call it once per pass.
  void rebuild_index_from(PhotonMap& previous, const std::string& method, std::shared_ptr<Runtime> runtime,
                          const MethodOptions& options = {});

  // The density estimate inside the query (blockhash_cl/density_query.hpp) for n queries with
  // their surface normals: out.estimate[q] is sum w Phi / (norm_w pi r^2) over the photons facing
  // the normal, without the lists coming back; the radiance is then kd * estimate * power_scale /
  // pi, equal to radiance() from the lists up to float rounding. The photons' power and direction
  // go to the device at the first call after each (re)build.
  // same_surface (the boundary correction, surface_area.hpp): the normals are the queries'
  // surface_class_vector and only the photons of that orientation class count.
  QueryStats estimate(const float* xyz, const float* normals, std::size_t n, const SearchParams& params,
                      const DensityEstimator& estimator, float scale2, DensityResult& out,
                      bool same_surface = false) const;

  // The radiance estimate (see top of file) from row `row` of a query result. scale2 < 1 shrinks
  // the disc to scale2 times the estimator's squared radius (a progressive pass, see
  // progressive.hpp): only the photons of the list inside the shrunk disc count (the list is
  // sorted, so they are its first entries), every filter included. scale2 = 1 is the plain
  // estimate, bit for bit.
  // same_surface: only the photons whose surface has n's orientation class count (instead of the
  // facing test); r2_used (when given) gets the disc's squared radius (0: none).
  Vec3 radiance(const KnnResult& r, std::size_t row, Vec3 n, Vec3 kd, float max_radius,
               const DensityEstimator& estimator = {}, float scale2 = 1.0f, bool same_surface = false,
               float* r2_used = nullptr) const;

 private:
  std::string name_;
  std::vector<PhotonRecord> records_;
  std::vector<float> positions_;
  // Decoded once per map (each photon is read by about k x queries / photons estimates, ~100s of
  // times per render): the half-float power and the unpacked (not normalised) incoming direction.
  std::vector<Vec3> power_, direction_;
  std::vector<Vec3> class_dir_;  // surface_class_vector of each photon's surface (0: unknown)
  std::vector<std::int8_t> class_;
  float power_scale_;
  std::unique_ptr<Index> index_;
  mutable std::unique_ptr<DensityWeights> weights_;  // for estimate(); reset by every (re)build
  mutable std::unique_ptr<DensityWeights> surface_weights_;  // the same with class_dir_ (same_surface)
  double build_seconds_ = 0;
};

}  // namespace bhcl::render
