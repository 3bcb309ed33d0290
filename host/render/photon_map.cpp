#include "photon_map.hpp"

#include <chrono>
#include <cmath>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/spatial_order.hpp"
#include "surface_area.hpp"

namespace bhcl::render {

PhotonMap::PhotonMap(std::string name, std::vector<PhotonRecord> records, float power_scale)
    : name_(std::move(name)), power_scale_(power_scale) {
  // Records in Hilbert order of their positions: the k photons of one estimate, and those of
  // neighbouring gather points, then lie close together in memory. In emission order they are
  // scattered over the whole map, and shading (k reads per estimate) waits on cache misses.
  {
    std::vector<float> xyz(records.size() * 3);
    for (std::size_t i = 0; i < records.size(); ++i)
      for (int d = 0; d < 3; ++d) xyz[3 * i + d] = records[i].position[d];
    const std::vector<std::size_t> order = hilbert_order(xyz.data(), records.size());
    records_.reserve(records.size());
    for (std::size_t i : order) records_.push_back(records[i]);
  }
  positions_.resize(records_.size() * 3);
  power_.resize(records_.size());
  direction_.resize(records_.size());
  class_dir_.resize(records_.size());
  class_.resize(records_.size());
  for (std::size_t i = 0; i < records_.size(); ++i) {
    for (int d = 0; d < 3; ++d) positions_[3 * i + d] = records_[i].position[d];
    power_[i] = records_[i].get_power();
    direction_[i] = records_[i].get_direction_unnormalized();
    const int c = records_[i].surface_class();
    class_[i] = static_cast<std::int8_t>(c);
    class_dir_[i] = c >= 0 ? surface_class_vector(c) : Vec3{0, 0, 0};
  }
}

void PhotonMap::build_index(const std::string& method, std::shared_ptr<Runtime> runtime,
                            const MethodOptions& options) {
  index_.reset();
  weights_.reset();
  surface_weights_.reset();
  build_seconds_ = 0;
  if (records_.empty()) return;
  auto t0 = std::chrono::steady_clock::now();
  index_ = make_index(method, std::move(runtime), positions_.data(), records_.size(), options);
  build_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

QueryStats PhotonMap::query(const float* xyz, std::size_t n, const SearchParams& params,
                            KnnResult& out) const {
  if (!index_) throw Error("photon map '" + name_ + "': query before build_index (or the map is empty)");
  return index_->query(xyz, n, params, out);
}

void PhotonMap::rebuild_index_from(PhotonMap& previous, const std::string& method,
                                   std::shared_ptr<Runtime> runtime, const MethodOptions& options) {
  Index* prev = previous.index_.get();
  if (!prev || !prev->rebuilds_in_place() || records_.empty()) {
    build_index(method, std::move(runtime), options);
    return;
  }
  weights_.reset();
  surface_weights_.reset();
  auto t0 = std::chrono::steady_clock::now();
  prev->rebuild(positions_.data(), records_.size());
  index_ = std::move(previous.index_);
  build_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

QueryStats PhotonMap::estimate(const float* xyz, const float* normals, std::size_t n, const SearchParams& params,
                               const DensityEstimator& est, float scale2, DensityResult& out,
                               bool same_surface) const {
  if (!index_) throw Error("photon map '" + name_ + "': estimate before build_index (or the map is empty)");
  static_assert(sizeof(Vec3) == 3 * sizeof(float), "Vec3 arrays are read as n x 3 floats");
  // The kernel's facing test, dot(direction, normal) > 0, becomes the class test when the
  // "directions" are the photons' class vectors and the normals the queries' (surface_area.hpp).
  std::unique_ptr<DensityWeights>& w = same_surface ? surface_weights_ : weights_;
  const std::vector<Vec3>& dirs = same_surface ? class_dir_ : direction_;
  if (!w)
    w = std::make_unique<DensityWeights>(*index_, reinterpret_cast<const float*>(power_.data()),
                                         reinterpret_cast<const float*>(dirs.data()), records_.size());
  DensityParams p;
  p.search = params;
  p.radius = est.radius == RadiusEstimator::Kth ? DiscRadius::Kth
             : est.radius == RadiusEstimator::Mean ? DiscRadius::Mean : DiscRadius::Variance;
  p.filter = est.filter == DensityFilter::Box ? DiscFilter::Box
             : est.filter == DensityFilter::Cone ? DiscFilter::Cone : DiscFilter::Epanechnikov;
  p.cone = kConeFilter;
  p.radius_scale2 = scale2;
  return density_estimate(*index_, *w, xyz, normals, n, p, out);
}

Vec3 PhotonMap::radiance(const KnnResult& r, std::size_t row, Vec3 n, Vec3 kd, float max_radius,
                         const DensityEstimator& est, float scale2, bool same_surface, float* r2_used) const {
  if (r2_used) *r2_used = 0;
  const int count = r.counts[row];
  if (count <= 0) return {0, 0, 0};
  const float* d2 = r.dist2.data() + row * static_cast<std::size_t>(r.k);
  float r2 = disc_radius2(est.radius, d2, count, r.k, max_radius);
  if (!(r2 > 0) || !std::isfinite(r2)) return {0, 0, 0};  // all photons on the query point: no disc
  // A progressive pass's shrunk disc: the photons beyond it (the list's tail) are left out.
  int used = count;
  if (scale2 < 1.0f) {
    r2 *= scale2;
    if (!(r2 > 0)) return {0, 0, 0};
    used = 0;
    while (used < count && d2[used] <= r2) ++used;
  }
  const float radius = std::sqrt(r2);
  if (r2_used) *r2_used = r2;
  const int want = same_surface ? surface_class(n) : -1;
  Vec3 sum{0, 0, 0};
  for (int j = 0; j < used; ++j) {
    const std::size_t id = static_cast<std::size_t>(r.id(row, j));
    if (same_surface ? class_[id] != want : dot(direction_[id], n) <= 0) continue;  // another surface / behind
    sum += power_[id] * filter_weight(est.filter, d2[j], r2, radius);
  }
  const float norm = filter_norm(est.filter) * kPi * r2;
  return kd * sum * (power_scale_ / (kPi * norm));
}

}  // namespace bhcl::render
