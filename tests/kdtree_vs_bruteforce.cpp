// The kd-tree kernel against brute force: bit-exact (ids with the lower-index tie rule, squared
// distances, counts) on point sets that stress splitting and pruning, k from 1 to 256, with and
// without a maximum radius. Also the tree's shape (balanced, no recursion), the buffer-level
// call, and bad input.
#include <chrono>
#include <cstring>
#include <random>

#include "test_util.hpp"

using namespace bhcl;

namespace bhcl::test {

struct PointSet {
  std::string name;
  std::vector<float> points, queries;
};

// Queries for a point set: uniform over its box grown by 10 %, exact copies of points (distance
// 0 ties, duplicates), and points moved by a tiny jitter (near-ties).
std::vector<float> queries_for(const std::vector<float>& pts, std::uint64_t seed, std::size_t each = 100) {
  const std::size_t N = pts.size() / 3;
  float lo[3], hi[3];
  for (int d = 0; d < 3; ++d) lo[d] = hi[d] = pts[d];
  for (std::size_t i = 0; i < N; ++i)
    for (int d = 0; d < 3; ++d) {
      lo[d] = std::min(lo[d], pts[3 * i + d]);
      hi[d] = std::max(hi[d], pts[3 * i + d]);
    }
  std::mt19937_64 rng(seed);
  std::vector<float> q;
  for (std::size_t i = 0; i < each; ++i)
    for (int d = 0; d < 3; ++d) {
      double ext = double(hi[d]) - lo[d];
      std::uniform_real_distribution<double> u(lo[d] - 0.1 * ext, hi[d] + 0.1 * ext);
      q.push_back(static_cast<float>(u(rng)));
    }
  std::uniform_int_distribution<std::size_t> pick(0, N - 1);
  for (std::size_t i = 0; i < each; ++i) {
    std::size_t p = pick(rng);
    q.insert(q.end(), pts.begin() + 3 * p, pts.begin() + 3 * p + 3);
  }
  std::normal_distribution<float> jitter(0.0f, 1.0f);
  for (std::size_t i = 0; i < each; ++i) {
    std::size_t p = pick(rng);
    for (int d = 0; d < 3; ++d) {
      float v = pts[3 * p + d];
      float step = std::max(std::abs(v) * 1e-6f, 1e-4f * float(double(hi[d]) - lo[d]));
      q.push_back(v + step * jitter(rng));
    }
  }
  return q;
}

// The point sets every exact method is checked on (flann_vs_bruteforce.cpp uses them too).
std::vector<PointSet> exact_point_sets() {
  std::vector<PointSet> sets;
  auto add = [&](const std::string& name, std::vector<float> pts, std::uint64_t seed) {
    std::vector<float> q = queries_for(pts, seed);
    sets.push_back({name, std::move(pts), std::move(q)});
  };
  add("uniform", datasets::uniform(3000, 101), 1);
  add("clustered", datasets::clustered(4000, 102, 8, 0.002f), 2);
  add("duplicates", datasets::with_duplicates(3000, 103, 0.5), 3);
  add("identical", std::vector<float>(3 * 1000, 0.375f), 4);
  {
    auto pts = datasets::uniform(3000, 105);
    for (std::size_t i = 0; i < pts.size(); i += 3) pts[i + 2] = 0.5f;  // flat: z = const
    add("flat", std::move(pts), 5);
  }
  {
    // Collinear: a diagonal line (x = y = z) and an axis-aligned one, with repeated positions.
    std::mt19937_64 rng(106);
    std::uniform_int_distribution<int> t(0, 1500);
    std::vector<float> pts;
    for (int i = 0; i < 2000; ++i) {
      float v = static_cast<float>(t(rng)) / 1500.0f;
      pts.insert(pts.end(), {v, v, v});
    }
    for (int i = 0; i < 1000; ++i) pts.insert(pts.end(), {static_cast<float>(t(rng)) / 1500.0f, 0.25f, 0.75f});
    add("collinear", std::move(pts), 6);
  }
  {
    // Offset far from the origin: at 1e6 a float step is 0.0625, so coordinates are coarsely
    // quantised and distances tie often.
    auto pts = datasets::uniform(3000, 107, -50.0f, 50.0f);
    datasets::offset(pts, 1e4, -2e5, 1e6);
    add("offset", std::move(pts), 7);
  }
  return sets;
}

// A radius that cuts many rows short: the median distance to the 8th neighbour.
float cutting_radius(const PointSet& s) {
  SearchParams p;
  p.k = 8;
  const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
  KnnResult r = reference::knn_float(s.points.data(), N, s.queries.data(), n, p);
  std::vector<float> d;
  for (std::size_t q = 0; q < n; ++q)
    if (r.counts[q] == 8) d.push_back(r.d2(q, 7));
  std::nth_element(d.begin(), d.begin() + d.size() / 2, d.end());
  return std::sqrt(d[d.size() / 2]);
}

// Bit-exact equality of two results (ids, counts, distances including +inf), naming the first
// differing entry.
void require_identical(const KnnResult& r, const KnnResult& ref, const std::string& what) {
  REQUIRE(r.n == ref.n);
  REQUIRE(r.k == ref.k);
  CHECK(r.counts == ref.counts);
  for (std::size_t i = 0; i < r.ids.size(); ++i) {
    if (r.ids[i] == ref.ids[i] && std::memcmp(&r.dist2[i], &ref.dist2[i], sizeof(float)) == 0) continue;
    FAIL_CHECK(what << ": query " << i / r.k << " rank " << i % r.k << ": id " << r.ids[i] << " d2 "
                    << r.dist2[i] << ", brute force id " << ref.ids[i] << " d2 " << ref.dist2[i]);
    return;
  }
}

// Runs an exact index on a point set for every k, with and without the cutting radius.
void check_index_on_set(const Index& index, const PointSet& s) {
  const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
  const float radius = cutting_radius(s);
  for (float r : {INFINITY, radius}) {
    for (int k : {1, 8, 10, 50, 100, 256}) {
      SearchParams p;
      p.k = k;
      p.max_radius = r;
      CAPTURE(k);
      CAPTURE(r);
      KnnResult got;
      index.query(s.queries.data(), n, p, got);
      KnnResult ref = reference::knn_float(s.points.data(), N, s.queries.data(), n, p);
      require_identical(got, ref, index.method() + " on " + s.name);
    }
  }
}

}  // namespace bhcl::test

