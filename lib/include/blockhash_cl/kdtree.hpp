// Exact kNN on a kd-tree: the tree is built on the host (balanced median splits on the widest
// dimension, small leaf buckets), the queries run on the OpenCL device, one work-item each, with a
// stack-based traversal. Same result contract as brute force, bit for bit.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

struct KdTreeParams {
  // Most points per leaf. Buckets beat one point per node on CPUs and GPUs: the leaf scan is a
  // contiguous loop and the tree is shallower. Measured on PoCL, 2 threads, 1M points (uniform
  // and Autzen), k = 10 and 50 (bench/baselines --leaf, 3 interleaved rounds, speed relative to
  // FLANN in the same run): 16, 24 and 32 within noise of each other, 12 about 15 % slower,
  // 6-8 slower still.
  int leaf_size = 16;
  // Host threads for the build (0: all hardware threads). The tree is the same for every count.
  unsigned build_threads = 0;
};

class KdTreeIndex : public Index {
 public:
  // points: N x 3 floats (copied, reordered, to the device). Throws for N == 0, non-finite points
  // or a leaf size outside [1, 1024].
  KdTreeIndex(std::shared_ptr<Runtime> runtime, const float* points, std::size_t n_points,
              const KdTreeParams& params = {});

  std::string method() const override { return "kdtree"; }
  bool exact() const override { return true; }
  std::size_t memory_bytes() const override { return n_nodes_ * 16 + size() * 16; }
  // The caller's points (the double-precision fallback reads them) and the host mirror of the
  // device arrays (insert and remove update it): memory_bytes() again.
  std::size_t host_bytes() const override { return size() * 3 * sizeof(float) + memory_bytes(); }
  UsedFields build_used() const override;  // kdtree/options.cpp: the update counters

  std::size_t node_count() const { return n_nodes_; }
  std::size_t leaf_count() const { return n_leaves_; }
  // Inner nodes on the longest root-to-leaf path: the traversal stack the kernel needs.
  int depth() const { return depth_; }
  int leaf_size() const { return leaf_size_; }
  // Updates: removed points still stored as holes (a rebuild drops them), and rebuilds so far.
  std::size_t holes() const { return holes_; }
  std::size_t update_rebuilds() const { return rebuilds_; }
  std::size_t update_merges() const { return merges_; }  // inserts into the existing leaves

 protected:
  BHCL_INDEX_DEVICE_HOOKS
  BHCL_INDEX_UPDATE_HOOKS

 private:
  // The tree over n points (index coordinates); ids: each point's id (null: 0 .. n - 1).
  void build_tree(const float* points, std::size_t n, const std::int32_t* ids);
  void rebuild_live();  // over the live points of caller_points(), ids kept
  struct HostPoint {  // kernels/kdtree_layout.h's bhcl_kd_point (checked in kdtree.cpp)
    float x, y, z;
    std::int32_t id;
  };
  std::vector<HostPoint> host_points_;  // the device's points array, kept for updates
  std::vector<std::int32_t> pos_;  // id -> slot in host_points_ (-1: none); built by a remove
  std::vector<std::uint32_t> host_nodes_;  // the device's nodes (bhcl_kd_node, 4 words each)
  std::size_t holes_ = 0, rebuilds_ = 0, merges_ = 0, built_points_ = 0, points_cap_ = 0;
  unsigned build_threads_ = 0;
  cl::Buffer nodes_;   // bhcl_kd_node, depth-first
  cl::Buffer points_;  // float4 in leaf order, w = the caller's index (int bits)
  std::size_t n_nodes_ = 0, n_leaves_ = 0;
  int depth_ = 0;
  int leaf_size_ = 0;
};

}  // namespace bhcl
