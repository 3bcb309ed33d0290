// The kd-tree method: host build (iterative, O(N log N)) and the device dispatch.
#include "blockhash_cl/kdtree.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <cmath>
#include <cstring>
#include <map>
#include <vector>

#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "core/kernel_defines.hpp"
#include "core/parallel.hpp"
#include "kdtree/build.hpp"
#include "kdtree_layout.h"
#include "bhcl_shared.h"

// The layout of kernels/kdtree_layout.h as the host writes it.
static_assert(sizeof(bhcl_kd_node) == 16, "bhcl_kd_node must be 16 bytes");
static_assert(offsetof(bhcl_kd_node, split) == 0 && offsetof(bhcl_kd_node, dim) == 4 &&
                  offsetof(bhcl_kd_node, a) == 8 && offsetof(bhcl_kd_node, b) == 12,
              "bhcl_kd_node field offsets");
static_assert(sizeof(bhcl_kd_point) == sizeof(cl_float4), "bhcl_kd_point must match float4");
static_assert(offsetof(bhcl_kd_point, id) == 12, "bhcl_kd_point.id is the w lane");
static_assert(BHCL_KD_LEAF == 3u, "leaf marker follows the split dimensions 0..2");

namespace bhcl {
namespace detail {
namespace {

// The tree's shape follows from the point counts alone (a node of c > leaf points has children
// of c / 2 and c - c / 2), so every subtree's node count, and so every node's index in the
// depth-first array, is known before a split is made: subtrees are built independently, in any
// order, on any thread, into their own slices of the arrays.
class Shape {
 public:
  Shape(std::size_t n, std::size_t leaf) : leaf_(leaf) { visit(n); }
  std::size_t nodes(std::size_t c) const { return of(c).nodes; }
  std::size_t leaves(std::size_t c) const { return of(c).leaves; }
  int depth(std::size_t c) const { return of(c).depth; }

