// Block hashing's grid layout (the auto preset): the exact mode against brute force on every
// point set the exact methods are checked on, the kernel against its host reference bit for bit
// at every budget and both top-k forms, radius search exact, the build independent of threads,
// save/load, rebuild, and the parameters' checks.
#include <cstdio>
#include <random>
#include <fstream>

#include "blockhash/build.hpp"
#include "blockhash_cl/block_tables.hpp"
#include "blockhash_cl/grid_index.hpp"
#include "grid_test_util.hpp"
#include "test_util.hpp"

using namespace bhcl;

namespace {

SearchParams exact_params(int k, float r = INFINITY) {
  SearchParams p = test::knn_params(k);
  p.A = INFINITY;
  p.max_radius = r;
  return p;
}

void kernel_equals_reference(const BlockHashIndex& index, const std::vector<float>& qs,
                             const SearchParams& p, const std::string& what) {
  SearchParams pe = p;
  pe.count_examined = true;
  KnnResult r = index.query(qs, pe);
  std::vector<std::int32_t> ex_ref;
  KnnResult ref = index.reference_query(qs.data(), qs.size() / 3, p, &ex_ref);
  test::require_identical(r, ref, what);
  REQUIRE(r.examined == ex_ref);
}

}  // namespace

TEST_CASE("blockhash_grid_vs_bruteforce: the exact mode equals brute force on every exact set") {
  for (const test::PointSet& s : test::exact_point_sets()) {
    CAPTURE(s.name);
    auto index = BlockHashIndex::build(test::runtime(), s.points.data(), s.points.size() / 3);
    REQUIRE(index->info().grid);
    const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
    const float radius = test::cutting_radius(s);
    for (float r : {INFINITY, radius})
      for (int k : {1, 17, 100}) {  // both register-list sizes and the scalar list
        CAPTURE(k);
        CAPTURE(r);
        SearchParams p = exact_params(k, r);
        KnnResult got;
        index->query(s.queries.data(), n, p, got);
        KnnResult ref = reference::knn_float(s.points.data(), N, s.queries.data(), n, p);
        test::require_identical(got, ref, "grid exact on " + s.name);
        // recall_target = 1 is the same exact mode.
        if (std::isfinite(r)) continue;
        SearchParams pr = p;
        pr.A = 8;
        pr.recall_target = 1.0;
        KnnResult got1 = index->query(s.queries, pr);
        test::require_identical(got1, ref, "grid recall_target 1 on " + s.name);
      }
  }
}

