// Exact kNN on a kd-tree: the tree is built on the host (balanced median splits on the widest
// dimension, small leaf buckets), the queries run on the OpenCL device, one work-item each, with a
// stack-based traversal. Same result contract as brute force, bit for bit.
#pragma once

#include <cstddef>
#include <memory>

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

  std::size_t node_count() const { return n_nodes_; }
  std::size_t leaf_count() const { return n_leaves_; }
  // Inner nodes on the longest root-to-leaf path: the traversal stack the kernel needs.
  int depth() const { return depth_; }
  int leaf_size() const { return leaf_size_; }

 protected:
  cl::Event enqueue_radius_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                 std::size_t first, std::size_t count, float r2, int pass,
                                 const RadiusBuffers& out, const RadiusParams& params,
                                 std::size_t local_size,
                                 const std::vector<cl::Event>* wait) const override;
  cl::Event enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                          std::size_t first, std::size_t count, const ResultBuffers& out,
                          const SearchParams& params, std::size_t local_size,
                          const std::vector<cl::Event>* wait) const override;

 private:
  cl::Buffer nodes_;   // bhcl_kd_node, depth-first
  cl::Buffer points_;  // float4 in leaf order, w = the caller's index (int bits)
  std::size_t n_nodes_ = 0, n_leaves_ = 0;
  int depth_ = 0;
  int leaf_size_ = 0;
};

}  // namespace bhcl
