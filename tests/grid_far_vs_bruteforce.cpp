// Block hashing's grid where the query is not among the points (the occupancy pyramid's walk,
// kernels/grid_search.h): the exact default equal to brute force bit for bit on far queries, two
// clusters queried between them, a line, a plane, a shell queried from inside, both directories,
// after inserts and removes; kNN at every list form and radius; the kernel equal to its host
// reference with the walk from the first ring, after the default rings, and never (rings alone).
#include <cmath>
#include <random>

#include "test_util.hpp"

using namespace bhcl;

namespace {

struct FarCase {
  std::string name;
  std::vector<float> pts, qs;
};

std::vector<FarCase> far_cases() {
  std::vector<FarCase> cs;
  std::mt19937_64 rng(21);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::normal_distribution<float> g(0.0f, 0.01f);
  auto uq = [&](std::size_t n, float lo, float hi) {
    std::uniform_real_distribution<float> v(lo, hi);
    std::vector<float> q(3 * n);
    for (float& x : q) x = v(rng);
    return q;
  };
  {  // far queries: a unit cube of points, queries up to 20 boxes away
    FarCase c{"far queries", datasets::uniform(6000, 31), uq(300, -20.0f, 21.0f)};
    cs.push_back(std::move(c));
  }
  {  // two tight clusters 1 apart, queried between them
    FarCase c{"two clusters", {}, {}};
    for (int i = 0; i < 6000; ++i) c.pts.insert(c.pts.end(), {g(rng) + float(i % 2), g(rng), g(rng)});
    for (int i = 0; i < 300; ++i) c.qs.insert(c.qs.end(), {0.1f + 0.8f * u(rng), 0.1f * u(rng) - 0.05f, 0.1f * u(rng) - 0.05f});
    cs.push_back(std::move(c));
  }
  {  // points on a line (a grid one cell thick), queries off it
    FarCase c{"line", {}, {}};
    for (int i = 0; i < 20000; ++i) c.pts.insert(c.pts.end(), {u(rng), 0.0f, 0.0f});
    for (int i = 0; i < 300; ++i) c.qs.insert(c.qs.end(), {1.4f * u(rng) - 0.2f, 0.5f * u(rng), 0.5f * u(rng) - 0.25f});
    cs.push_back(std::move(c));
  }
  {  // points on a plane, queries above and below it
    FarCase c{"plane", {}, {}};
    for (int i = 0; i < 20000; ++i) c.pts.insert(c.pts.end(), {u(rng), u(rng), 0.0f});
    for (int i = 0; i < 300; ++i) c.qs.insert(c.qs.end(), {u(rng), u(rng), u(rng) - 0.5f});
    cs.push_back(std::move(c));
  }
  {  // a spherical shell queried from inside (and a few at its centre: many ties)
    FarCase c{"shell from inside", {}, {}};
    for (int i = 0; i < 12000; ++i) {
      float x = g(rng), y = g(rng), z = g(rng);
      const float n = std::sqrt(x * x + y * y + z * z);
      c.pts.insert(c.pts.end(), {x / n, y / n, z / n});
    }
    for (int i = 0; i < 300; ++i) c.qs.insert(c.qs.end(), {0.6f * u(rng) - 0.3f, 0.6f * u(rng) - 0.3f, 0.6f * u(rng) - 0.3f});
    for (int i = 0; i < 4; ++i) c.qs.insert(c.qs.end(), {0.0f, 0.0f, 0.0f});
    cs.push_back(std::move(c));
  }
  return cs;
}

SearchParams exact(int k, const std::string& defines = "") {
  SearchParams p = test::knn_params(k);
  p.A = INFINITY;
  p.kernel_defines = defines;
  return p;
}

void knn_equals_bruteforce(const BlockHashIndex& index, const std::vector<float>& pts, const std::vector<float>& qs,
                           const std::string& what) {
  const std::size_t N = pts.size() / 3, n = qs.size() / 3;
  for (int k : {1, 10, 17, 50, 100}) {  // one register, four, the scalar list past 64
    CAPTURE(k);
    const SearchParams p = exact(k);
    KnnResult got;
    index.query(qs.data(), n, p, got);
    const KnnResult ref = reference::knn_float(pts.data(), N, qs.data(), n, p);
    test::require_identical(got, ref, what + ", k = " + std::to_string(k));
  }
}

}  // namespace

TEST_CASE("grid_far_vs_bruteforce: the exact default equals brute force wherever the query is") {
  for (const FarCase& c : far_cases())
    for (int directory : {0, 1}) {  // direct and two-level directories
      CAPTURE(c.name);
      CAPTURE(directory);
      BlockHashBuildParams bp;
      bp.grid_directory = directory;
      auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), c.pts.size() / 3, bp);
      REQUIRE(index->info().grid);
      knn_equals_bruteforce(*index, c.pts, c.qs, c.name);
    }
}