 private:
  struct Counts {
    std::size_t nodes, leaves;
    int depth;
  };
  // Every count in the tree is n halved down and up, at most two per level: a small table,
  // filled once, read-only while the threads build.
  const Counts& visit(std::size_t c) {
    auto it = memo_.find(c);
    if (it != memo_.end()) return it->second;
    Counts r{1, 1, 0};
    if (c > leaf_) {
      Counts a = visit(c / 2), b = visit(c - c / 2);
      r = {1 + a.nodes + b.nodes, a.leaves + b.leaves, 1 + std::max(a.depth, b.depth)};
    }
    return memo_.emplace(c, r).first->second;
  }
  const Counts& of(std::size_t c) const { return memo_.at(c); }
  std::size_t leaf_;
  std::map<std::size_t, Counts> memo_;
};

struct Task {
  std::size_t begin, end;  // the node's points: perm[begin, end)
  std::size_t index;       // the node's slot in the depth-first array
};

// Makes the node of `task` (a leaf, or a median split of its points, which reorders perm inside
// [begin, end) only) and pushes its children, if any: the right one first.
struct KeyId {
  float key;
  std::uint32_t id;
};

void make_node(const float* xyz, std::size_t leaf, const Shape& shape, KdTreeArrays& t,
               const Task& task, std::vector<Task>& out, std::vector<KeyId>& scratch) {
  const std::size_t count = task.end - task.begin;
  bhcl_kd_node node{0.0f, BHCL_KD_LEAF, 0u, 0u};
  if (count <= leaf) {
    node.a = static_cast<std::uint32_t>(task.begin);
    node.b = static_cast<std::uint32_t>(count);
    t.nodes[task.index] = node;
    return;
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
  // nth_element over (coordinate, index) pairs gathered once: it compares and moves exactly as it
  // would over perm with a comparator that gathers the coordinates (its steps depend on the
  // comparisons' outcomes alone), so the order is the same, from contiguous loads.
  scratch.resize(count);
  for (std::size_t i = 0; i < count; ++i) {
    const std::uint32_t id = t.perm[task.begin + i];
    scratch[i] = {xyz[3 * std::size_t(id) + dim], id};
  }
  std::nth_element(scratch.begin(), scratch.begin() + (mid - task.begin), scratch.end(),
                   [](const KeyId& a, const KeyId& b) { return a.key < b.key; });
  for (std::size_t i = 0; i < count; ++i) t.perm[task.begin + i] = scratch[i].id;
  const std::size_t right = task.index + 1 + shape.nodes(mid - task.begin);
  node.split = scratch[mid - task.begin].key;
  node.dim = static_cast<std::uint32_t>(dim);
  node.a = static_cast<std::uint32_t>(right);
  t.nodes[task.index] = node;
  out.push_back({mid, task.end, right});
  out.push_back({task.begin, mid, task.index + 1});
}

}  // namespace

// Median splits on the widest dimension of each node's points, nodes in depth-first order (left
// child = next node). An explicit stack instead of recursion; nth_element keeps every level O(n),
// so the build is O(N log N) whatever the data (duplicates, flat or collinear sets split by
// position, never by value, so the tree stays balanced: depth <= ceil(log2(N / leaf))).
// In parallel: the top levels one level at a time, each level's nodes on the threads, until there
// are 4 subtrees per thread (or they get small); then each thread builds whole subtrees, taking
// the next one left.
KdTreeArrays build_kdtree(const float* xyz, std::size_t n, std::size_t leaf, unsigned threads) {
  if (threads == 0) threads = default_threads();
  KdTreeArrays t;
  const Shape shape(n, leaf);
  t.nodes.resize(shape.nodes(n));
  t.leaves = shape.leaves(n);
  t.depth = shape.depth(n);
  t.perm.resize(n);
  parallel_for(n, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) t.perm[i] = static_cast<std::uint32_t>(i);
  }, threads, 1 << 16);
  // Below this many points a subtree is not worth a thread of its own.
  constexpr std::size_t kMinParallel = 1 << 14;
  std::vector<Task> level{{0, n, 0}};
  while (threads > 1 && !level.empty() && level.size() < 4 * std::size_t(threads) &&
         n / level.size() >= kMinParallel) {
    std::vector<std::vector<Task>> children(level.size());
    parallel_for(level.size(), [&](std::size_t b, std::size_t e) {
      std::vector<KeyId> scratch;
      for (std::size_t i = b; i < e; ++i) make_node(xyz, leaf, shape, t, level[i], children[i], scratch);
    }, threads, 1);
    std::vector<Task> below;
    for (auto& c : children) below.insert(below.end(), c.rbegin(), c.rend());
    level.swap(below);
  }
  // Each thread takes the next subtree left (any thread count balances).
  std::atomic<std::size_t> next{0};
  parallel_for(std::min<std::size_t>(threads, level.size()), [&](std::size_t, std::size_t) {
    std::vector<Task> stack;
    std::vector<KeyId> scratch;
    for (std::size_t i; (i = next.fetch_add(1)) < level.size();) {
      stack.assign(1, level[i]);
      while (!stack.empty()) {
        Task task = stack.back();
        stack.pop_back();
        make_node(xyz, leaf, shape, t, task, stack, scratch);
      }
    }
  }, threads, 1);
  return t;
}

}  // namespace detail

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
  build_threads_ = params.build_threads;
  build_tree(points, n_points, nullptr);
  set_build_seconds(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
}

void KdTreeIndex::build_tree(const float* points, std::size_t n_points, const std::int32_t* ids) {
  static_assert(sizeof(HostPoint) == sizeof(bhcl_kd_point) && offsetof(HostPoint, id) == offsetof(bhcl_kd_point, id),
                "HostPoint mirrors bhcl_kd_point");
  detail::KdTreeArrays tree = detail::build_kdtree(points, n_points, static_cast<std::size_t>(leaf_size_),
                                                   build_threads_);
  n_nodes_ = tree.nodes.size();
  n_leaves_ = tree.leaves;
  depth_ = tree.depth;
  // w = the point's id: the caller's index, or after updates the stable id (ids ascending in the
  // input, so ties still go to the lower id).
  host_points_.resize(n_points);
  detail::parallel_for(n_points, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      const float* p = points + 3 * std::size_t(tree.perm[i]);
      const std::int32_t id = ids ? ids[tree.perm[i]] : static_cast<std::int32_t>(tree.perm[i]);
      host_points_[i] = HostPoint{p[0], p[1], p[2], id};
    }
  }, build_threads_, 1 << 16);
  nodes_ = detail::upload_vector(runtime_ptr(), tree.nodes, "kdtree nodes");
  points_ = detail::upload_vector(runtime_ptr(), host_points_, "kdtree points");
  points_cap_ = std::max<std::size_t>(host_points_.size(), 1) * sizeof(HostPoint);
  host_nodes_.resize(tree.nodes.size() * 4);
  std::memcpy(host_nodes_.data(), tree.nodes.data(), tree.nodes.size() * sizeof(bhcl_kd_node));
  holes_ = 0;
  built_points_ = n_points;
  pos_.clear();  // filled by the first remove
}