TEST_CASE("blockhash_grid_vs_reference: kernel == host reference at every budget, every list form") {
  using Case = test::NamedCase;
  std::vector<Case> cases;
  cases.push_back({"uniform", datasets::uniform(20000, 1), datasets::uniform(500, 2)});
  cases.push_back({"clustered", datasets::clustered(20000, 3, 8, 0.01f), datasets::clustered(500, 4, 8, 0.01f)});
  auto far = datasets::uniform(300, 9, -3.0f, 4.0f);  // many outside the data's box
  cases.push_back({"far queries", datasets::uniform(5000, 8), far});
  auto wall = datasets::uniform(20000, 5);
  for (std::size_t i = 0; i < wall.size() / 3; ++i) wall[3 * i + (i % 3)] = (i % 2) ? 0.0f : 1.0f;  // box walls
  cases.push_back({"walls", wall, datasets::uniform(500, 6)});
  for (const Case& c : cases) {
    auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), c.pts.size() / 3);
    // The list forms' edges: one register (k <= 16), four (<= 64), the scalar list past them.
    for (int k : {1, 16, 17, 64, 65})
      for (float A : {1.0f, 2.0f, 8.0f, INFINITY}) {
        SearchParams p = test::knn_params(k);
        p.A = A;
        CAPTURE(c.name);
        CAPTURE(k);
        CAPTURE(A);
        kernel_equals_reference(*index, c.qs, p, c.name);
        // The scalar list (the GPU form) gives the same rows as the register list.
        SearchParams ps = p;
        ps.kernel_defines = "-DBHCL_GRID_VTOPK=0 -DBHCL_GRID_PREFETCH=0 -DBHCL_GRID_ROWCAP=0";
        if (k <= 16 || A == 8.0f) kernel_equals_reference(*index, c.qs, ps, std::string(c.name) + " scalar list");
        // The register list's other fills give the same rows as the default: k insertions, or
        // appended then sorted once (the default past 16), the sort in a function or inlined.
        const char* const fills_one[] = {"-DBHCL_GRID_FILLSORT=1", "-DBHCL_GRID_FILLSORT=1 -DBHCL_GRID_SORT_CALL=0"};
        const char* const fills_four[] = {"-DBHCL_GRID_FILLSORT=0", "-DBHCL_GRID_SORT_CALL=0"};
        if (k <= 64 && (A == 8.0f || !std::isfinite(A)))
          for (const char* fill : k <= 16 ? fills_one : fills_four) {
            SearchParams pf = p;
            pf.kernel_defines = fill;
            kernel_equals_reference(*index, c.qs, pf, std::string(c.name) + " " + fill);
          }
        // The lane tests through OpenCL's any() (BHCL_GRID_REDUCE=0), and the rings' slab cache
        // smaller than the rings searched (BHCL_GRID_NEAR=1: read within one cell, made beyond
        // it), give the same rows.
        if (k <= 64 && (A == 8.0f || !std::isfinite(A))) {
          SearchParams pr = p;
          pr.kernel_defines = "-DBHCL_GRID_REDUCE=0 -DBHCL_GRID_NEAR=1";
          kernel_equals_reference(*index, c.qs, pr, std::string(c.name) + " " + pr.kernel_defines);
        }
        // The budget bounds the points examined to within one run.
        if (std::isfinite(A)) {
          SearchParams pe = p;
          pe.count_examined = true;
          KnnResult r = index->query(c.qs, pe);
          const std::uint32_t b = BlockHashIndex::budget(p);
          for (std::size_t i = 0; i < r.n; ++i) {
            if (std::uint32_t(r.examined[i]) <= b) continue;
            REQUIRE(r.examined[i] >= 0);  // over the budget only by the last run scanned
          }
        }
      }
  }
}

TEST_CASE("blockhash_grid_radius_vs_bruteforce: radius search is exact by default") {
  for (const test::PointSet& s : test::exact_point_sets()) {
    CAPTURE(s.name);
    auto index = BlockHashIndex::build(test::runtime(), s.points.data(), s.points.size() / 3);
    const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
    const float r = test::cutting_radius(s);
    RadiusResult got;
    index->radius_search(s.queries.data(), n, r, RadiusParams{}, got);
    // Brute force through the kNN reference with k = N and the radius.
    SearchParams p = exact_params(static_cast<int>(std::min<std::size_t>(N, 256)), r);
    KnnResult ref = reference::knn_float(s.points.data(), N, s.queries.data(), n, p);
    for (std::size_t q = 0; q < n; ++q) {
      if (ref.counts[q] == p.k) continue;  // more than 256 within r: not comparable this way
      REQUIRE(got.count(q) == std::size_t(ref.counts[q]));
      for (std::size_t j = 0; j < got.count(q); ++j) {
        REQUIRE(got.ids[got.offsets[q] + j] == ref.id(q, int(j)));
        REQUIRE(got.dist2[got.offsets[q] + j] == ref.d2(q, int(j)));
      }
    }
  }
}

