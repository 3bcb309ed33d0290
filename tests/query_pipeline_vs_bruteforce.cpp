// The one host-array query pipeline (lib/src/core/query_pipeline.cpp): its shared steps (dispatches
// split by the batch bound, the Hilbert order, the buffers kept from call to call, the exact
// re-answer of suspect rows) give the same answers for both kinds of query, kNN and radius, on
// every method, checked against brute force (the float reference).
#include <cstring>

#include "blockhash_cl/density_query.hpp"
#include "test_util.hpp"

namespace bhcl::test {
namespace {

// The float reference of a radius search with RadiusParams's defaults (sorted slices, no cap).
RadiusResult radius_reference(const std::vector<float>& pts, const std::vector<float>& qs, float r) {
  return reference_radius_slices(pts, qs, {r * r});
}

KnnResult knn_reference(const std::vector<float>& pts, const std::vector<float>& qs, int k) {
  return reference::knn_float(pts.data(), pts.size() / 3, qs.data(), qs.size() / 3, knn_params(k));
}

// The points and queries of these tests, with the radius holding about 12 points per query.
struct Case {
  std::vector<float> pts = datasets::clustered(3000, 5);
  std::vector<float> qs = queries_for(pts, 17, 40);
  float r = 0;
  Case() {
    const KnnResult twelve = knn_reference(pts, qs, 12);
    std::vector<float> d;
    for (std::size_t q = 0; q < twelve.n; ++q)
      if (twelve.counts[q] == 12) d.push_back(twelve.d2(q, 11));
    std::nth_element(d.begin(), d.begin() + d.size() / 2, d.end());
    r = std::sqrt(d[d.size() / 2]);
  }
  std::size_t n() const { return qs.size() / 3; }
};

// kNN rows of an exact method equal the reference bit for bit; block hashing's valid by the contract.
void check_knn(const Index& ix, const KnnResult& got, const KnnResult& ref, const Case& c, const std::string& what) {
  if (ix.exact()) require_identical(got, ref, what);
  else check_contract(got, c.pts.data(), c.pts.size() / 3, c.qs.data(), knn_params(ref.k));
}

TEST_CASE("pipeline: kNN and radius, every method: dispatches split by the batch bound equal one dispatch and brute force") {
  const Case c;
  const KnnResult knn_ref = knn_reference(c.pts, c.qs, 10);
  const RadiusResult radius_ref = radius_reference(c.pts, c.qs, c.r);
  for (const auto& m : method_names()) {
    INFO("method " << m);
    auto ix = make_index(m, runtime(), c.pts.data(), c.pts.size() / 3);
    SearchParams one = knn_params(10), split = knn_params(10);
    split.max_batch = 13;  // many dispatches of one chunk, the last one short
    KnnResult a, b;
    const QueryStats sa = ix->query(c.qs.data(), c.n(), one, a);
    const QueryStats sb = ix->query(c.qs.data(), c.n(), split, b);
    require_identical(b, a, m + ": kNN split by max_batch");
    check_knn(*ix, a, knn_ref, c, m + ": kNN vs brute force");
    RadiusParams rone, rsplit;
    rsplit.max_batch = 13;
    rsplit.max_batch_results = 40;  // fill groups bounded by the results they hold
    RadiusResult ra, rb;
    const QueryStats ta = ix->radius_search(c.qs.data(), c.n(), c.r, rone, ra);
    const QueryStats tb = ix->radius_search(c.qs.data(), c.n(), c.r, rsplit, rb);
    require_same_slices(rb, ra, m + ": radius split by max_batch and max_batch_results");
    if (ix->exact()) require_same_slices(ra, radius_ref, m + ": radius vs brute force");
    if (method_info(m).on_device) {  // the stats count the dispatches the bound made
      CHECK(sb.batches > sa.batches);
      CHECK(tb.batches > ta.batches);
    }
    CHECK(sb.n_queries == c.n());
    CHECK(tb.n_queries == c.n());
  }
}

TEST_CASE("pipeline: a batch past the driver's launch limit is split below it (Quirks::max_launch_items) and equals brute force") {
  const Quirks& q = runtime()->quirks();
  if (q.max_launch_items == 0) return;  // no limit on this device: nothing to split
  // 70,000 queries: one launch past PoCL's 65535 items; the split keeps every launch below it in
  // whole groups, so the variant the warm-up compiled is the one that runs.
  const auto pts = datasets::uniform(2000, 71);
  const auto qs = datasets::uniform(70000, 72);
  const std::size_t n = qs.size() / 3;
  const std::size_t local = q.default_local_size;
  const std::size_t per = (q.max_launch_items - 1) / local * local;
  REQUIRE(per < q.max_launch_items);
  const KnnResult ref = knn_reference(pts, qs, 4);
  for (const char* m : {"blockhash", "kdtree", "bruteforce"}) {
    INFO("method " << m);
    auto ix = make_index(m, runtime(), pts.data(), pts.size() / 3);
    KnnResult got;
    const QueryStats st = ix->query(qs.data(), n, knn_params(4), got);
    require_identical(got, ref, std::string(m) + ": kNN past the launch limit");
    CHECK(st.batches == (n + per - 1) / per);
    SearchParams wish = knn_params(4);
    wish.max_batch = 1u << 30;  // a caller's bound above the limit does not lift it
    CHECK(ix->query(qs.data(), n, wish, got).batches == (n + per - 1) / per);
    RadiusResult rr;
    const QueryStats rs = ix->radius_search(qs.data(), n, 0.02f, RadiusParams{}, rr);
    CHECK(rs.batches >= (n + per - 1) / per);
  }
}

TEST_CASE("pipeline: the helper kernels past the driver's launch limit (scale copies, the density estimate) run in launches below it") {
  // detail::launch_1d_split: each launch's first item is a kernel argument; an item past the
  // first launch that read it wrong would leave its value unscaled (or its estimate unwritten).
  const Quirks& q = runtime()->quirks();
  if (q.max_launch_items == 0) return;  // no limit on this device: one launch each
  // Extreme scales through the buffer-level call: 30,000 queries (90,000 coordinates scaled in a
  // copy) at k = 4 (120,000 distances scaled back): two launches of each scale kernel.
  const auto tiny = datasets::uniform(3000, 81, 0.0f, 1e-30f);
  const auto tiny_q = datasets::uniform(30000, 82, 0.0f, 1e-30f);
  for (const char* m : {"blockhash", "bruteforce"}) {
    INFO("method " << m);
    auto ix = make_index(m, runtime(), tiny.data(), tiny.size() / 3);
    KnnResult host;
    ix->query(tiny_q.data(), tiny_q.size() / 3, knn_params(4), host);
    require_identical(buffer_query(*ix, tiny_q, knn_params(4)), host, std::string(m) + ": extreme scale, buffer call");
  }
  // The density estimate of 70,000 queries in one chunk (its kernel in two launches) equals the
  // estimate in chunks of 5,000 and with the default chunk, bit for bit.
  const auto pts = datasets::uniform(2000, 83);
  const auto qs = datasets::uniform(70000, 84);
  const std::size_t n = qs.size() / 3;
  std::vector<float> normals(3 * n), power(pts.size(), 1.0f), direction(pts.size());
  for (std::size_t i = 0; i < n; ++i) normals[3 * i + 2] = 1.0f;
  for (std::size_t i = 0; i < pts.size() / 3; ++i) {
    direction[3 * i + 2] = 1.0f;  // facing the queries (normal +z)
    power[3 * i] = 1.0f + float(i % 7);
  }
  auto ix = make_index("kdtree", runtime(), pts.data(), pts.size() / 3);
  const DensityWeights w(*ix, power.data(), direction.data(), pts.size() / 3);
  DensityParams dp;
  dp.search = knn_params(8);
  DensityResult whole, parts, dflt;
  dp.chunk = n;
  density_estimate(*ix, w, qs.data(), normals.data(), n, dp, whole);
  dp.chunk = 5000;
  density_estimate(*ix, w, qs.data(), normals.data(), n, dp, parts);
  dp.chunk = 0;
  density_estimate(*ix, w, qs.data(), normals.data(), n, dp, dflt);
  REQUIRE(whole.estimate.size() == 3 * n);
  CHECK(whole.estimate == parts.estimate);
  CHECK(whole.radius2 == parts.radius2);
  CHECK(dflt.estimate == parts.estimate);
  std::size_t lit = 0;
  for (std::size_t i = 0; i < n; ++i) lit += whole.radius2[i] > 0 && whole.estimate[3 * i] > 0;
  CHECK(lit == n);  // every query's disc found points facing it (the last launch's too)
}

TEST_CASE("pipeline: kNN and radius, every method: the Hilbert dispatch order does not change answers") {
  Case c;
  c.qs.insert(c.qs.end(), {NAN, 0.5f, 0.5f, 0.25f, INFINITY, 0.5f});  // non-finite queries: empty rows
  for (const auto& m : method_names()) {
    INFO("method " << m);
    auto ix = make_index(m, runtime(), c.pts.data(), c.pts.size() / 3);
    SearchParams given = knn_params(8), sorted = knn_params(8);
    given.sort_queries = 0;
    sorted.sort_queries = 1;
    given.count_examined = sorted.count_examined = ix->counts_examined();
    KnnResult a, b;
    const QueryStats sa = ix->query(c.qs.data(), c.n(), given, a);
    const QueryStats sb = ix->query(c.qs.data(), c.n(), sorted, b);
    require_identical(b, a, m + ": kNN sorted dispatch");
    CHECK(b.examined == a.examined);
    CHECK(sa.nonfinite_queries == 2);
    CHECK(sb.nonfinite_queries == 2);
    RadiusParams rgiven, rsorted;
    rgiven.sort_queries = 0;
    rsorted.sort_queries = 1;
    rgiven.count_examined = rsorted.count_examined = ix->counts_examined();
    RadiusResult ra, rb;
    const QueryStats ta = ix->radius_search(c.qs.data(), c.n(), c.r, rgiven, ra);
    const QueryStats tb = ix->radius_search(c.qs.data(), c.n(), c.r, rsorted, rb);
    require_same_slices(rb, ra, m + ": radius sorted dispatch");
    CHECK(rb.examined == ra.examined);
    CHECK(ta.nonfinite_queries == 2);
    CHECK(tb.nonfinite_queries == 2);
    const std::size_t last = c.n() - 1;
    CHECK(ra.count(last) == 0);
    CHECK(a.counts[last] == 0);
  }
}

TEST_CASE("pipeline: buffers kept from call to call: calls of both kinds and growing sizes equal brute force") {
  const Case c;
  const std::size_t n = c.n();
  for (const auto& m : exact_method_names()) {
    INFO("method " << m);
    auto ix = make_index(m, runtime(), c.pts.data(), c.pts.size() / 3);
    // Small, large, small again, k changing, radius between: every call on the buffers the last left.
    for (std::size_t count : {std::size_t(5), n, std::size_t(1), n}) {
      const std::vector<float> qs(c.qs.begin(), c.qs.begin() + 3 * count);
      for (int k : {3, 10}) {
        KnnResult got;
        ix->query(qs.data(), count, knn_params(k), got);
        require_identical(got, knn_reference(c.pts, qs, k), m + ": kNN k=" + std::to_string(k) + " n=" + std::to_string(count));
      }
      RadiusResult got;
      ix->radius_search(qs.data(), count, c.r, RadiusParams{}, got);
      require_same_slices(got, radius_reference(c.pts, qs, c.r), m + ": radius n=" + std::to_string(count));
    }
  }
}

TEST_CASE("pipeline: kNN and radius, exact methods: suspect rows re-answered in double, sorted or not") {
  // Points at 1e-25 apart around 1: float distances below 2^-120 are suspect for both kinds.
  std::vector<float> pts, qs;
  for (int i = 0; i < 200; ++i)
    for (float base : {1.0f, 3.0f}) pts.insert(pts.end(), {base + i * 1e-3f, base, base});
  for (int i = 0; i < 50; ++i) qs.insert(qs.end(), {1.0f + i * 2e-3f, 1.0f, 1.0f});
  const SearchParams p = knn_params(4);
  const KnnResult ref = reference::knn_double(pts.data(), pts.size() / 3, qs.data(), qs.size() / 3, p);
  for (const auto& m : exact_method_names()) {
    INFO("method " << m);
    auto ix = make_index(m, runtime(), pts.data(), pts.size() / 3);
    for (int sort : {0, 1}) {
      SearchParams s = p;
      s.sort_queries = sort;
      KnnResult got;
      ix->query(qs.data(), qs.size() / 3, s, got);
      require_identical(got, ref, m + ": kNN, sort " + std::to_string(sort));
      RadiusParams rp;
      rp.sort_queries = sort;
      RadiusResult tiny;  // a radius whose square is below 2^-120: every slice re-answered in double
      ix->radius_search(qs.data(), qs.size() / 3, 1e-19f, rp, tiny);
      for (std::size_t q = 0; q < tiny.n; ++q) {
        REQUIRE(tiny.count(q) == 1);  // the query itself is a point; its neighbours lie 1e-3 away
        CHECK(tiny.dist2[tiny.offsets[q]] == 0.0f);
      }
    }
  }
}

// query_into's rows into memory filled with a pattern first (the call must write every entry and
// read none), against query's rows: sorted and not, split into many dispatches (the kernel's
// result rows offset within a chunk), examined counts, and points at 2^100 (the distances scaled
// back where the kernel wrote them).
void check_query_into(const Index& ix, const std::vector<float>& qs, const SearchParams& p, const std::string& what) {
  const std::size_t n = qs.size() / 3, nk = n * static_cast<std::size_t>(p.k);
  KnnResult want;
  ix.query(qs.data(), n, p, want);
  std::vector<std::int32_t> ids(nk, 0x5a5a5a5a), counts(n, -7), examined(n, -7);
  std::vector<float> d2(nk, -1.0f);
  ix.query_into(qs.data(), n, p, {ids.data(), d2.data(), counts.data(), p.count_examined ? examined.data() : nullptr});
  REQUIRE_MESSAGE(ids == want.ids, what);
  REQUIRE_MESSAGE(counts == want.counts, what);
  for (std::size_t i = 0; i < nk; ++i)
    REQUIRE_MESSAGE(std::memcmp(&d2[i], &want.dist2[i], 4) == 0, what << " entry " << i);
  if (p.count_examined) REQUIRE_MESSAGE(examined == want.examined, what);
}

TEST_CASE("pipeline: query_into writes query's rows into caller memory, sorted, split, scaled, every method") {
  Case c;
  c.qs.insert(c.qs.end(), {NAN, 0.5f, 0.5f});  // a non-finite query: its empty row written too
  std::vector<float> big_pts = c.pts, big_qs = c.qs;
  for (float& v : big_pts) v = std::ldexp(v, 100);
  for (float& v : big_qs) v = std::ldexp(v, 100);
  for (const auto& m : method_names()) {
    INFO("method " << m);
    auto ix = make_index(m, runtime(), c.pts.data(), c.pts.size() / 3);
    auto big = make_index(m, runtime(), big_pts.data(), big_pts.size() / 3);
    for (int sort : {0, 1})
      for (std::size_t batch : {std::size_t(0), std::size_t(13)}) {
        SearchParams p = knn_params(7);
        p.sort_queries = sort;
        p.max_batch = batch;
        p.count_examined = ix->counts_examined();
        const std::string what = m + ": sort " + std::to_string(sort) + ", max_batch " + std::to_string(batch);
        check_query_into(*ix, c.qs, p, what);
        check_query_into(*big, big_qs, p, what + ", points at 2^100");
      }
    SearchParams p = knn_params(3);
    CHECK_THROWS_WITH_AS(ix->query_into(c.qs.data(), c.n(), p, {}), doctest::Contains("null output array"), Error);
  }
}

TEST_CASE("pipeline: a host method's buffer-level call answers as its host-array call") {
  const Case c;
  for (const auto& m : method_names()) {
    auto ix = make_index(m, runtime(), c.pts.data(), c.pts.size() / 3);
    if (method_info(m).on_device) continue;
    INFO("method " << m);
    KnnResult direct;
    ix->query(c.qs.data(), c.n(), knn_params(10), direct);
    require_identical(buffer_query(*ix, c.qs, knn_params(10)), direct, m + ": enqueue_query");
  }
}

}  // namespace
}  // namespace bhcl::test