// Updates (Index::insert/remove; figures in docs/UPDATES.md). An insert joins the existing leaves
// (insert_points below) or, past its limits, rebuilds the tree over the live points; a remove
// turns each point into a hole in place (+inf coordinates, the empty-slot id: never within any
// bound, never ranked before an empty slot) and rebuilds once holes pass a quarter of the stored
// points. One tree rather than nanoflann's forest of log2 N trees: a query searches one tree.
void KdTreeIndex::rebuild_live() {
  const std::vector<float>& cp = caller_points();
  const std::size_t bound = cp.size() / 3;
  std::vector<float> live;
  std::vector<std::int32_t> ids;
  live.reserve(3 * size());
  ids.reserve(size());
  for (std::size_t i = 0; i < bound; ++i)
    if (!id_removed(static_cast<std::int32_t>(i))) {
      live.insert(live.end(), cp.begin() + 3 * i, cp.begin() + 3 * i + 3);
      ids.push_back(static_cast<std::int32_t>(i));
    }
  std::vector<float> storage;
  const float* pts = to_structure(live.data(), ids.size(), storage);
  build_tree(pts, ids.size(), ids.data());
}

// An insert into the existing leaves: the traversal prunes a cell by its distance to the split
// planes that bound it (kernels/kdtree_knn.cl), a lower bound for any point inside the cell, so a
// new point may join the leaf whose cell holds it (descending by the splits) without changing
// any answer's exactness. The points array is laid out again with each leaf's new points behind
// its old ones (one O(N) pass, holes dropped), the nodes' counts updated. Leaves grow: past 4x the
// leaf size, or once the set has grown by half since the last build, the tree is rebuilt.
void KdTreeIndex::insert_points(const float*, const float* scaled, std::size_t m, std::int32_t first) {
  const bhcl_kd_node* nodes = reinterpret_cast<const bhcl_kd_node*>(host_nodes_.data());
  const std::size_t n_nodes = host_nodes_.size() / 4;
  std::vector<std::uint32_t> leaf(m), added(n_nodes, 0);
  std::size_t biggest = 0;
  for (std::size_t i = 0; i < m; ++i) {
    const float* p = scaled + 3 * i;
    std::uint32_t node = 0;
    while (nodes[node].dim != BHCL_KD_LEAF) node = p[nodes[node].dim] <= nodes[node].split ? node + 1 : nodes[node].a;
    leaf[i] = node;
    biggest = std::max<std::size_t>(biggest, nodes[node].b + ++added[node]);
  }
  const std::size_t stored = host_points_.size() - holes_ + m;
  if (biggest > 4 * std::size_t(leaf_size_) || 2 * stored > 3 * built_points_) {
    rebuild_live();  // caller_points() already holds the new points
    ++rebuilds_;
    return;
  }
  // The new points of each leaf, in id order (a counting sort by leaf).
  std::vector<std::uint32_t> start(n_nodes + 1, 0), order(m);
  for (std::size_t c = 0; c < n_nodes; ++c) start[c + 1] = start[c] + added[c];
  {
    std::vector<std::uint32_t> at(start.begin(), start.end() - 1);
    for (std::size_t i = 0; i < m; ++i) order[at[leaf[i]]++] = std::uint32_t(i);
  }
  // Leaves in depth-first order hold ascending ranges of the points array: one pass lays it out.
  std::vector<HostPoint> next;
  next.reserve(stored);
  bhcl_kd_node* wn = reinterpret_cast<bhcl_kd_node*>(host_nodes_.data());
  for (std::size_t c = 0; c < n_nodes; ++c) {
    if (wn[c].dim != BHCL_KD_LEAF) continue;
    const std::size_t a = next.size();
    for (std::uint32_t i = wn[c].a; i < wn[c].a + wn[c].b; ++i)
      if (host_points_[i].id != BHCL_EMPTY_SLOT_ID) next.push_back(host_points_[i]);
    for (std::uint32_t j = start[c]; j < start[c + 1]; ++j) {
      const std::uint32_t i = order[j];
      next.push_back(HostPoint{scaled[3 * i], scaled[3 * i + 1], scaled[3 * i + 2], first + std::int32_t(i)});
    }
    wn[c].a = std::uint32_t(a);
    wn[c].b = std::uint32_t(next.size() - a);
  }
  host_points_.swap(next);
  holes_ = 0;
  pos_.clear();
  const auto& rt = runtime_ptr();
  check_cl(rt->queue().finish(), "clFinish", "kdtree insert");
  const std::size_t bytes = host_points_.size() * sizeof(HostPoint);
  if (bytes > points_cap_) {  // capacity grown by half: a growing sequence reallocates rarely
    const std::size_t cap = std::max(bytes, points_cap_ + points_cap_ / 2);
    cl_int err = CL_SUCCESS;
    points_ = cl::Buffer(rt->context(), CL_MEM_READ_ONLY, cap, nullptr, &err);
    check_cl(err, "clCreateBuffer", "kdtree points, " + std::to_string(cap) + " bytes");
    points_cap_ = cap;
  }
  check_cl(rt->queue().enqueueWriteBuffer(points_, CL_FALSE, 0, bytes, host_points_.data()), "clEnqueueWriteBuffer",
           "kdtree points (insert)");
  check_cl(rt->queue().enqueueWriteBuffer(nodes_, CL_TRUE, 0, host_nodes_.size() * 4, host_nodes_.data()),
           "clEnqueueWriteBuffer", "kdtree nodes (insert)");
  ++merges_;
}

