// What only the kd-tree has: its shape (balanced, no recursion), its leaf size, its kernel file.
// Its answers are checked with every exact method in exact_methods_vs_bruteforce.cpp.
#include <chrono>
#include <cstdint>
#include <cstring>
#include <random>

#include "kdtree/build.hpp"
#include "test_util.hpp"

using namespace bhcl;

namespace {

// The serial build as it was before the parallel one (one explicit stack, node indices in pop
// order, a right child's index patched into its parent): the parallel build must give these
// arrays byte for byte.
detail::KdTreeArrays serial_reference_build(const float* xyz, std::size_t n, std::size_t leaf) {
  detail::KdTreeArrays t;
  t.perm.resize(n);
  for (std::size_t i = 0; i < n; ++i) t.perm[i] = static_cast<std::uint32_t>(i);
  struct Task {
    std::size_t begin, end;
    int depth;
    std::int64_t parent;
  };
  std::vector<Task> stack{{0, n, 0, -1}};
  while (!stack.empty()) {
    Task task = stack.back();
    stack.pop_back();
    const auto index = static_cast<std::uint32_t>(t.nodes.size());
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
    for (std::size_t i = task.begin + 1; i < task.end; ++i)
      for (int d = 0; d < 3; ++d) {
        lo[d] = std::min(lo[d], xyz[3 * std::size_t(t.perm[i]) + d]);
        hi[d] = std::max(hi[d], xyz[3 * std::size_t(t.perm[i]) + d]);
      }
    int dim = 0;
    double widest = -1.0;
    for (int d = 0; d < 3; ++d)
      if (double(hi[d]) - double(lo[d]) > widest) widest = double(hi[d]) - double(lo[d]), dim = d;
    const std::size_t mid = task.begin + count / 2;
    std::nth_element(t.perm.begin() + task.begin, t.perm.begin() + mid, t.perm.begin() + task.end,
                     [xyz, dim](std::uint32_t a, std::uint32_t b) {
                       return xyz[3 * std::size_t(a) + dim] < xyz[3 * std::size_t(b) + dim];
                     });
    node.split = xyz[3 * std::size_t(t.perm[mid]) + dim];
    node.dim = static_cast<std::uint32_t>(dim);
    t.nodes.push_back(node);
    stack.push_back({mid, task.end, task.depth + 1, static_cast<std::int64_t>(index)});
    stack.push_back({task.begin, mid, task.depth + 1, -1});
  }
  return t;
}

}  // namespace

TEST_CASE("kdtree: the parallel build gives the serial build's arrays, byte for byte") {
  struct Set {
    std::string name;
    std::vector<float> pts;
  };
  std::vector<Set> sets = {{"uniform 100k", datasets::uniform(100000, 7)},
                           {"cornell 100k", datasets::cornell_photons(100000, 3)},
                           {"duplicates 60k", datasets::with_duplicates(60000, 5, 0.5)},
                           {"uniform 40001", datasets::uniform(40001, 9)},
                           {"uniform 1000", datasets::uniform(1000, 11)}};
  for (const auto& s : sets) {
    const std::size_t n = s.pts.size() / 3;
    for (std::size_t leaf : {std::size_t(1), std::size_t(16), std::size_t(23)}) {
      if (leaf == 1 && n > 50000) continue;  // one point per leaf: the small sets only
      CAPTURE(s.name);
      CAPTURE(leaf);
      const auto ref = serial_reference_build(s.pts.data(), n, leaf);
      for (unsigned threads : {1u, 2u, 3u, 8u}) {
        CAPTURE(threads);
        const auto t = detail::build_kdtree(s.pts.data(), n, leaf, threads);
        CHECK(t.leaves == ref.leaves);
        CHECK(t.depth == ref.depth);
        REQUIRE(t.nodes.size() == ref.nodes.size());
        CHECK(std::memcmp(t.nodes.data(), ref.nodes.data(), ref.nodes.size() * sizeof(bhcl_kd_node)) == 0);
        CHECK(t.perm == ref.perm);
      }
    }
  }
  // The index: one build thread and several answer alike.
  auto pts = datasets::cornell_photons(50000, 4);
  auto qs = datasets::cornell_queries(1000, 5);
  KdTreeParams one, many;
  one.build_threads = 1;
  many.build_threads = 4;
  KdTreeIndex a(test::runtime(), pts.data(), 50000, one), b(test::runtime(), pts.data(), 50000, many);
  CHECK(a.node_count() == b.node_count());
  CHECK(a.depth() == b.depth());
  SearchParams p = test::knn_params(10);
  test::require_identical(a.query(qs, p), b.query(qs, p), "build_threads 1 vs 4");
}