TEST_CASE("blockhash_grid_build: independent of threads, stable, every point in its cell") {
  auto pts = datasets::clustered(150000, 11, 12, 0.02f);
  BlockHashBuildParams one;
  one.threads = 1;
  BlockHashBuildParams two;
  two.threads = 2;
  auto a = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, one);
  auto b = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, two);
  const blockhash::Grid& ga = *a->structure().grid;
  const blockhash::Grid& gb = *b->structure().grid;
  REQUIRE(ga.starts == gb.starts);
  REQUIRE(ga.ids == gb.ids);
  REQUIRE(ga.x == gb.x);
  ga.validate("test");
  // Stable: inside a cell the caller's indices ascend.
  for (std::size_t c = 0; c < ga.ncells(); ++c)
    for (std::uint32_t i = ga.start(c) + 1; i < ga.start(c + 1); ++i) REQUIRE(ga.ids[i - 1] < ga.ids[i]);
  // The tuning aims at 24 points per point's cell; the sample estimate lands near it.
  CHECK(a->info().mean_cell_points > 8);
  CHECK(a->info().mean_cell_points < 72);
  REQUIRE(a->first_mismatch(pts.data(), pts.size() / 3) == -1);
  auto other = pts;
  other[3 * 777 + 1] += 1e-3f;
  REQUIRE(a->first_mismatch(other.data(), other.size() / 3) == 777);
}

// A fresh build of a direct directory gathers levels 1 and 2 of the pyramid and level 2's boxes
// while it places each bucket's points, each worker for the slabs its range of buckets holds
// whole, the rest from the directory after: the pyramid must be the one build_grid_occupancy
// makes from the directory and the points, at any thread count (the ranges differ) and for dims
// that are not multiples of 4. The bits byte for byte, the boxes by value (the gathering's
// four-wide minima may keep -0 where the directory's pass keeps +0: equal as numbers, which is
// all the kernels compare).
TEST_CASE("blockhash_grid_build: the pyramid gathered while placing equals the one from the directory") {
  std::vector<test::PointSet> sets = test::exact_point_sets();
  sets.push_back({"clustered 150k", datasets::clustered(150000, 11, 12, 0.02f), {}});
  sets.push_back({"cornell 200k", datasets::cornell_photons(200000, 5), {}});
  std::vector<float> zeros;  // the plane z = 0, each point's zero of either sign
  std::mt19937 rng(17);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  for (int i = 0; i < 60000; ++i) {
    zeros.push_back(u(rng));
    zeros.push_back(u(rng));
    zeros.push_back(rng() & 1u ? 0.0f : -0.0f);
  }
  sets.push_back({"plane of signed zeros 60k", zeros, {}});
  int gathered = 0;
  for (const test::PointSet& s : sets)
    for (unsigned threads : {1u, 2u, 3u, 8u}) {
      CAPTURE(s.name);
      CAPTURE(threads);
      BlockHashBuildParams bp;
      bp.threads = threads;
      auto ix = BlockHashIndex::build(test::runtime(), s.points.data(), s.points.size() / 3, bp);
      gathered += blockhash::PyramidGather::apply(ix->structure().grid->geom) ? 1 : 0;
      test::require_pyramid_as_built(*ix);  // no holes in a build: the boxes equal too
    }
  CHECK(gathered >= 8);  // the gathering path ran (a direct directory with a level 2)
}

TEST_CASE("blockhash_grid_two_level_vs_bruteforce: the two-level directory answers as the direct one") {
  BlockHashBuildParams two;
  two.grid_directory = 1;
  BlockHashBuildParams direct;
  direct.grid_directory = 0;
  for (const test::PointSet& s : test::exact_point_sets()) {
    CAPTURE(s.name);
    const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
    auto a = BlockHashIndex::build(test::runtime(), s.points.data(), N, two);
    REQUIRE(a->info().grid_two_level);
    a->structure().grid->validate("two-level");
    BlockHashBuildParams d = direct;
    d.cell_size = a->info().cell_size;  // the same cells, so the same sorted order
    d.max_cells_per_point = 1024;      // and no growing to fit a direct table
    auto b = BlockHashIndex::build(test::runtime(), s.points.data(), N, d);
    REQUIRE_FALSE(b->info().grid_two_level);
    REQUIRE_FALSE(b->info().grid_capped);
    REQUIRE(a->structure().grid->ids == b->structure().grid->ids);
    for (std::size_t c = 0; c <= a->structure().grid->ncells(); ++c)
      REQUIRE(a->structure().grid->start(c) == b->structure().grid->start(c));
    for (int k : {1, 10, 50}) {
      CAPTURE(k);
      SearchParams p = exact_params(k);
      KnnResult ref = reference::knn_float(s.points.data(), N, s.queries.data(), n, p);
      test::require_identical(a->query(s.queries, p), ref, "two-level exact on " + s.name);
      SearchParams pa = p;
      pa.A = 2;
      test::require_identical(a->query(s.queries, pa), b->query(s.queries, pa), "two-level A 2 on " + s.name);
      kernel_equals_reference(*a, s.queries, pa, "two-level reference");
      SearchParams ps = pa;
      ps.kernel_defines = "-DBHCL_GRID_VTOPK=0 -DBHCL_GRID_PREFETCH=0 -DBHCL_GRID_ROWCAP=0";
      kernel_equals_reference(*a, s.queries, ps, "two-level scalar list");
    }
    RadiusResult ra, rb;
    const float r = test::cutting_radius(s);
    a->radius_search(s.queries.data(), n, r, RadiusParams{}, ra);
    b->radius_search(s.queries.data(), n, r, RadiusParams{}, rb);
    REQUIRE(ra.ids == rb.ids);
    REQUIRE(ra.offsets == rb.offsets);
  }
}