TEST_CASE("grid_far_vs_reference: kernel == host reference, walk from ring 0, after the rings, or never") {
  for (const FarCase& c : far_cases()) {
    auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), c.pts.size() / 3);
    const std::size_t N = c.pts.size() / 3, n = c.qs.size() / 3;
    for (const char* d : {"-DBHCL_GRID_FINE_RINGS=0", "-DBHCL_GRID_FINE_RINGS=1", "-DBHCL_GRID_FINE_RINGS=0xffffffff",
                          "-DBHCL_GRID_VTOPK=0 -DBHCL_GRID_PREFETCH=0 -DBHCL_GRID_ROWCAP=0",
                          // the walk depth-first, and best-first with a queue that overflows at once or soon
                          // (the last with every run of the walk measured one point at a time by the
                          // register list, BHCL_GRID_SHORT_RUN: the same distances, so the same rows;
                          // the default takes both ways)
                          "-DBHCL_GRID_WALKCAP=0", "-DBHCL_GRID_WALKCAP=1",
                          "-DBHCL_GRID_WALKCAP=3 -DBHCL_GRID_SHORT_RUN=1024"})
      for (int k : {1, 16, 17, 65})
        for (float A : {2.0f, INFINITY}) {
          CAPTURE(c.name);
          CAPTURE(d);
          CAPTURE(k);
          CAPTURE(A);
          SearchParams p = exact(k, d);
          p.A = A;
          SearchParams pe = p;
          pe.count_examined = true;
          const KnnResult r = index->query(c.qs, pe);
          std::vector<std::int32_t> ex_ref;
          const KnnResult ref = index->reference_query(c.qs.data(), n, p, &ex_ref);
          test::require_identical(r, ref, c.name + " " + d);
          REQUIRE(r.examined == ex_ref);
          if (std::isinf(A))
            test::require_identical(r, reference::knn_float(c.pts.data(), N, c.qs.data(), n, p), c.name + " exact");
        }
  }
}

TEST_CASE("grid_far_best_first: the best-first walk examines fewer points between two clusters") {
  // Its purpose: the depth-first walk's fixed child order scans the far cluster first for about
  // half the queries between them; best-first reaches the near one first and its bound prunes
  // the other. Same rows either way (checked above).
  const FarCase c = far_cases()[1];
  REQUIRE(c.name == "two clusters");
  auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), c.pts.size() / 3);
  for (int k : {1, 10}) {
    CAPTURE(k);
    long long examined[2] = {0, 0};
    for (int best_first : {0, 1}) {
      SearchParams p = exact(k, best_first ? "-DBHCL_GRID_WALKCAP=32" : "-DBHCL_GRID_WALKCAP=0");
      p.count_examined = true;
      const KnnResult r = index->query(c.qs, p);
      for (std::int32_t e : r.examined) examined[best_first] += e;
    }
    MESSAGE("k = " << k << ": points examined depth-first " << examined[0] << ", best-first " << examined[1]);
    CHECK(examined[1] < examined[0]);
  }
}

TEST_CASE("grid_far_vs_bruteforce: the best-first walk without its descent (the experiment's other arm) exact") {
  // BHCL_GRID_WALK_DESCEND=0 queues every child instead of following the nearest; the host
  // reference walks the default, so only the exact rows can be compared, against brute force.
  for (const FarCase& c : far_cases()) {
    auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), c.pts.size() / 3);
    for (int k : {1, 17}) {
      CAPTURE(c.name);
      CAPTURE(k);
      const SearchParams p = exact(k, "-DBHCL_GRID_WALK_DESCEND=0 -DBHCL_GRID_WALKCAP=3");
      test::require_identical(index->query(c.qs, p),
                              reference::knn_float(c.pts.data(), c.pts.size() / 3, c.qs.data(), c.qs.size() / 3, p),
                              c.name + " no descent");
    }
  }
}

TEST_CASE("grid_far_radius_vs_bruteforce: radius search exact where the query is far") {
  for (const FarCase& c : far_cases()) {
    CAPTURE(c.name);
    auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), c.pts.size() / 3);
    for (float r : {0.05f, 0.3f, 1.5f}) {
      CAPTURE(r);
      RadiusResult got;
      index->radius_search(c.qs.data(), c.qs.size() / 3, r, RadiusParams{}, got);
      test::require_same_slices(got, test::reference_radius_slices(c.pts, c.qs, {r * r}), c.name);
    }
  }
}

