// The brute-force kernel against the host references: bit-exact against the float reference
// (same arithmetic), tie-tolerant against the double-precision reference.
#include "test_util.hpp"

using namespace bhcl;

namespace {

void run_case(const std::vector<float>& pts, const std::vector<float>& qs, SearchParams p) {
  const std::size_t N = pts.size() / 3, n = qs.size() / 3;
  BruteForceIndex index(test::runtime(), pts.data(), N);
  KnnResult r;
  QueryStats st = index.query(qs.data(), n, p, r);
  CHECK(st.n_queries == n);
  KnnResult ref = reference::knn_float(pts.data(), N, qs.data(), n, p);
  CHECK(r.ids == ref.ids);
  CHECK(r.counts == ref.counts);
  for (std::size_t i = 0; i < r.dist2.size(); ++i) {
    INFO("entry " << i);
    REQUIRE((r.dist2[i] == ref.dist2[i] || (std::isinf(r.dist2[i]) && std::isinf(ref.dist2[i]))));
  }
  test::check_exact_vs_double(r, pts.data(), N, qs.data(), n, p);
}

}  // namespace

TEST_CASE("bruteforce_vs_reference: uniform, k from 1 to 256") {
  auto pts = datasets::uniform(3000, 11);
  auto qs = datasets::uniform(300, 12);
  for (int k : {1, 7, 8, 10, 33, 64, 100, 256}) {
    CAPTURE(k);
    SearchParams p = test::knn_params(k);
    run_case(pts, qs, p);
  }
}

TEST_CASE("bruteforce_vs_reference: clustered and offset data") {
  SearchParams p = test::knn_params(16);
  run_case(datasets::clustered(4000, 3, 8, 0.002f), datasets::clustered(400, 4, 8, 0.002f), p);
  auto pts = datasets::uniform(2000, 5, -50.0f, 50.0f);
  auto qs = datasets::uniform(200, 6, -50.0f, 50.0f);
  datasets::offset(pts, 1e4, -2e4, 3e3);
  datasets::offset(qs, 1e4, -2e4, 3e3);
  run_case(pts, qs, p);
}

TEST_CASE("bruteforce_vs_reference: duplicates keep the lower index first") {
  auto pts = datasets::with_duplicates(2000, 7, 0.5);
  // Queries exactly on points: many zero distances that tie.
  std::vector<float> qs(pts.begin(), pts.begin() + 3 * 200);
  SearchParams p = test::knn_params(12);
  run_case(pts, qs, p);
  // All points identical: the answer is ids 0..k-1 at distance d.
  std::vector<float> same(3 * 100, 0.25f);
  std::vector<float> q = {0.0f, 0.0f, 0.0f};
  BruteForceIndex index(test::runtime(), same.data(), 100);
  KnnResult r = index.query(q, p);
  for (int j = 0; j < p.k; ++j) {
    CHECK(r.id(0, j) == j);
    CHECK(r.d2(0, j) == reference::dist2_float(same.data(), q.data()));
  }
}

TEST_CASE("bruteforce_vs_reference: k > N fills the row with -1 / +inf") {
  auto pts = datasets::uniform(5, 8);
  auto qs = datasets::uniform(10, 9);
  SearchParams p = test::knn_params(32);
  run_case(pts, qs, p);
  BruteForceIndex index(test::runtime(), pts.data(), 5);
  KnnResult r = index.query(qs, p);
  for (std::size_t q = 0; q < 10; ++q) {
    CHECK(r.counts[q] == 5);
    CHECK(r.id(q, 5) == -1);
    CHECK(std::isinf(r.d2(q, 31)));
  }
}

TEST_CASE("bruteforce_vs_reference: maximum radius cuts the rows") {
  auto pts = datasets::uniform(3000, 21);
  auto qs = datasets::uniform(300, 22);
  SearchParams p = test::knn_params(40);
  p.max_radius = 0.05f;
  run_case(pts, qs, p);
  p.max_radius = 0.0f;  // only exact hits
  std::vector<float> on(pts.begin(), pts.begin() + 30);
  run_case(pts, on, p);
}

