// The kd-tree method: host build (iterative, O(N log N)) and the device dispatch.
#include "blockhash_cl/kdtree.hpp"

#include <algorithm>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "kdtree_layout.h"

// The layout of kernels/kdtree_layout.h as the host writes it.
static_assert(sizeof(bhcl_kd_node) == 16, "bhcl_kd_node must be 16 bytes");
static_assert(offsetof(bhcl_kd_node, split) == 0 && offsetof(bhcl_kd_node, dim) == 4 &&
                  offsetof(bhcl_kd_node, a) == 8 && offsetof(bhcl_kd_node, b) == 12,
              "bhcl_kd_node field offsets");
static_assert(sizeof(bhcl_kd_point) == sizeof(cl_float4), "bhcl_kd_point must match float4");
static_assert(offsetof(bhcl_kd_point, id) == 12, "bhcl_kd_point.id is the w lane");
static_assert(BHCL_KD_LEAF == 3u, "leaf marker follows the split dimensions 0..2");

namespace bhcl {
namespace {

struct BuiltTree {
  std::vector<bhcl_kd_node> nodes;
  std::vector<std::uint32_t> perm;  // leaf order -> caller's index
  std::size_t leaves = 0;
  int depth = 0;
};

// Median splits on the widest dimension of each node's points, nodes in depth-first order (left
// child = next node). An explicit stack instead of recursion; nth_element keeps every level O(n),
// so the build is O(N log N) whatever the data (duplicates, flat or collinear sets split by
// position, never by value, so the tree stays balanced: depth <= ceil(log2(N / leaf))).
BuiltTree build_tree(const float* xyz, std::size_t n, std::size_t leaf) {
  BuiltTree t;
  t.perm.resize(n);
  for (std::size_t i = 0; i < n; ++i) t.perm[i] = static_cast<std::uint32_t>(i);
  t.nodes.reserve(2 * (n / leaf + 1));
  struct Task {
    std::size_t begin, end;
    int depth;
    std::int64_t parent;  // inner node whose right child this is; -1 for the root and left children
  };
  std::vector<Task> stack;
  stack.push_back({0, n, 0, -1});
  while (!stack.empty()) {
    Task task = stack.back();
    stack.pop_back();
    const std::uint32_t index = static_cast<std::uint32_t>(t.nodes.size());
    if (task.parent >= 0) t.nodes[static_cast<std::size_t>(task.parent)].a = index;
    const std::size_t count = task.end - task.begin;
    bhcl_kd_node node{0.0f, BHCL_KD_LEAF, 0u, 0u};
    if (count <= leaf) {
      node.a = static_cast<std::uint32_t>(task.begin);
      node.b = static_cast<std::uint32_t>(count);
      t.nodes.push_back(node);
      ++t.leaves;
      t.depth = std::max(t.depth, task.depth);
      continue;
    }
    float lo[3], hi[3];
    for (int d = 0; d < 3; ++d) lo[d] = hi[d] = xyz[3 * std::size_t(t.perm[task.begin]) + d];
    for (std::size_t i = task.begin + 1; i < task.end; ++i) {
      const float* p = xyz + 3 * std::size_t(t.perm[i]);
      for (int d = 0; d < 3; ++d) {
        lo[d] = std::min(lo[d], p[d]);
        hi[d] = std::max(hi[d], p[d]);
      }
    }
    // Extents in double: hi - lo can overflow float for far-apart finite points.
    int dim = 0;
    double widest = -1.0;
    for (int d = 0; d < 3; ++d) {
      double e = double(hi[d]) - double(lo[d]);
      if (e > widest) {
        widest = e;
        dim = d;
      }
    }
    const std::size_t mid = task.begin + count / 2;
    std::nth_element(t.perm.begin() + task.begin, t.perm.begin() + mid, t.perm.begin() + task.end,
                     [xyz, dim](std::uint32_t a, std::uint32_t b) {
                       return xyz[3 * std::size_t(a) + dim] < xyz[3 * std::size_t(b) + dim];
                     });
    node.split = xyz[3 * std::size_t(t.perm[mid]) + dim];
    node.dim = static_cast<std::uint32_t>(dim);
    t.nodes.push_back(node);
    // LIFO: the left child is popped next and so gets index + 1; the right child patches `a`.
    stack.push_back({mid, task.end, task.depth + 1, static_cast<std::int64_t>(index)});
    stack.push_back({task.begin, mid, task.depth + 1, -1});
  }
  return t;
}

}  // namespace

KdTreeIndex::KdTreeIndex(std::shared_ptr<Runtime> runtime, const float* points,
                         std::size_t n_points, const KdTreeParams& params)
    : Index(std::move(runtime), n_points) {
  auto t0 = std::chrono::steady_clock::now();
  if (params.leaf_size < 1 || params.leaf_size > 1024)
    throw Error("kdtree: leaf_size = " + std::to_string(params.leaf_size) +
                " is out of range: must be in [1, 1024]");
  std::vector<float> scaled;
  points = prepare_points(points, n_points, scaled);  // validates; extreme scales
  leaf_size_ = params.leaf_size;
  BuiltTree tree = build_tree(points, n_points, static_cast<std::size_t>(leaf_size_));
  n_nodes_ = tree.nodes.size();
  n_leaves_ = tree.leaves;
  depth_ = tree.depth;

  std::vector<bhcl_kd_point> reordered(n_points);
  for (std::size_t i = 0; i < n_points; ++i) {
    const float* p = points + 3 * std::size_t(tree.perm[i]);
    reordered[i] = bhcl_kd_point{p[0], p[1], p[2], static_cast<std::int32_t>(tree.perm[i])};
  }
  nodes_ = detail::upload_vector(runtime_ptr(), tree.nodes, "kdtree nodes");
  points_ = detail::upload_vector(runtime_ptr(), reordered, "kdtree points");
  set_build_seconds(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
}

cl::Event KdTreeIndex::enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                     std::size_t first, std::size_t count,
                                     const ResultBuffers& out, const SearchParams& params,
                                     std::size_t local_size,
                                     const std::vector<cl::Event>* wait) const {
  const int kmax = kmax_variant(params.k);
  // The stack must hold one entry per inner level; rounding up to a multiple of 8 lets trees of
  // similar size share a compiled program.
  const int stack = std::max(8, (depth_ + 7) / 8 * 8);
  cl::Kernel kernel = runtime().kernel(
      "kdtree_knn.cl", "kdtree_knn",
      detail::with_defines("-DBHCL_KMAX=" + std::to_string(kmax) + " -DBHCL_KD_STACK=" + std::to_string(stack), params));
  detail::KernelArgs args(kernel, "kdtree_knn");
  args.add(nodes_)
      .add(points_)
      .add_queries(queries, first, count, params)
      .add_results(out);
  return detail::launch_1d(queue, kernel, count, local_size, wait, "kdtree_knn");
}

cl::Event KdTreeIndex::enqueue_radius_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                            std::size_t first, std::size_t count, float r2, int pass,
                                            const RadiusBuffers& out, const RadiusParams& params,
                                            std::size_t local_size,
                                            const std::vector<cl::Event>* wait) const {
  const int stack = std::max(8, (depth_ + 7) / 8 * 8);  // as enqueue_batch
  std::string options = "-DBHCL_KD_STACK=" + std::to_string(stack);
  if (!params.kernel_defines.empty()) options += " " + params.kernel_defines;
  cl::Kernel kernel = runtime().kernel("kdtree_radius.cl", "kdtree_radius", options);
  detail::KernelArgs args(kernel, "kdtree_radius");
  args.add(nodes_).add(points_).add_radius(queries, first, count, r2, pass, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, "kdtree_radius");
}

}  // namespace bhcl