TEST_CASE("grid_far_after_updates: exact after inserts and removes, queried far and between") {
  // Two clusters; a third inserted far from both (new occupied cells the pyramid must show), then
  // part of the first removed (cells emptied, holes) and compacted.
  std::mt19937_64 rng(5);
  std::normal_distribution<float> g(0.0f, 0.01f);
  std::uniform_real_distribution<float> u(-1.0f, 3.0f);
  std::vector<float> pts;
  for (int i = 0; i < 8000; ++i) pts.insert(pts.end(), {g(rng) + float(i % 2), g(rng), g(rng)});
  std::vector<float> qs;
  for (int i = 0; i < 300; ++i) qs.insert(qs.end(), {u(rng), u(rng) * 0.3f, u(rng) * 0.3f});
  auto index = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3);
  // Inside the box (a merge into the cells) and outside it (a rebuild).
  std::vector<float> add;
  for (int i = 0; i < 2000; ++i) add.insert(add.end(), {g(rng) + 0.5f, g(rng) + 0.005f, g(rng)});
  index->insert(add.data(), add.size() / 3);
  pts.insert(pts.end(), add.begin(), add.end());
  knn_equals_bruteforce(*index, pts, qs, "after an insert inside the box");
  // Removed: the first cluster's first 3000; their brute-force stand-ins are moved out of reach.
  std::vector<std::int32_t> gone;
  for (std::int32_t i = 0; i < 6000; i += 2) gone.push_back(i);
  index->remove(gone.data(), gone.size());
  for (std::int32_t i : gone) pts[3 * i] = pts[3 * i + 1] = pts[3 * i + 2] = 1e6f;
  knn_equals_bruteforce(*index, pts, qs, "after a remove");
  std::vector<float> off;
  for (int i = 0; i < 500; ++i) off.insert(off.end(), {g(rng) + 4.0f, g(rng) + 2.0f, g(rng)});
  index->insert(off.data(), off.size() / 3);
  pts.insert(pts.end(), off.begin(), off.end());
  knn_equals_bruteforce(*index, pts, qs, "after an insert off the box");
}

TEST_CASE("grid_far_batches_vs_bruteforce: batches all near, all far, mixed and empty, every home-skip arm") {
  // The walk's entry (BHCL_GRID_HOME_SKIP: after ring 0, before the rings, never) changes only
  // where the search goes, never its rows: each arm
  // bit-exact against brute force on a batch of queries among the points, one far from them
  // (home 4^3 blocks empty), both interleaved, and an empty batch.
  const std::vector<float> pts = datasets::uniform(20000, 5);
  std::mt19937_64 rng(36);
  std::uniform_real_distribution<float> near(0.0f, 1.0f), far(2.0f, 6.0f);
  std::vector<float> near_q, far_q, mixed_q;
  for (int i = 0; i < 400; ++i) {
    const float a[3] = {near(rng), near(rng), near(rng)};
    const float b[3] = {far(rng), -far(rng), near(rng)};
    near_q.insert(near_q.end(), a, a + 3);
    far_q.insert(far_q.end(), b, b + 3);
    mixed_q.insert(mixed_q.end(), (i % 3 == 0) ? b : a, ((i % 3 == 0) ? b : a) + 3);
  }
  auto index = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3);
  REQUIRE(index->info().grid);
  const std::size_t N = pts.size() / 3;
  for (const char* d : {"", "-DBHCL_GRID_HOME_SKIP=1", "-DBHCL_GRID_HOME_SKIP=0"})
    for (int k : {1, 10, 50}) {
      CAPTURE(d);
      CAPTURE(k);
      const SearchParams p = exact(k, d);
      for (const auto* qs : {&near_q, &far_q, &mixed_q}) {
        const std::string what = std::string(qs == &near_q ? "all near" : qs == &far_q ? "all far" : "mixed") + " " + d;
        test::require_identical(index->query(*qs, p), reference::knn_float(pts.data(), N, qs->data(), qs->size() / 3, p),
                                what);
      }
      KnnResult none;
      index->query(near_q.data(), 0, p, none);
      CHECK(none.counts.empty());
      CHECK(none.ids.empty());
    }
  // The default's examined counts equal its host reference's (the same entry into the walk).
  SearchParams pe = exact(10);
  pe.count_examined = true;
  std::vector<std::int32_t> ex_ref;
  const KnnResult r = index->query(mixed_q, pe);
  const KnnResult ref = index->reference_query(mixed_q.data(), mixed_q.size() / 3, exact(10), &ex_ref);
  test::require_identical(r, ref, "mixed, kernel vs reference");
  CHECK(r.examined == ex_ref);
}