TEST_CASE("kdtree: the leaf size changes the tree, not the answer") {
  for (const auto& s : test::exact_point_sets()) {
    CAPTURE(s.name);
    KdTreeIndex index(test::runtime(), s.points.data(), s.points.size() / 3);
    KdTreeParams one;
    one.leaf_size = 1;
    KdTreeIndex fine(test::runtime(), s.points.data(), s.points.size() / 3, one);
    SearchParams p = test::knn_params(10);
    test::require_identical(fine.query(s.queries, p), index.query(s.queries, p), "leaf_size 1");
  }
}

TEST_CASE("kdtree: balanced tree, iterative build, quick on degenerate data") {
  auto pts = datasets::uniform(100000, 141);
  KdTreeIndex index(test::runtime(), pts.data(), 100000);
  // Median splits: depth = ceil(log2(N / leaf)) exactly.
  const int expect = static_cast<int>(std::ceil(std::log2(100000.0 / index.leaf_size())));
  CHECK(index.depth() == expect);
  CHECK(index.node_count() == 2 * index.leaf_count() - 1);
  CHECK(index.memory_bytes() == index.node_count() * 16 + 100000 * 16);
  // 200k identical points: a value-based split would recurse N deep or go quadratic.
  std::vector<float> same(3 * 200000, 1.5f);
  auto t0 = std::chrono::steady_clock::now();
  KdTreeIndex deg(test::runtime(), same.data(), 200000);
  double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  CHECK(deg.depth() == static_cast<int>(std::ceil(std::log2(200000.0 / deg.leaf_size()))));
  CHECK(s < 5.0);
  std::vector<float> q = {1.5f, 1.5f, 1.5f, 0.0f, 0.0f, 0.0f};
  SearchParams p = test::knn_params(256);
  KnnResult r = deg.query(q, p);
  for (int j = 0; j < 256; ++j) {
    CHECK(r.id(0, j) == j);
    CHECK(r.id(1, j) == j);
  }
  CHECK(r.d2(0, 255) == 0.0f);
}

TEST_CASE("kdtree: a leaf size out of range is refused") {
  auto rt = test::runtime();
  std::vector<float> pts = datasets::uniform(10, 171);
  CHECK_THROWS_WITH_AS(KdTreeIndex(rt, pts.data(), 0), doctest::Contains("empty"), Error);
  KdTreeParams bad;
  bad.leaf_size = 0;
  CHECK_THROWS_WITH_AS(KdTreeIndex(rt, pts.data(), 10, bad), doctest::Contains("leaf_size"), Error);
  bad.leaf_size = 1025;
  CHECK_THROWS_WITH_AS(KdTreeIndex(rt, pts.data(), 10, bad), doctest::Contains("leaf_size"), Error);
}

TEST_CASE("kdtree: the kernel file builds on its own, with its default defines") {
  auto rt = test::runtime();
  cl::Program prog = rt->program("kdtree_knn.cl");
  cl_int err = CL_SUCCESS;
  cl::Kernel k(prog, "kdtree_knn", &err);
  CHECK(err == CL_SUCCESS);
}
