// Radius search (Index::radius_search) for every method of the registry: exact methods against a
// float reference (the contract's distance and boundary rule) checked in double precision, block
// hashing as a subset with its recall, the layout (offsets, sorted slices), the cap, batch
// splitting, sorted dispatch, extreme scales and bad input.
#include <nlohmann/json.hpp>

#include "test_util.hpp"

namespace bhcl::test {
namespace {

// The exact answer under the contract: every point with dist2_float <= r2, sorted (d, id).
RadiusResult reference_radius(const std::vector<float>& pts, const std::vector<float>& qs, float r2) {
  return reference_radius_slices(pts, qs, {r2});
}

// The layout's invariants and, per entry, the contract's distance within r2; returns the count.
void check_layout(const RadiusResult& r, const std::vector<float>& pts, const std::vector<float>& qs,
                  float r2) {
  REQUIRE(r.offsets.size() == r.n + 1);
  REQUIRE(r.offsets[0] == 0);
  REQUIRE(static_cast<std::size_t>(r.offsets.back()) == r.ids.size());
  REQUIRE(r.ids.size() == r.dist2.size());
  const std::size_t N = pts.size() / 3;
  for (std::size_t q = 0; q < r.n; ++q) {
    REQUIRE(r.offsets[q] <= r.offsets[q + 1]);
    std::set<std::int32_t> seen;
    for (auto j = r.offsets[q]; j < r.offsets[q + 1]; ++j) {
      const std::int32_t id = r.ids[j];
      REQUIRE(id >= 0);
      REQUIRE(static_cast<std::size_t>(id) < N);
      REQUIRE(seen.insert(id).second);
      REQUIRE(r.dist2[j] == reference::dist2_float(&pts[3 * id], &qs[3 * q]));
      REQUIRE(r.dist2[j] <= r2);
      if (j > r.offsets[q])
        REQUIRE(std::make_pair(r.dist2[j - 1], r.ids[j - 1]) < std::make_pair(r.dist2[j], r.ids[j]));
    }
  }
}

// The double-precision check of the boundary rule: a point clearly inside r (double distance
// below r2 by more than float rounding) is in the exact answer, a point clearly outside is not.
void check_boundary_in_double(const RadiusResult& ref, const std::vector<float>& pts,
                              const std::vector<float>& qs, float r2) {
  const std::size_t N = pts.size() / 3;
  for (std::size_t q = 0; q < ref.n; ++q) {
    std::set<std::int32_t> in(ref.ids.begin() + ref.offsets[q], ref.ids.begin() + ref.offsets[q + 1]);
    const float* qp = &qs[3 * q];
    if (!(std::isfinite(qp[0]) && std::isfinite(qp[1]) && std::isfinite(qp[2]))) {
      REQUIRE(in.empty());
      continue;
    }
    for (std::size_t i = 0; i < N; ++i) {
      double d = 0;
      for (int c = 0; c < 3; ++c) {
        double t = double(qp[c]) - double(pts[3 * i + c]);
        d += t * t;
      }
      const double tol = 1e-6 * std::max(d, double(r2)) + 1e-37;
      if (d < double(r2) - tol) REQUIRE(in.count(static_cast<std::int32_t>(i)) == 1);
      if (d > double(r2) + tol) REQUIRE(in.count(static_cast<std::int32_t>(i)) == 0);
    }
  }
}

// A radius holding about `target` points per query on average (from the 1st query's neighbours).
float radius_for(const std::vector<float>& pts, const std::vector<float>& qs, std::size_t target) {
  std::vector<float> d;
  const std::size_t N = pts.size() / 3;
  for (std::size_t q = 0; q < std::min<std::size_t>(qs.size() / 3, 20); ++q) {
    std::vector<float> row;
    for (std::size_t i = 0; i < N; ++i) row.push_back(reference::dist2_float(&pts[3 * i], &qs[3 * q]));
    std::size_t t = std::min(target, N - 1);
    std::nth_element(row.begin(), row.begin() + t, row.end());
    d.push_back(row[t]);
  }
  std::sort(d.begin(), d.end());
  return std::sqrt(d[d.size() / 2]);
}

// A case: the points, their queries (queries_for's `each` of every kind, seeded) and a radius
// holding about `target` points a query.
struct RadiusCase {
  std::vector<float> pts, qs;
  float r;
};
RadiusCase radius_case(std::vector<float> pts, std::uint64_t seed, std::size_t each, std::size_t target) {
  RadiusCase c{std::move(pts), {}, 0.0f};
  c.qs = queries_for(c.pts, seed, each);
  c.r = radius_for(c.pts, c.qs, target);
  return c;
}

// method's index over pts (the registry's build, as bhcl makes it).
std::unique_ptr<Index> index_over(const std::string& method, const std::vector<float>& pts) {
  return make_index(method, runtime(), pts.data(), pts.size() / 3);
}

}  // namespace

TEST_CASE("radius: exact methods equal the float reference, checked in double (every set)") {
  for (const auto& s : exact_point_sets()) {
    const float r = radius_for(s.points, s.queries, 20);
    const RadiusResult ref = reference_radius(s.points, s.queries, r * r);
    check_boundary_in_double(ref, s.points, s.queries, r * r);
    for (const auto& m : exact_method_names()) {
      auto index = index_over(m, s.points);
      RadiusResult got;
      index->radius_search(s.queries.data(), s.queries.size() / 3, r, {}, got);
      require_same_slices(got, ref, m + " on " + s.name + ", r = " + std::to_string(r));
      REQUIRE(got.truncated_queries == 0);
      // r = 0: exactly the coincident points.
      RadiusResult zero;
      index->radius_search(s.queries.data(), s.queries.size() / 3, 0.0f, {}, zero);
      require_same_slices(zero, reference_radius(s.points, s.queries, 0.0f), m + " on " + s.name + ", r = 0");
    }
  }
}

TEST_CASE("radius: block hashing, every layout: the grid exact, the block layouts a subset within r") {
  const auto [pts, qs, r] = radius_case(datasets::uniform(20000, 7), 11, 100, 30);
  const RadiusResult ref = reference_radius(pts, qs, r * r);
  // auto: the grid (exact); tables: auto's L tables (grid = 0); paper.
  for (const std::string preset : {"auto", "tables", "paper"}) {
    MethodOptions o;
    o.set("preset", preset == "tables" ? "auto" : preset);
    if (preset == "tables") o.set("grid", "0");
    auto index = make_index("blockhash", runtime(), pts.data(), pts.size() / 3, o);
    RadiusParams p;
    p.count_examined = true;
    RadiusResult got;
    index->radius_search(qs.data(), qs.size() / 3, r, p, got);
    check_layout(got, pts, qs, r * r);
    REQUIRE(got.examined.size() == got.n);
    if (preset == "auto") require_same_slices(got, ref, "the grid's radius search against brute force");
    std::size_t hit = 0;
    for (std::size_t q = 0; q < got.n; ++q) {
      std::set<std::int32_t> truth(ref.ids.begin() + ref.offsets[q], ref.ids.begin() + ref.offsets[q + 1]);
      for (auto j = got.offsets[q]; j < got.offsets[q + 1]; ++j) hit += truth.count(got.ids[j]);
      REQUIRE(got.count(q) <= ref.count(q));
    }
    const double recall = double(hit) / double(std::max<std::size_t>(1, ref.total()));
    INFO(preset << ": radius recall " << recall);
    CHECK(recall >= (preset == "paper" ? 0.4 : 0.9));  // measured: tables 0.9+, paper 0.49; the grid 1
    // A budget can only lose points, and the examined counts respect it (a block at a time).
    RadiusParams b = p;
    b.budget = 64;
    RadiusResult small;
    index->radius_search(qs.data(), qs.size() / 3, r, b, small);
    check_layout(small, pts, qs, r * r);
    REQUIRE(small.total() <= got.total());
    for (std::size_t q = 0; q < small.n; ++q) REQUIRE(small.examined[q] < 64 + 2 * 256);
  }
}

TEST_CASE("radius: every method, the cap keeps the nearest and reports truncation") {
  const auto [pts, qs, r] = radius_case(datasets::clustered(5000, 3), 5, 40, 40);
  for (const auto& m : method_names()) {
    auto index = index_over(m, pts);
    RadiusResult full, capped;
    index->radius_search(qs.data(), qs.size() / 3, r, {}, full);
    RadiusParams p;
    p.max_results = 5;
    index->radius_search(qs.data(), qs.size() / 3, r, p, capped);
    INFO(m);
    REQUIRE(capped.found == full.found);
    std::size_t truncated = 0;
    for (std::size_t q = 0; q < full.n; ++q) {
      const std::size_t c = std::min<std::size_t>(5, full.count(q));
      REQUIRE(capped.count(q) == c);
      truncated += full.count(q) > 5;
      for (std::size_t j = 0; j < c; ++j) {
        REQUIRE(capped.ids[capped.offsets[q] + j] == full.ids[full.offsets[q] + j]);
        REQUIRE(capped.dist2[capped.offsets[q] + j] == full.dist2[full.offsets[q] + j]);
      }
    }
    REQUIRE(truncated > 0);
    REQUIRE(capped.truncated_queries == truncated);
  }
}

TEST_CASE("radius: every method, results do not depend on batching, sorting or the squared form") {
  const auto [pts, qs, r] = radius_case(datasets::uniform(4000, 9), 13, 60, 25);
  for (const auto& m : method_names()) {
    auto index = index_over(m, pts);
    RadiusParams p;
    p.sort_queries = 0;
    RadiusResult a, b, c, d;
    index->radius_search(qs.data(), qs.size() / 3, r, p, a);
    RadiusParams split = p;
    split.max_batch = 7;
    split.max_batch_results = 50;  // many fill dispatches, and queries above it alone
    index->radius_search(qs.data(), qs.size() / 3, r, split, b);
    require_same_slices(b, a, m + ": split batches");
    RadiusParams sorted = p;
    sorted.sort_queries = 1;
    index->radius_search(qs.data(), qs.size() / 3, r, sorted, c);
    require_same_slices(c, a, m + ": Hilbert-sorted dispatch");
    index->radius_search_squared(qs.data(), qs.size() / 3, r * r, p, d);
    require_same_slices(d, a, m + ": squared form");
    // Unsorted slices: the same points per query; with a cap, the same nearest ones.
    for (std::size_t cap : {std::size_t(0), std::size_t(3)}) {
      RadiusParams u = p, s = p;
      u.sorted = false;
      u.max_results = s.max_results = cap;
      RadiusResult ru, rs;
      index->radius_search(qs.data(), qs.size() / 3, r, u, ru);
      index->radius_search(qs.data(), qs.size() / 3, r, s, rs);
      REQUIRE(ru.offsets == rs.offsets);
      REQUIRE(ru.found == rs.found);
      for (std::size_t q = 0; q < ru.n; ++q) {
        std::vector<std::pair<float, std::int32_t>> x, y;
        for (auto j = ru.offsets[q]; j < ru.offsets[q + 1]; ++j) x.emplace_back(ru.dist2[j], ru.ids[j]);
        for (auto j = rs.offsets[q]; j < rs.offsets[q + 1]; ++j) y.emplace_back(rs.dist2[j], rs.ids[j]);
        std::sort(x.begin(), x.end());
        INFO(m << " unsorted, cap " << cap << ", query " << q);
        REQUIRE(x == y);
      }
    }
    check_layout(a, pts, qs, r * r);
  }
}

TEST_CASE("radius: every method, degenerate input") {
  const auto pts = datasets::uniform(500, 1);
  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  for (const auto& m : method_names()) {
    INFO(m);
    auto index = index_over(m, pts);
    const std::vector<float> qs = {pts[0], pts[1], pts[2], nan, 0, 0, 0, inf, 0, pts[3], pts[4], pts[5]};
    RadiusResult r;
    QueryStats st = index->radius_search(qs.data(), 4, 0.2f, {}, r);
    REQUIRE(st.nonfinite_queries == 2);
    REQUIRE(r.count(1) == 0);
    REQUIRE(r.count(2) == 0);
    REQUIRE(r.count(0) >= 1);
    REQUIRE(r.ids[r.offsets[0]] == 0);  // itself, at distance 0
    // No queries: one offset.
    RadiusResult empty;
    index->radius_search(qs.data(), 0, 0.2f, {}, empty);
    REQUIRE(empty.offsets == std::vector<std::int64_t>{0});
    REQUIRE(empty.ids.empty());
    // A radius reaching every point: all of them, sorted.
    RadiusResult all;
    index->radius_search(qs.data(), 1, 1e30f, {}, all);
    if (index->exact()) REQUIRE(all.count(0) == pts.size() / 3);
    // Bad radii and parameters are refused with a message.
    for (float bad : {-1.0f, nan}) {
      RadiusResult x;
      CHECK_THROWS_WITH_AS(index->radius_search(qs.data(), 1, bad, {}, x),
                           doctest::Contains("radius must be >= 0"), Error);
      CHECK_THROWS_WITH_AS(index->radius_search_squared(qs.data(), 1, bad, {}, x),
                           doctest::Contains("squared radius must be >= 0"), Error);
    }
    // r = +inf (Euclidean or squared) is every point, as scipy's query_ball_point gives; block
    // hashing's default radius search is exact too (its grid layout).
    for (int squared = 0; squared < 2; ++squared) {
      RadiusResult every;
      if (squared) index->radius_search_squared(qs.data(), 1, inf, {}, every);
      else index->radius_search(qs.data(), 1, inf, {}, every);
      REQUIRE(every.count(0) == pts.size() / 3);
      REQUIRE(every.found[0] == static_cast<std::int64_t>(pts.size() / 3));
    }
    RadiusParams bad;
    bad.sort_queries = 3;
    RadiusResult x;
    CHECK_THROWS_AS(index->radius_search(qs.data(), 1, 0.1f, bad, x), Error);
    if (!index->counts_examined()) {
      RadiusParams ce;
      ce.count_examined = true;
      CHECK_THROWS_AS(index->radius_search(qs.data(), 1, 0.1f, ce, x), Error);
    }
  }
}

TEST_CASE("radius: extreme scales give the unscaled answer") {
  const auto base = datasets::uniform(2000, 4);
  const auto qs0 = queries_for(base, 8, 30);
  const float r = radius_for(base, qs0, 15);
  for (float scale : {0x1p-70f, 0x1p+70f}) {
    std::vector<float> pts(base), qs(qs0);
    for (auto& v : pts) v *= scale;
    for (auto& v : qs) v *= scale;
    for (const auto& m : exact_method_names()) {
      auto a = index_over(m, base);
      auto b = index_over(m, pts);
      RadiusResult ra, rb;
      a->radius_search(qs0.data(), qs0.size() / 3, r, {}, ra);
      b->radius_search(qs.data(), qs.size() / 3, r * scale, {}, rb);
      INFO(m << " at scale " << scale);
      REQUIRE(rb.offsets == ra.offsets);
      REQUIRE(rb.ids == ra.ids);
      for (std::size_t i = 0; i < ra.dist2.size(); ++i) REQUIRE(rb.dist2[i] == ra.dist2[i] * scale * scale);
    }
  }
}

}  // namespace bhcl::test