namespace {

// Rolling ground over the unit square (hills 0.2 high, many cells: a LiDAR terrain), rough by
// 0.01; the queries above it up to half its width, and every eighth among its points.
float ground_height(float x, float y) { return 0.1f * (std::sin(6.0f * x) + std::cos(5.0f * y)); }
FarCase ground_case() {
  FarCase c{"ground from above", {}, {}};
  std::mt19937_64 rng(44);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  for (int i = 0; i < 30000; ++i) {
    const float x = u(rng), y = u(rng);
    c.pts.insert(c.pts.end(), {x, y, ground_height(x, y) + 0.01f * u(rng)});
  }
  for (int i = 0; i < 400; ++i) {
    const float x = u(rng), y = u(rng);
    c.qs.insert(c.qs.end(), {x, y, ground_height(x, y) + (i % 8 == 0 ? 0.01f : 0.5f) * u(rng)});
  }
  return c;
}

long long examined_sum(const BlockHashIndex& index, const std::vector<float>& qs, SearchParams p) {
  p.count_examined = true;
  long long s = 0;
  for (std::int32_t e : index.query(qs, p).examined) s += e;
  return s;
}

}  // namespace

TEST_CASE("grid_far_node_boxes_vs_bruteforce: the nodes' point boxes keep a surface queried from above exact") {
  // The walk clips each pyramid node's slabs to its points' box (BHCL_GRID_TBOX): exact against
  // brute force with and without it, at k = 1, 10, 50 and on every walk form, the kernel equal to
  // its host reference, and fewer points examined with it at k = 1 (what it is for).
  const FarCase c = ground_case();
  const std::size_t N = c.pts.size() / 3, n = c.qs.size() / 3;
  for (int directory : {0, 1}) {
    CAPTURE(directory);
    BlockHashBuildParams bp;
    bp.grid_directory = directory;
    auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), N, bp);
    REQUIRE(index->info().grid);
    for (const char* d : {"", "-DBHCL_GRID_TBOX=0", "-DBHCL_GRID_WALKCAP=0", "-DBHCL_GRID_FINE_RINGS=0"})
      for (int k : {1, 10, 50}) {
        CAPTURE(d);
        CAPTURE(k);
        const SearchParams p = exact(k, d);
        test::require_identical(index->query(c.qs, p), reference::knn_float(c.pts.data(), N, c.qs.data(), n, p),
                                std::string("ground ") + d);
      }
    SearchParams pe = exact(1);
    pe.count_examined = true;
    std::vector<std::int32_t> ex_ref;
    const KnnResult r = index->query(c.qs, pe);
    index->reference_query(c.qs.data(), n, exact(1), &ex_ref);
    CHECK(r.examined == ex_ref);
    const long long with = examined_sum(*index, c.qs, exact(1)), without = examined_sum(*index, c.qs, exact(1, "-DBHCL_GRID_TBOX=0"));
    MESSAGE("k = 1 over the ground: points examined with the node boxes " << with << ", without " << without);
    CHECK(with < without);
  }
}

TEST_CASE("grid_far_node_boxes_after_updates: inserts widen the nodes' boxes, removes keep them right") {
  // Points inserted 0.02 above the ground's roughness (inside its level-2 nodes, outside their old
  // boxes) become the nearest of the queries above them: a box left as built would prune them.
  FarCase c = ground_case();
  auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), c.pts.size() / 3);
  std::mt19937_64 rng(45);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::vector<float> add;
  for (int i = 0; i < 300; ++i) {
    const float x = u(rng), y = u(rng);
    add.insert(add.end(), {x, y, ground_height(x, y) + 0.03f});
  }
  const std::int32_t first = index->insert(add.data(), add.size() / 3);
  REQUIRE(first == 30000);  // ids follow the ground's (the brute force's rows)
  c.pts.insert(c.pts.end(), add.begin(), add.end());
  for (int k : {1, 10, 50}) {
    CAPTURE(k);
    test::require_identical(index->query(c.qs, exact(k)),
                            reference::knn_float(c.pts.data(), c.pts.size() / 3, c.qs.data(), c.qs.size() / 3, exact(k)),
                            "ground after an insert above it");
  }
  // The inserted points removed again (ids after the ground's), and a third of the ground.
  std::vector<std::int32_t> gone;
  for (std::int32_t i = 0; i < 300; ++i) gone.push_back(first + i);
  for (std::int32_t i = 0; i < 30000; i += 3) gone.push_back(i);
  index->remove(gone.data(), gone.size());
  for (std::int32_t i : gone) c.pts[3 * i] = c.pts[3 * i + 1] = c.pts[3 * i + 2] = 1e6f;
  for (int k : {1, 10, 50}) {
    CAPTURE(k);
    test::require_identical(index->query(c.qs, exact(k)),
                            reference::knn_float(c.pts.data(), c.pts.size() / 3, c.qs.data(), c.qs.size() / 3, exact(k)),
                            "ground after a remove");
  }
}