namespace {

void run_set(const std::string& name) {
  for (const auto& s : test::exact_point_sets()) {
    if (s.name != name) continue;
    KdTreeIndex index(test::runtime(), s.points.data(), s.points.size() / 3);
    test::check_index_on_set(index, s);
    // A different bucket size changes the tree, not the answer.
    KdTreeParams one;
    one.leaf_size = 1;
    KdTreeIndex fine(test::runtime(), s.points.data(), s.points.size() / 3, one);
    SearchParams p;
    p.k = 10;
    test::require_identical(fine.query(s.queries, p), index.query(s.queries, p), "leaf_size 1");
    return;
  }
  FAIL("no point set named " << name);
}

}  // namespace

TEST_CASE("kdtree_vs_bruteforce: uniform") { run_set("uniform"); }
TEST_CASE("kdtree_vs_bruteforce: clustered") { run_set("clustered"); }
TEST_CASE("kdtree_vs_bruteforce: 50% duplicates") { run_set("duplicates"); }
TEST_CASE("kdtree_vs_bruteforce: all points identical") { run_set("identical"); }
TEST_CASE("kdtree_vs_bruteforce: flat (z = const)") { run_set("flat"); }
TEST_CASE("kdtree_vs_bruteforce: collinear") { run_set("collinear"); }
TEST_CASE("kdtree_vs_bruteforce: offset by 1e4..1e6") { run_set("offset"); }

TEST_CASE("kdtree_vs_bruteforce: equals the brute-force kernel itself") {
  auto pts = datasets::clustered(2500, 111, 4, 0.01f);
  auto qs = test::queries_for(pts, 112);
  KdTreeIndex kd(test::runtime(), pts.data(), 2500);
  BruteForceIndex bf(test::runtime(), pts.data(), 2500);
  for (int k : {1, 33, 256}) {
    CAPTURE(k);
    SearchParams p;
    p.k = k;
    test::require_identical(kd.query(qs, p), bf.query(qs, p), "kdtree vs bruteforce kernel");
  }
}

TEST_CASE("kdtree: k > N and tiny sets fill rows with -1 / +inf") {
  for (std::size_t N : {1, 2, 5, 13}) {
    CAPTURE(N);
    auto pts = datasets::uniform(N, 120 + N);
    auto qs = datasets::uniform(20, 121);
    KdTreeIndex index(test::runtime(), pts.data(), N);
    SearchParams p;
    p.k = 32;
    KnnResult r = index.query(qs, p);
    test::require_identical(r, reference::knn_float(pts.data(), N, qs.data(), 20, p), "k > N");
    for (std::size_t q = 0; q < 20; ++q) CHECK(r.counts[q] == static_cast<int>(N));
  }
}

TEST_CASE("kdtree: radius 0 finds exact hits only") {
  auto pts = datasets::with_duplicates(2000, 131, 0.5);
  std::vector<float> on(pts.begin(), pts.begin() + 3 * 50);
  auto off = datasets::uniform(50, 132);
  on.insert(on.end(), off.begin(), off.end());
  KdTreeIndex index(test::runtime(), pts.data(), 2000);
  SearchParams p;
  p.k = 16;
  p.max_radius = 0.0f;
  KnnResult r = index.query(on, p);
  test::require_identical(r, reference::knn_float(pts.data(), 2000, on.data(), 100, p), "radius 0");
  for (std::size_t q = 0; q < 50; ++q) CHECK(r.counts[q] >= 1);
}

