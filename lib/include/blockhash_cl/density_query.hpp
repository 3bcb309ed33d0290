// The density estimate inside the query: per query, the filtered sum of the k nearest points'
// weights over the disc they cover, and the disc's squared radius, instead of the k-nearest lists.
// A photon-mapping renderer asks for k ids and distances per gather query (8 k bytes) only to sum
// photon powers; here the lists stay on the device and 16 bytes per query come back.
//
//   estimate(q) = sum_{j in disc, dot(D_j, N_q) > 0} w(d_j / r) P_j / (norm_w pi r^2)
//
// P_j: the point's weight (RGB, e.g. a photon's power), D_j: its direction (e.g. the photon's
// incoming direction, any length), N_q: the query's normal; points arriving from behind the
// query's surface are skipped. The disc r and the filter w are those of the renderer
// (host/render/density.hpp): r from the k-th distance, the mean distance or the variance of the
// distances, r = max_radius when fewer than k points are within a finite max_radius; w box, cone
// (1 - d / (c r), c = cone) or Epanechnikov (1 - d^2 / r^2), norm_w the filter's integral over the
// unit disc over pi. radius_scale2 < 1 shrinks the disc to that fraction of its squared radius (a
// progressive photon-mapping pass) and only the points inside the shrunk disc count.
//
// Every method offers it through one generic path: queries are answered in chunks by the
// method's buffer-level call (Index::enqueue_query: device methods' kernels, host methods such as
// FLANN through the same contract) into device buffers reused from chunk to chunk, then the kernel
// kernels/density_estimate.cl reduces each query's list on the device and only the estimates are
// read back. It equals the estimate computed on the host from the lists of Index::query (same
// points, same sums in the same order, float: the mean and variance estimators sum in float where
// the renderer sums in double; relative difference ~1e-6).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

enum class DiscRadius { Kth = 0, Mean = 1, Variance = 2 };
enum class DiscFilter { Box = 0, Cone = 1, Epanechnikov = 2 };

struct DensityParams {
  SearchParams search;  // k, max_radius, A, ... as for Index::query
  DiscRadius radius = DiscRadius::Kth;
  DiscFilter filter = DiscFilter::Cone;
  float cone = 1.1f;          // the cone filter's c (>= 1)
  float radius_scale2 = 1.0f; // in (0, 1]
  // Queries per chunk (0: automatic: 65536, or 65280 on PoCL, whose launches stay below 65535 items;
  // fewer when k x chunk does not fit a device buffer).
  std::size_t chunk = 0;
};

// Per-point weights on the index's device: n = index.size() points in the caller's order (the
// order the index was built from). Upload once per point set; rebuild after the index is rebuilt
// over other points.
class DensityWeights {
 public:
  // power: n x 3 floats, direction: n x 3 floats; every value finite (bhcl::Error naming the
  // first bad point otherwise).
  DensityWeights(const Index& index, const float* power, const float* direction, std::size_t n);
  std::size_t size() const { return n_; }
  const cl::Buffer& power() const { return power_; }
  const cl::Buffer& direction() const { return direction_; }

 private:
  std::size_t n_;
  cl::Buffer power_, direction_;
};

struct DensityResult {
  std::size_t n = 0;
  std::vector<float> estimate;       // n x 3
  std::vector<float> radius2;        // n: the disc's squared radius used (0: no disc)
  std::size_t bytes_read_back = 0;   // device -> host bytes of the call (16 per query)
  std::size_t list_bytes_on_device = 0;  // the reused chunk buffers of the lists (ids, dist2, counts)
};

// queries, normals: n x 3 floats. A query with a NaN/Inf coordinate gets estimate 0 and radius 0
// (as its empty kNN row); normals must be finite (bhcl::Error naming the query). weights must have
// index.size() points.
QueryStats density_estimate(const Index& index, const DensityWeights& weights, const float* queries,
                            const float* normals, std::size_t n, const DensityParams& params,
                            DensityResult& out);

}  // namespace bhcl
