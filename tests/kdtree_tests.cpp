// What only the kd-tree has: its shape (balanced, no recursion), its leaf size, its kernel file.
// Its answers are checked with every exact method in exact_methods_vs_bruteforce.cpp.
#include <chrono>
#include <cstring>
#include <random>

#include "test_util.hpp"

using namespace bhcl;

TEST_CASE("kdtree: the leaf size changes the tree, not the answer") {
  for (const auto& s : test::exact_point_sets()) {
    CAPTURE(s.name);
    KdTreeIndex index(test::runtime(), s.points.data(), s.points.size() / 3);
    KdTreeParams one;
    one.leaf_size = 1;
    KdTreeIndex fine(test::runtime(), s.points.data(), s.points.size() / 3, one);
    SearchParams p;
    p.k = 10;
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
  SearchParams p;
  p.k = 256;
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