TEST_CASE("kdtree: points whose distances overflow to +inf still fill the row") {
  // |q - p|^2 overflows float for coordinates near 1e20: the index computes in coordinates
  // scaled by a power of two (knn.hpp, "Extreme scales"), so the row is ordered by the true
  // distances, as brute force orders it, and the distances read +inf.
  std::vector<float> pts = {0.0f, 0.0f, 0.0f, 3e19f, 0.0f, 0.0f, -3e19f, 1e19f, 0.0f,
                            1.0f, 1.0f, 1.0f, 0.0f, -3e19f, 2e19f};
  std::vector<float> qs = {0.5f, 0.5f, 0.5f, -3e19f, -3e19f, 0.0f};
  KdTreeIndex index(test::runtime(), pts.data(), 5);
  BruteForceIndex brute(test::runtime(), pts.data(), 5);
  SearchParams p;
  p.k = 5;
  KnnResult r = index.query(qs, p);
  test::require_identical(r, brute.query(qs, p), "overflowing distances");
  test::check_exact_vs_double(r, pts.data(), 5, qs.data(), 2, p);
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

TEST_CASE("kdtree: results do not depend on batch or work-group size") {
  auto pts = datasets::uniform(3000, 151);
  auto qs = datasets::uniform(700, 152);
  KdTreeIndex index(test::runtime(), pts.data(), 3000);
  SearchParams p;
  p.k = 10;
  KnnResult base = index.query(qs, p);
  for (std::size_t local : {1, 7, 32, 128}) {
    for (std::size_t batch : {0, 33, 699}) {
      CAPTURE(local);
      CAPTURE(batch);
      SearchParams q = p;
      q.local_size = local;
      q.max_batch = batch;
      test::require_identical(index.query(qs, q), base, "batch/local");
    }
  }
}

TEST_CASE("kdtree: non-finite queries get empty rows, warm-up is separate from queries") {
  auto pts = datasets::uniform(500, 161);
  std::vector<float> qs = datasets::uniform(4, 162);
  qs[3 * 1 + 0] = NAN;
  qs[3 * 3 + 2] = -INFINITY;
  KdTreeIndex index(test::runtime(), pts.data(), 500);
  SearchParams p;
  p.k = 5;
  index.warm_up(p);
  CHECK(index.warm_up(p) == 0.0);  // already compiled: the count-0 launch is not repeated
  QueryStats st;
  KnnResult r = index.query(qs, p, &st);
  CHECK(st.nonfinite_queries == 2);
  CHECK(st.compile_s == 0.0);
  CHECK(r.counts == std::vector<std::int32_t>{5, 0, 5, 0});
  CHECK(r.id(1, 0) == -1);
  CHECK(std::isinf(r.d2(3, 4)));
}

TEST_CASE("kdtree: bad input is refused with a clear error") {
  auto rt = test::runtime();
  std::vector<float> pts = datasets::uniform(10, 171);
  CHECK_THROWS_WITH_AS(KdTreeIndex(rt, pts.data(), 0), doctest::Contains("empty"), Error);
  KdTreeParams bad;
  bad.leaf_size = 0;
  CHECK_THROWS_WITH_AS(KdTreeIndex(rt, pts.data(), 10, bad), doctest::Contains("leaf_size"), Error);
  pts[3 * 6 + 2] = INFINITY;
  CHECK_THROWS_WITH_AS(KdTreeIndex(rt, pts.data(), 10), doctest::Contains("point 6"), Error);
  pts[3 * 6 + 2] = 0.5f;
  KdTreeIndex index(rt, pts.data(), 10);
  SearchParams p;
  p.k = kMaxK + 1;
  CHECK_THROWS_WITH_AS(index.query(pts, p), doctest::Contains("out of range"), Error);
}

TEST_CASE("kdtree: buffer-level call on caller-owned buffers, and the factory") {
  auto rt = test::runtime();
  auto pts = datasets::uniform(1500, 181);
  auto qs = datasets::uniform(100, 182);
  auto index = make_index("kdtree", rt, pts.data(), 1500);
  CHECK(index->method() == "kdtree");
  CHECK(index->exact());
  SearchParams p;
  p.k = 8;
  cl::Buffer qb(rt->context(), CL_MEM_READ_ONLY | CL_MEM_COPY_HOST_PTR, qs.size() * 4, qs.data());
  ResultBuffers out{cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 8 * 4),
                    cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 8 * 4),
                    cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 4)};
  cl::Event e = index->enqueue_query(rt->queue(), qb, 100, out, p);
  std::vector<cl::Event> wait{e};
  std::vector<int> ids(800);
  std::vector<float> d2(800);
  rt->queue().enqueueReadBuffer(out.ids, CL_TRUE, 0, 800 * 4, ids.data(), &wait);
  rt->queue().enqueueReadBuffer(out.dist2, CL_TRUE, 0, 800 * 4, d2.data(), &wait);
  KnnResult ref = reference::knn_float(pts.data(), 1500, qs.data(), 100, p);
  CHECK(ids == ref.ids);
  CHECK(d2 == ref.dist2);
}

TEST_CASE("kdtree: the kernel file builds on its own, with its default defines") {
  auto rt = test::runtime();
  cl::Program prog = rt->program("kdtree_knn.cl");
  cl_int err = CL_SUCCESS;
  cl::Kernel k(prog, "kdtree_knn", &err);
  CHECK(err == CL_SUCCESS);
}