TEST_CASE("blockhash_grid_two_level: chosen for sparse sets, saved and loaded, damage refused") {
  // Points on the six faces of a box: most cells of the box empty, as in the Cornell box.
  auto pts = datasets::uniform(60000, 41);
  for (std::size_t i = 0; i < pts.size() / 3; ++i) pts[3 * i + (i % 3)] = ((i / 3) % 2) ? 0.0f : 1.0f;
  auto qs = datasets::uniform(500, 42);
  BlockHashBuildParams bp;
  bp.max_cells_per_point = 0.05;  // a direct table of 65536 cells at most (the floor)
  bp.target_cell_points = 2;      // small cells: ~357k of them
  auto index = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, bp);
  REQUIRE(index->info().grid_two_level);
  const double cells = double(index->info().grid_dims[0]) * index->info().grid_dims[1] * index->info().grid_dims[2];
  REQUIRE(cells > 65536);  // more cells than a direct table may have
  REQUIRE(index->info().grid_directory_bytes < cells * 4);
  SearchParams p = exact_params(10);
  KnnResult ref = reference::knn_float(pts.data(), pts.size() / 3, qs.data(), qs.size() / 3, p);
  test::require_identical(index->query(qs, p), ref, "two-level faces");
  const std::string path = test::tmp_path("grid_two_level.bhcl");
  index->save(path);
  auto loaded = BlockHashIndex::load(test::runtime(), path);
  REQUIRE(loaded->info().grid_two_level);
  REQUIRE(loaded->info().occupied_cells == index->info().occupied_cells);
  test::require_identical(loaded->query(qs, p), ref, "loaded two-level");
  // A segment entry pointing past the directory is refused by name.
  blockhash::Grid g = *index->structure().grid;
  std::size_t seg = 0;
  while (g.starts[seg] & BHCL_GRID_EMPTY_SEG) ++seg;
  g.starts[seg] = static_cast<std::uint32_t>(g.starts.size());
  REQUIRE_THROWS_WITH_AS(g.validate("x"), doctest::Contains("segment"), Error);
  std::remove(path.c_str());
}

TEST_CASE("blockhash_grid_io: save and load answer identically, damage is refused") {
  auto pts = datasets::uniform(30000, 21);
  auto qs = datasets::uniform(400, 22);
  auto index = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3);
  const std::string path = test::tmp_path("grid_index.bhcl");
  index->save(path);
  auto loaded = BlockHashIndex::load(test::runtime(), path);
  REQUIRE(loaded->info().grid);
  REQUIRE(loaded->first_mismatch(pts.data(), pts.size() / 3) == -1);
  for (float A : {2.0f, INFINITY}) {
    SearchParams p = test::knn_params(10);
    p.A = A;
    test::require_identical(loaded->query(qs, p), index->query(qs, p), "loaded grid");
  }
  // One flipped byte in the payload: the checksum refuses it.
  std::string bytes;
  {
    std::ifstream in(path, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), {});
  }
  std::string bad = bytes;
  bad[bad.size() - 5] ^= 0x20;
  REQUIRE_THROWS_WITH_AS(blockhash::parse_grid(bad, "x"), doctest::Contains("checksum"), Error);
  REQUIRE_THROWS_WITH_AS(blockhash::parse_grid(bytes.substr(0, bytes.size() - 4), "x"),
                         doctest::Contains("bytes"), Error);
  std::remove(path.c_str());
}

