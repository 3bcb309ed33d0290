// Radius search with one radius per query (radius_search_per_query) for every method of the
// registry, against a brute-force float reference: exact methods slice for slice, block hashing
// as a subset within each query's radius with its recall; equal radii equal radius_search; the
// cap after the cut; bad radii refused naming the query.
#include "blockhash_cl/radius_per_query.hpp"

#include "test_util.hpp"

namespace bhcl::test {
namespace {

// Every point with dist2_float <= r_i^2, sorted (d, id): the contract's rule per query.
RadiusResult brute_per_query(const std::vector<float>& pts, const std::vector<float>& qs,
                             const std::vector<float>& radii) {
  std::vector<float> r2(radii.size());
  for (std::size_t q = 0; q < radii.size(); ++q) r2[q] = radii[q] * radii[q];
  return reference_radius_slices(pts, qs, r2);
}

// Radii spread over two orders of magnitude around a radius holding ~`target` points, with some
// exact zeros and repeats (bands of one value).
std::vector<float> spread_radii(const std::vector<float>& pts, std::size_t n, std::size_t target, std::uint64_t seed) {
  // The median 20th-neighbour distance of a few queries sets the scale.
  std::vector<float> d;
  const std::size_t N = pts.size() / 3;
  for (std::size_t q = 0; q < 10; ++q) {
    std::vector<float> row;
    for (std::size_t i = 0; i < N; ++i) row.push_back(reference::dist2_float(&pts[3 * i], &pts[3 * ((q * 7919) % N)]));
    std::nth_element(row.begin(), row.begin() + std::min(target, N - 1), row.end());
    d.push_back(std::sqrt(row[std::min(target, N - 1)]));
  }
  std::sort(d.begin(), d.end());
  const float base = d[d.size() / 2];
  std::vector<float> r(n);
  std::uint64_t s = seed;
  for (std::size_t i = 0; i < n; ++i) {
    s = s * 6364136223846793005ull + 1442695040888963407ull;
    const double u = double(s >> 11) / double(1ull << 53);
    r[i] = i % 17 == 0 ? 0.0f : i % 5 == 0 ? base : static_cast<float>(base * std::pow(10.0, 2.0 * u - 1.3));
  }
  return r;
}

}  // namespace

TEST_CASE("radius per query: exact methods equal brute force on every set (radius_per_query_vs_bruteforce)") {
  for (const auto& s : exact_point_sets()) {
    const std::size_t n = s.queries.size() / 3;
    const std::vector<float> radii = spread_radii(s.points, n, 20, 3);
    const RadiusResult ref = brute_per_query(s.points, s.queries, radii);
    for (const auto& m : exact_method_names()) {
      auto index = make_index(m, runtime(), s.points.data(), s.points.size() / 3);
      RadiusResult got;
      radius_search_per_query(*index, s.queries.data(), n, radii.data(), {}, got);
      require_same_slices(got, ref, m + " on " + s.name);
      REQUIRE(got.truncated_queries == 0);
    }
  }
}

TEST_CASE("radius per query: block hashing is a subset within each radius, recall high (radius_per_query_vs_bruteforce)") {
  const auto pts = datasets::uniform(20000, 7);
  const auto qs = queries_for(pts, 11, 100);
  const std::size_t n = qs.size() / 3;
  const std::vector<float> radii = spread_radii(pts, n, 30, 5);
  const RadiusResult ref = brute_per_query(pts, qs, radii);
  auto index = make_index("blockhash", runtime(), pts.data(), pts.size() / 3);
  RadiusParams p;
  p.count_examined = true;
  RadiusResult got;
  radius_search_per_query(*index, qs.data(), n, radii.data(), p, got);
  REQUIRE(got.offsets.size() == n + 1);
  REQUIRE(got.examined.size() == n);
  std::size_t hit = 0;
  for (std::size_t q = 0; q < n; ++q) {
    std::set<std::int32_t> truth(ref.ids.begin() + ref.offsets[q], ref.ids.begin() + ref.offsets[q + 1]);
    for (auto j = got.offsets[q]; j < got.offsets[q + 1]; ++j) {
      REQUIRE(got.dist2[j] <= radii[q] * radii[q]);
      REQUIRE(got.dist2[j] == reference::dist2_float(&pts[3 * got.ids[j]], &qs[3 * q]));
      if (j > got.offsets[q]) REQUIRE(got.dist2[j - 1] <= got.dist2[j]);
      hit += truth.count(got.ids[j]);
    }
    REQUIRE(got.count(q) <= ref.count(q));
  }
  const double recall = double(hit) / double(std::max<std::size_t>(1, ref.total()));
  INFO("per-query radius recall " << recall);
  CHECK(recall >= 0.9);  // as radius_search's auto preset (radius_search_vs_bruteforce)
}

TEST_CASE("radius per query: every method, equal radii equal radius_search, the cap comes after the cut") {
  const auto pts = datasets::clustered(5000, 3);
  const auto qs = queries_for(pts, 5, 40);
  const std::size_t n = qs.size() / 3;
  const std::vector<float> spread = spread_radii(pts, n, 30, 9);
  for (const auto& m : method_names()) {
    INFO(m);
    auto index = make_index(m, runtime(), pts.data(), pts.size() / 3);
    const float r = spread[1];
    const std::vector<float> same(n, r);
    RadiusResult a, b;
    index->radius_search(qs.data(), n, r, {}, a);
    radius_search_per_query(*index, qs.data(), n, same.data(), {}, b);
    require_same_slices(b, a, m + ": equal radii");
    // The cap keeps the nearest within each query's own radius; found is the count before it.
    RadiusResult full, capped;
    radius_search_per_query(*index, qs.data(), n, spread.data(), {}, full);
    RadiusParams p;
    p.max_results = 4;
    radius_search_per_query(*index, qs.data(), n, spread.data(), p, capped);
    REQUIRE(capped.found == full.found);
    std::size_t truncated = 0;
    for (std::size_t q = 0; q < n; ++q) {
      const std::size_t c = std::min<std::size_t>(4, full.count(q));
      REQUIRE(capped.count(q) == c);
      truncated += full.count(q) > 4;
      for (std::size_t j = 0; j < c; ++j) REQUIRE(capped.ids[capped.offsets[q] + j] == full.ids[full.offsets[q] + j]);
    }
    REQUIRE(capped.truncated_queries == truncated);
  }
}

TEST_CASE("radius per query: bad radii are refused naming the query") {
  const auto pts = datasets::uniform(500, 1);
  auto index = make_index("bruteforce", runtime(), pts.data(), pts.size() / 3);
  const std::vector<float> qs = {0.5f, 0.5f, 0.5f, 0.1f, 0.2f, 0.3f};
  RadiusResult out;
  for (float bad : {-1.0f, NAN, INFINITY}) {
    const std::vector<float> radii = {0.1f, bad};
    try {
      radius_search_per_query(*index, qs.data(), 2, radii.data(), {}, out);
      FAIL("accepted radius " << bad);
    } catch (const Error& e) {
      CHECK(std::string(e.what()).find("radius of query 1") != std::string::npos);
    }
  }
  CHECK_THROWS_AS(radius_search_per_query(*index, qs.data(), 2, nullptr, {}, out), Error);
  radius_search_per_query(*index, qs.data(), 0, nullptr, {}, out);
  CHECK(out.offsets.size() == 1);
}

}  // namespace bhcl::test