namespace bhcl::test {

TEST_CASE("radius: bhcl knn --radius writes the library's three arrays, and refuses misuse") {
  auto [pts, qs, P, Q] = test::cli_inputs("rad", 3000, 71, 80, 72);
  std::string O = tmp_path("rad_o.i64"), I = tmp_path("rad_i.i32"), D = tmp_path("rad_d.f32"),
              C = tmp_path("rad_c.i32"), S = tmp_path("rad_s.json");
  const float r = 0.08f;
  for (const std::string m : {"kdtree", "blockhash"}) {
    std::string out;
    int rc = run_bhcl("knn --points " + P + " --queries " + Q + " --method " + m + " --radius 0.08 --max-results 12" +
                          " --out-offsets " + O + " --out-ids " + I + " --out-dist2 " + D + " --out-counts " + C +
                          " --stats " + S + " --quiet",
                      &out);
    INFO(m << ": " << out);
    REQUIRE(rc == 0);
    auto index = index_over(m, pts);
    RadiusParams p;
    p.max_results = 12;
    RadiusResult ref;
    index->radius_search(qs.data(), qs.size() / 3, r, p, ref);
    REQUIRE(read_raw<std::int64_t>(O) == ref.offsets);
    REQUIRE(read_raw<std::int32_t>(I) == ref.ids);
    REQUIRE(read_raw<float>(D) == ref.dist2);
    auto counts = read_raw<std::int32_t>(C);
    REQUIRE(counts.size() == ref.n);
    for (std::size_t i = 0; i < ref.n; ++i) REQUIRE(std::size_t(counts[i]) == ref.count(i));
    std::ifstream s(S);
    const nlohmann::json j = nlohmann::json::parse(s);
    CHECK(j.at("radius").at("results") == ref.total());
    CHECK(j.at("radius").at("truncated_queries") == ref.truncated_queries);
  }
  const std::string base = "knn --points " + P + " --queries " + Q + " --out-ids " + I + " --out-dist2 " + D;
  for (const std::string& bad : {std::string(" --method kdtree --radius 0.1"),           // no --out-offsets
                                " --method kdtree --radius 0.1 --k 3 --out-offsets " + O,  // --k is kNN's
                                " --method kdtree --radius -1 --out-offsets " + O,
                                " --method kdtree --radius nan --out-offsets " + O,
                                " --method kdtree --radius 0.1 --budget 9 --out-offsets " + O,
                                std::string(" --method kdtree --max-results 3")}) {
    std::string out;
    INFO(bad);
    CHECK(run_bhcl(base + bad, &out) == 2);
    CHECK(out.find("usage error") != std::string::npos);
  }
}

}  // namespace bhcl::test
