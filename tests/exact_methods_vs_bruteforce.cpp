// Every exact method of the registry (exact_method_names(): bruteforce, kdtree, flann where built)
// against the brute-force float reference: bit-exact (ids with the lower-index tie rule, squared
// distances, counts) on point sets that stress splitting and pruning, k from 1 to 256, with and
// without a maximum radius, and on the small-set edge cases. Then what every method of the
// registry must do alike: the buffer-level call, the warm-up, and the refusal of bad parameters.
// A new method is covered here by its registry entry alone.
#include "test_util.hpp"

using namespace bhcl;

namespace {

void run_set(const std::string& name) {
  for (const auto& s : test::exact_point_sets()) {
    if (s.name != name) continue;
    for (const auto& method : exact_method_names()) {
      CAPTURE(method);
      auto index = make_index(method, test::runtime(), s.points.data(), s.points.size() / 3);
      REQUIRE(index->exact());
      test::check_index_on_set(*index, s);
    }
    return;
  }
  FAIL("no point set named " << name);
}

}  // namespace

TEST_CASE("exact_methods_vs_bruteforce: uniform") { run_set("uniform"); }
TEST_CASE("exact_methods_vs_bruteforce: clustered") { run_set("clustered"); }
TEST_CASE("exact_methods_vs_bruteforce: 50% duplicates") { run_set("duplicates"); }
TEST_CASE("exact_methods_vs_bruteforce: all points identical") { run_set("identical"); }
TEST_CASE("exact_methods_vs_bruteforce: flat (z = const)") { run_set("flat"); }
TEST_CASE("exact_methods_vs_bruteforce: collinear") { run_set("collinear"); }
TEST_CASE("exact_methods_vs_bruteforce: offset by 1e4..1e6") { run_set("offset"); }

TEST_CASE("exact_methods_vs_bruteforce: k > N, radius 0, distances that overflow to +inf") {
  auto rt = test::runtime();
  for (const auto& method : exact_method_names()) {
    CAPTURE(method);
    // k > N and tiny sets: rows filled with -1 / +inf after the N points.
    for (std::size_t N : {1, 2, 5, 13}) {
      CAPTURE(N);
      auto pts = datasets::uniform(N, 120 + N);
      auto qs = datasets::uniform(20, 121);
      SearchParams p = test::knn_params(32);
      KnnResult r = make_index(method, rt, pts.data(), N)->query(qs, p);
      test::require_identical(r, reference::knn_float(pts.data(), N, qs.data(), 20, p), "k > N");
      for (std::size_t q = 0; q < 20; ++q) CHECK(r.counts[q] == static_cast<int>(N));
    }
    // Radius 0: exact hits only (duplicates included), nothing for queries off the points.
    {
      auto pts = datasets::with_duplicates(2000, 131, 0.5);
      std::vector<float> on(pts.begin(), pts.begin() + 3 * 50);
      auto off = datasets::uniform(50, 132);
      on.insert(on.end(), off.begin(), off.end());
      SearchParams p = test::knn_params(16);
      p.max_radius = 0.0f;
      KnnResult r = make_index(method, rt, pts.data(), 2000)->query(on, p);
      test::require_identical(r, reference::knn_float(pts.data(), 2000, on.data(), 100, p), "radius 0");
      for (std::size_t q = 0; q < 50; ++q) CHECK(r.counts[q] >= 1);
    }
    // |q - p|^2 overflows float near 1e20: the index computes in coordinates scaled by a power
    // of two (knn.hpp, "Extreme scales"), so the row is ordered by the true distances and the
    // distances read +inf.
    {
      std::vector<float> pts = {0.0f, 0.0f, 0.0f, 3e19f, 0.0f, 0.0f, -3e19f, 1e19f, 0.0f,
                                1.0f, 1.0f, 1.0f, 0.0f, -3e19f, 2e19f};
      std::vector<float> qs = {0.5f, 0.5f, 0.5f, -3e19f, -3e19f, 0.0f};
      SearchParams p = test::knn_params(5);
      KnnResult r = make_index(method, rt, pts.data(), 5)->query(qs, p);
      test::require_identical(r, make_index("bruteforce", rt, pts.data(), 5)->query(qs, p),
                              "overflowing distances");
      test::check_exact_vs_double(r, pts.data(), 5, qs.data(), 2, p);
    }
  }
}

TEST_CASE("every method: the buffer-level call on caller-owned buffers equals the host-array call") {
  auto rt = test::runtime();
  auto pts = datasets::uniform(1500, 181);
  auto qs = datasets::uniform(100, 182);
  for (const auto& method : method_names()) {
    CAPTURE(method);
    auto index = make_index(method, rt, pts.data(), 1500);
    CHECK(index->method() == method);
    CHECK(index->exact() == method_info(method).exact);
    SearchParams p = test::knn_params(8);
    p.max_batch = 30;  // several dispatches (or host round trips), each on its own rows
    // Warm-up is separate from queries: the second warm-up and the query compile nothing.
    index->warm_up(p);
    CHECK(index->warm_up(p) == 0.0);
    KnnResult buf = test::buffer_query(*index, qs, p);
    QueryStats st;
    KnnResult host = index->query(qs, p, &st);
    CHECK(st.compile_s == 0.0);
    CHECK(buf.ids == host.ids);
    CHECK(buf.dist2 == host.dist2);
    CHECK(buf.counts == host.counts);
    if (index->exact()) {
      KnnResult ref = reference::knn_float(pts.data(), 1500, qs.data(), 100, p);
      CHECK(buf.ids == ref.ids);
      CHECK(buf.dist2 == ref.dist2);
    }
    // Result buffers too small for n queries are refused before anything is enqueued.
    cl::Buffer qb(rt->context(), CL_MEM_READ_ONLY | CL_MEM_COPY_HOST_PTR, qs.size() * 4, qs.data());
    ResultBuffers small{cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 8 * 4),
                        cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 8 * 4),
                        cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 10 * 4)};
    CHECK_THROWS_WITH_AS(index->enqueue_query(rt->queue(), qb, 100, small, p),
                         doctest::Contains("counts buffer holds 40 bytes"), Error);
  }
}

TEST_CASE("every method: bad search parameters and ragged query arrays are refused") {
  auto rt = test::runtime();
  std::vector<float> pts = datasets::uniform(10, 1);
  std::vector<float> qs = datasets::uniform(3, 2);
  for (const auto& method : method_names()) {
    CAPTURE(method);
    auto index = make_index(method, rt, pts.data(), 10);
    SearchParams p = test::knn_params(0);
    CHECK_THROWS_WITH_AS(index->query(qs, p), doctest::Contains("k = 0"), Error);
    p.k = kMaxK + 1;
    CHECK_THROWS_WITH_AS(index->query(qs, p), doctest::Contains("out of range"), Error);
    p.k = 3;
    p.max_radius = -1.0f;
    CHECK_THROWS_WITH_AS(index->query(qs, p), doctest::Contains("max_radius"), Error);
    p.max_radius = INFINITY;
    std::vector<float> ragged = {1.0f, 2.0f};
    CHECK_THROWS_WITH_AS(index->query(ragged, p), doctest::Contains("multiple of 3"), Error);
    KnnResult empty = index->query(std::vector<float>{}, p);
    CHECK(empty.n == 0);
  }
}