TEST_CASE("blockhash_grid_rebuild: the next frame equals a fresh build with the same cell side") {
  auto f1 = datasets::uniform(40000, 31);
  auto f2 = datasets::clustered(30000, 32, 6, 0.05f);
  auto f3 = datasets::uniform(60000, 33, -2.0f, 2.0f);
  auto qs = datasets::uniform(300, 34);
  auto index = BlockHashIndex::build(test::runtime(), f1.data(), f1.size() / 3);
  const double h = index->info().cell_size;
  for (const auto* f : {&f2, &f3}) {
    index->rebuild(f->data(), f->size() / 3);
    REQUIRE(index->size() == f->size() / 3);
    REQUIRE(index->info().cell_size == doctest::Approx(h));
    BlockHashBuildParams bp;
    bp.cell_size = h;
    auto fresh = BlockHashIndex::build(test::runtime(), f->data(), f->size() / 3, bp);
    for (float A : {4.0f, INFINITY}) {
      SearchParams p = test::knn_params(12);
      p.A = A;
      test::require_identical(index->query(qs, p), fresh->query(qs, p), "rebuild");
    }
  }
}

TEST_CASE("blockhash_factory: the grid a GridIndex, the L tables a BlockTablesIndex, the other's fields refused") {
  auto rt = test::runtime();
  auto pts = datasets::uniform(3000, 43);
  auto qs = datasets::uniform(200, 44);
  const std::size_t n = pts.size() / 3;
  auto is_grid = [](const BlockHashIndex& ix) { return dynamic_cast<const GridIndex*>(&ix) != nullptr; };
  auto is_tables = [](const BlockHashIndex& ix) { return dynamic_cast<const BlockTablesIndex*>(&ix) != nullptr; };
  BlockHashBuildParams one, zero, paper, cells;
  one.grid = 1;
  zero.grid = 0;
  paper.preset = BlockHashBuildParams::Preset::Paper;
  cells.preset = BlockHashBuildParams::Preset::PaperCells;
  auto def = BlockHashIndex::build(rt, pts.data(), n);
  CHECK(is_grid(*def));
  CHECK(is_grid(*BlockHashIndex::build(rt, pts.data(), n, one)));
  auto tables = BlockHashIndex::build(rt, pts.data(), n, zero);
  CHECK(is_tables(*tables));
  CHECK(is_tables(*BlockHashIndex::build(rt, pts.data(), n, paper)));
  CHECK(is_tables(*BlockHashIndex::build(rt, pts.data(), n, cells)));
  // A grid field on the tables, table fields on the grid: refused, naming them.
  BlockHashBuildParams side = paper;
  side.max_cells_per_point = 2;
  REQUIRE_THROWS_WITH_AS(BlockHashIndex::build(rt, pts.data(), n, side),
                         doctest::Contains("max_cells_per_point is an option of the grid (the auto preset's layout), "
                                           "not of the paper preset's tables"),
                         Error);
  BlockHashBuildParams lx = one;
  lx.L = 2;
  lx.X = 8;
  REQUIRE_THROWS_WITH_AS(BlockHashIndex::build(rt, pts.data(), n, lx),
                         doctest::Contains("L, X are options of the block layouts"), Error);
  // Each class built from its own parameters answers as the factory's.
  SearchParams p = test::knn_params(8);
  p.A = 4;
  GridIndex grid(rt, pts.data(), n, GridBuildParams{});
  BlockTablesIndex own(rt, pts.data(), n, TableBuildParams{});
  test::require_identical(grid.query(qs, p), def->query(qs, p), "GridIndex vs the factory's default");
  test::require_identical(own.query(qs, p), tables->query(qs, p), "BlockTablesIndex vs the factory's grid = 0");
  // Their own ranges, checked when built directly.
  GridBuildParams gd;
  gd.grid_directory = 3;
  CHECK_THROWS_WITH_AS(GridIndex(rt, pts.data(), n, gd), doctest::Contains("grid_directory"), Error);
  TableBuildParams hb;
  hb.hilbert_bits = 40;
  CHECK_THROWS_WITH_AS(BlockTablesIndex(rt, pts.data(), n, hb), doctest::Contains("hilbert_bits must be"), Error);
  // load() gives back the class the file holds.
  const std::string gpath = test::tmp_path("factory_grid.bhi"), tpath = test::tmp_path("factory_tables.bhi");
  def->save(gpath);
  tables->save(tpath);
  auto gl = BlockHashIndex::load(rt, gpath);
  auto tl = BlockHashIndex::load(rt, tpath);
  CHECK(is_grid(*gl));
  CHECK(is_tables(*tl));
  test::require_identical(tl->query(qs, p), tables->query(qs, p), "loaded tables");
  std::remove(gpath.c_str());
  std::remove(tpath.c_str());
}

