// FLANN on the host: the second exact baseline and the default ground truth of `bhcl eval`.
//
// flann::KDTreeSingleIndex with L2_Simple<float> (exact for 3D), queried by our own threads
// (Debian's FLANN is used header-only, without OpenMP, so its `cores` parameter would do nothing).
// Results follow the same contract as the device methods, bit for bit equal to brute force:
//  - each neighbour's distance is the contract's float sum((q-p)^2), as reference::dist2_float
//    computes it (FLANN's L2_Simple evaluates the same expression in the same order; checked at
//    build time, recomputed if it ever differs);
//  - FLANN's search feeds our result set, which keeps the k smallest (distance, index) pairs, ties
//    to the lower index, and reports a bound slightly above the k-th distance so that FLANN's
//    float pruning (incremental cell distances, strict `<` at the leaves) cannot drop a point that
//    ties the k-th distance or beats it by a rounding error;
//  - rows FLANN cannot fill (points whose squared distance overflows to +inf) are completed by a
//    linear scan.
// The buffer-level call (Index::enqueue_query) is honest but not asynchronous: it waits for
// `wait`, reads the queries back, answers them on the host and writes the results back blocking.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

struct FlannParams {
  int threads = 0;         // query threads; 0 = the CPUs the process may use (sched_getaffinity)
  int leaf_max_size = 10;  // FLANN's default
};

class FlannIndex : public Index {
 public:
  // points: N x 3 floats (copied). The runtime serves the buffer-level call only. Throws for
  // N == 0, non-finite points or a null runtime.
  FlannIndex(std::shared_ptr<Runtime> runtime, const float* points, std::size_t n_points,
             const FlannParams& params = {});
  ~FlannIndex() override;

  std::string method() const override { return "flann"; }
  bool exact() const override { return true; }
  // Host memory: FLANN's tree, its reordered copy of the points and our copy.
  std::size_t memory_bytes() const override;
  int threads() const { return threads_; }
  UsedFields build_used() const override;  // flann/options.cpp: the threads

  // Answers on the host (Index::query and enqueue_query call host_search). QueryStats: query_s =
  // wall time of the search itself (all threads), no compile, upload or download; batches = 0.
  bool answers_on_host() const override { return true; }
  double host_radius_search(const float* queries, std::size_t n, float r2,
                            const RadiusParams& params, RadiusResult& out) const override;
  double host_search(const float* queries, std::size_t n, const SearchParams& params,
                     KnnResult& out) const override;

 protected:
  BHCL_INDEX_UPDATE_HOOKS

 private:
  // The tree over n points (index coordinates); ext: their ids (empty: 0 .. n - 1).
  void build_tree(const float* pts, std::size_t n, std::vector<std::int32_t> ext);
  // One full build over the stored points not marked in `dead` (n_dead of them) and m new ones.
  void rebuild_live(const std::vector<std::uint8_t>& dead, std::size_t n_dead, const float* added, std::size_t m,
                    std::int32_t first);
  // Answers rows [0, n) into raw arrays (n*k ids and distances, n counts), in the index's own
  // (possibly scaled) coordinates; returns how many queries had a non-finite coordinate.
  std::size_t search(const float* queries, std::size_t n, const SearchParams& params,
                     std::int32_t* ids, float* dist2, std::int32_t* counts) const;

  struct Impl;
  std::unique_ptr<Impl> impl_;
  int threads_ = 1;
};

}  // namespace bhcl