void KdTreeIndex::remove_points(const std::int32_t* ids, std::size_t n) {
  if (4 * (holes_ + n) > host_points_.size()) {
    rebuild_live();  // these ids are already marked removed
    ++rebuilds_;
    return;
  }
  if (pos_.empty()) {
    pos_.assign(std::size_t(id_bound()), -1);
    for (std::size_t i = 0; i < host_points_.size(); ++i)
      if (host_points_[i].id != BHCL_EMPTY_SLOT_ID) pos_[std::size_t(host_points_[i].id)] = std::int32_t(i);
  }
  pos_.resize(std::size_t(id_bound()), -1);
  std::vector<std::int32_t> at(n);
  for (std::size_t i = 0; i < n; ++i) {
    at[i] = pos_[std::size_t(ids[i])];
    if (at[i] < 0) throw Error("kdtree: remove: id " + std::to_string(ids[i]) + " is not in the tree (internal)");
  }
  const auto& rt = runtime_ptr();
  check_cl(rt->queue().finish(), "clFinish", "kdtree remove");
  std::int32_t lo = *std::min_element(at.begin(), at.end()), hi = *std::max_element(at.begin(), at.end());
  for (std::size_t i = 0; i < n; ++i) {
    host_points_[std::size_t(at[i])] = HostPoint{INFINITY, INFINITY, INFINITY, BHCL_EMPTY_SLOT_ID};
    pos_[std::size_t(ids[i])] = -1;
  }
  // One write of the span the holes touch (fewer, larger writes beat one per point).
  check_cl(rt->queue().enqueueWriteBuffer(points_, CL_TRUE, std::size_t(lo) * sizeof(HostPoint),
                                          std::size_t(hi - lo + 1) * sizeof(HostPoint), host_points_.data() + lo),
           "clEnqueueWriteBuffer", "kdtree points (remove)");
  holes_ += n;
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
      detail::kernel_build_options("kdtree_knn.cl", {{"BHCL_KMAX", kmax}, {"BHCL_KD_STACK", stack}}, params.kernel_defines));
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
  cl::Kernel kernel = runtime().kernel(
      "kdtree_radius.cl", "kdtree_radius",
      detail::kernel_build_options("kdtree_radius.cl", {{"BHCL_KD_STACK", stack}}, params.kernel_defines));
  detail::KernelArgs args(kernel, "kdtree_radius");
  args.add(nodes_).add(points_).add_radius(queries, first, count, r2, pass, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, "kdtree_radius");
}

}  // namespace bhcl