TEST_CASE("blockhash_grid_params: the layouts and the checks") {
  auto pts = datasets::uniform(5000, 41);
  auto def = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3);
  CHECK(def->info().grid);
  // A block-layout option on the auto preset is refused, never obeyed by switching layouts.
  BlockHashBuildParams old;
  old.P = 8;
  REQUIRE_THROWS_WITH_AS(BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, old),
                         doctest::Contains("P is an option of the block layouts"), Error);
  old.grid = 0;
  auto blocks = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, old);
  CHECK_FALSE(blocks->info().grid);
  BlockHashBuildParams bad = old;
  bad.grid = 1;
  REQUIRE_THROWS_WITH_AS(BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, bad),
                         doctest::Contains("P is an option of the block layouts"), Error);
  BlockHashBuildParams paper_grid;
  paper_grid.preset = BlockHashBuildParams::Preset::Paper;
  paper_grid.grid = 1;
  REQUIRE_THROWS_WITH_AS(BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, paper_grid),
                         doctest::Contains("grid = 1"), Error);
  // And the grid's options on a block layout.
  BlockHashBuildParams side = old;
  side.cell_size = 0.1;
  REQUIRE_THROWS_WITH_AS(BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, side),
                         doctest::Contains("cell_size is an option of the grid"), Error);
  BlockHashBuildParams cs;
  cs.cell_size = -3;
  REQUIRE_THROWS_WITH_AS(BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, cs),
                         doctest::Contains("cell"), Error);
  SearchParams p;
  p.A = -1;
  REQUIRE_THROWS_WITH_AS(def->query(pts, p), doctest::Contains("A must be positive"), Error);
  // The default search (A = 0) is the exact mode on the grid.
  SearchParams d = test::knn_params(7);
  test::require_identical(def->query(pts, d), reference::knn_float(pts.data(), 5000, pts.data(), 5000, d),
                          "the default search");
  // One point, coincident points, k above N.
  std::vector<float> one = {0.5f, 0.5f, 0.5f};
  auto single = BlockHashIndex::build(test::runtime(), one.data(), 1);
  SearchParams p3 = test::knn_params(3);
  KnnResult r = single->query(std::vector<float>{0, 0, 0, 1, 1, 1}, p3);
  REQUIRE(r.counts == std::vector<std::int32_t>{1, 1});
  REQUIRE(r.id(0, 1) == -1);
  std::vector<float> same(3 * 5000, 0.25f);
  auto dup = BlockHashIndex::build(test::runtime(), same.data(), 5000);
  KnnResult rd = dup->query(std::vector<float>{0.25f, 0.25f, 0.25f}, exact_params(20));
  for (int j = 0; j < 20; ++j) REQUIRE(rd.id(0, j) == j);  // ties by index
}
