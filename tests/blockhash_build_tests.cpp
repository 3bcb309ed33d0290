// Block hashing: each host build stage on its own (lib/src/blockhash/build.hpp).
#include <map>
#include <random>

#include "blockhash/build.hpp"
#include "blockhash/options.hpp"
#include "test_util.hpp"

#include "blockhash_cl/spatial_order.hpp"

using namespace bhcl;
using namespace bhcl::blockhash;

namespace {

// A structure with its blocks cut (stages 1-2), ready for params/thresholds/tables.
std::unique_ptr<Structure> cut(const std::vector<float>& pts, const TableBuildParams& p) {
  auto s = std::make_unique<Structure>();
  s->n_points = pts.size() / 3;
  s->info.preset = p.preset;
  s->info.n_points = s->n_points;
  s->info.X = derive_x(p);
  sort_points(pts.data(), s->n_points, p.hilbert_bits, *s);
  make_blocks(pts.data(), s->order, s->info.X, s->blocks, s->boxes);
  return s;
}

TableBuildParams preset(const char* name) {
  TableBuildParams p;
  p.preset = BlockHashBuildParams::parse_preset(name);
  return p;
}

}  // namespace

TEST_CASE("blockhash hilbert: a bijection on the grid that steps to an adjacent cell") {
  for (int bits : {1, 2, 3, 4}) {
    CAPTURE(bits);
    const std::uint32_t side = 1u << bits;
    const std::uint64_t cells = std::uint64_t(side) * side * side;
    std::vector<int> hit(cells, 0);
    std::vector<std::array<std::uint32_t, 3>> at(cells);
    for (std::uint32_t x = 0; x < side; ++x)
      for (std::uint32_t y = 0; y < side; ++y)
        for (std::uint32_t z = 0; z < side; ++z) {
          std::uint64_t k = hilbert_encode(x, y, z, bits);
          REQUIRE(k < cells);
          ++hit[k];
          at[k] = {x, y, z};
          std::uint32_t back[3];
          hilbert_decode(k, bits, back);
          REQUIRE(back[0] == x);
          REQUIRE(back[1] == y);
          REQUIRE(back[2] == z);
        }
    for (auto h : hit) REQUIRE(h == 1);
    // Locality: consecutive keys are face neighbours (Manhattan distance 1).
    for (std::uint64_t k = 1; k < cells; ++k) {
      int d = 0;
      for (int i = 0; i < 3; ++i) d += std::abs(int(at[k][i]) - int(at[k - 1][i]));
      REQUIRE(d == 1);
    }
  }
  // Full resolution: round trip of random cells.
  std::mt19937_64 rng(3);
  for (int i = 0; i < 1000; ++i) {
    std::uint32_t c[3] = {std::uint32_t(rng() & 0x1fffff), std::uint32_t(rng() & 0x1fffff), std::uint32_t(rng() & 0x1fffff)};
    std::uint32_t back[3];
    hilbert_decode(hilbert_encode(c[0], c[1], c[2], 21), 21, back);
    CHECK(back[0] == c[0]);
    CHECK(back[1] == c[1]);
    CHECK(back[2] == c[2]);
  }
}

TEST_CASE("blockhash hilbert: quantisation behaves for flat, tiny, huge and offset boxes") {
  auto spread = [](const std::vector<float>& pts, int bits) {
    Quantiser q = make_quantiser(pts.data(), pts.size() / 3, bits);
    std::set<std::uint64_t> distinct;
    for (std::size_t i = 0; i < pts.size() / 3; ++i) {
      std::uint32_t c[3];
      for (int d = 0; d < 3; ++d) {
        c[d] = q.cell(d, pts[3 * i + d]);
        REQUIRE(c[d] < (1u << bits));
      }
      distinct.insert(hilbert_encode(c[0], c[1], c[2], bits));
    }
    return distinct.size();
  };
  auto base = datasets::uniform(2000, 1);
  CHECK(spread(base, 21) == 2000);
  auto flat = base;  // z = 0: a plane
  for (std::size_t i = 0; i < 2000; ++i) flat[3 * i + 2] = 0.0f;
  CHECK(spread(flat, 21) == 2000);
  auto tiny = datasets::uniform(2000, 1, 0.0f, 1e-30f);
  CHECK(spread(tiny, 21) > 1990);
  auto huge = datasets::uniform(2000, 1, -1e37f, 1e37f);
  CHECK(spread(huge, 21) == 2000);
  auto off = datasets::uniform(2000, 1, -1.0f, 1.0f);
  datasets::offset(off, 1e6, -1e6, 5e5);
  CHECK(spread(off, 21) > 1900);  // float spacing at 1e6 is 0.06: some points coincide
  std::vector<float> same(300, 7.0f);
  CHECK(spread(same, 21) == 1);
}

TEST_CASE("spatial order: bhcl::hilbert_order is a permutation, local, non-finite points last") {
  CHECK(bhcl::hilbert_order(nullptr, 0).empty());
  auto pts = datasets::uniform(4000, 3);
  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  pts[3 * 10 + 1] = nan;
  pts[3 * 20 + 2] = -inf;
  const std::vector<std::size_t> order = bhcl::hilbert_order(pts.data(), 4000);
  REQUIRE(order.size() == 4000);
  std::vector<int> seen(4000, 0);
  for (std::size_t i : order) ++seen[i];
  for (int v : seen) REQUIRE(v == 1);
  CHECK(order[3998] == 10);  // the non-finite ones last, in their own order
  CHECK(order[3999] == 20);
  // Locality: consecutive points along the order are far closer than random pairs (mean distance
  // of random pairs in the unit cube is about 0.66).
  double step = 0;
  for (std::size_t i = 1; i < 3998; ++i) {
    double d2 = 0;
    for (int d = 0; d < 3; ++d) d2 += std::pow(pts[3 * order[i] + d] - pts[3 * order[i - 1] + d], 2);
    step += std::sqrt(d2);
  }
  CHECK(step / 3997 < 0.1);
  std::vector<float> one{1, 2, 3};
  CHECK(bhcl::hilbert_order(one.data(), 1) == std::vector<std::size_t>{0});
}

TEST_CASE("blockhash hilbert: the order is a stable permutation and blocks are local") {
  auto pts = datasets::uniform(5000, 2);
  for (std::size_t i = 0; i < 500; ++i)  // duplicates keep the caller's order
    for (int d = 0; d < 3; ++d) pts[3 * (4000 + i) + d] = pts[3 * i + d];
  Quantiser q = make_quantiser(pts.data(), 5000, 21);
  auto keys = hilbert_keys(pts.data(), 5000, q);
  auto order = hilbert_order(keys);
  std::vector<int> seen(5000, 0);
  for (std::size_t i = 0; i < order.size(); ++i) {
    ++seen[order[i]];
    if (i) {
      REQUIRE(keys[order[i - 1]] <= keys[order[i]]);
      if (keys[order[i - 1]] == keys[order[i]]) REQUIRE(order[i - 1] < order[i]);
    }
  }
  for (int s : seen) REQUIRE(s == 1);
  CHECK(order == hilbert_order(keys));
  std::vector<bhcl_bh_block> blocks;
  std::vector<bhcl_bh_box> boxes;
  make_blocks(pts.data(), order, 16, blocks, boxes);
  REQUIRE(blocks.size() == (5000 + 15) / 16);
  // Locality: a block's box is much smaller than the unit cube (mean volume of 16 random points'
  // box in [0,1]^3 is ~0.4; along a Hilbert curve ~ 16 / 5000).
  double vol = 0;
  for (std::size_t b = 0; b < boxes.size(); ++b) {
    const auto& x = boxes[b];
    REQUIRE(x.count == std::min<int>(16, 5000 - int(b) * 16));
    REQUIRE(x.first == int(b) * 16);
    for (int j = 0; j < x.count; ++j) {
      int id = blocks[b].id[j];
      REQUIRE(id == order[b * 16 + j]);
      REQUIRE(blocks[b].x[j] == pts[3 * id]);
      REQUIRE(blocks[b].y[j] >= x.lo_y);
      REQUIRE(blocks[b].z[j] <= x.hi_z);
    }
    vol += double(x.hi_x - x.lo_x) * (x.hi_y - x.lo_y) * (x.hi_z - x.lo_z);
  }
  CHECK(vol / boxes.size() < 0.01);
  CHECK(blocks.back().id[15] == -1);  // 5000 = 312 * 16 + 8: the last block is partial
  CHECK_THROWS_AS(make_blocks(pts.data(), order, 17, blocks, boxes), Error);
}

TEST_CASE("blockhash thresholds: monotonic, CDF-balanced, jittered per table, reproducible") {
  auto pts = datasets::clustered(20000, 5, 8, 0.05f);
  Histogram h = histogram(pts.data(), 20000, 1, 1024);
  CHECK(h.total == 20000);
  for (bool guarded : {false, true}) {
    CAPTURE(guarded);
    const int P = 20;
    auto t0 = make_thresholds(h, P, 1, 0, 1, guarded);
    auto t1 = make_thresholds(h, P, 1, 1, 1, guarded);
    CHECK(t0 == make_thresholds(h, P, 1, 0, 1, guarded));
    CHECK(t0 != t1);
    CHECK(t0 != make_thresholds(h, P, 2, 0, 1, guarded));
    REQUIRE(t0.size() == std::size_t(P));
    for (int i = 1; i < P; ++i) REQUIRE(t0[i - 1] <= t0[i]);
    // Balanced: each of the P + 1 slabs holds about N / P points (the outer two share one
    // stratum); the sample is stratified, so no slab holds more than ~2 strata plus a bin.
    std::vector<int> slab(P + 1, 0);
    for (std::size_t i = 0; i < 20000; ++i) ++slab[hash_coord(t0.data(), P, pts[3 * i + 1])];
    int finite = 0;
    for (float t : t0) finite += std::isfinite(t) ? 1 : 0;
    CHECK(finite >= P - 2);
    for (int c : slab) CHECK(c < 2 * 20000 / P + 200);
    int big = 0;
    for (int c : slab) big += c > 20000 / (4 * P) ? 1 : 0;
    CHECK(big >= P - 3);
  }
  // hash_coord: the count of thresholds <= t, with the clamp outside.
  std::vector<float> t = {1.0f, 2.0f, 2.0f, 5.0f, INFINITY};
  CHECK(hash_coord(t.data(), 5, -100.0f) == 0);
  CHECK(hash_coord(t.data(), 5, 1.0f) == 1);
  CHECK(hash_coord(t.data(), 5, 2.0f) == 3);
  CHECK(hash_coord(t.data(), 5, 4.99f) == 3);
  CHECK(hash_coord(t.data(), 5, 1e30f) == 4);
}

TEST_CASE("blockhash thresholds: the guard keeps a wall and the space just off it together") {
  // 60 % of the points on the floor y = 0, the rest uniform above: the raw inverse CDF puts many
  // thresholds inside the floor's bin; guarded ones keep off it.
  std::mt19937_64 rng(9);
  std::uniform_real_distribution<float> u(0.0f, 555.0f);
  std::vector<float> pts;
  for (int i = 0; i < 20000; ++i) {
    bool floor = i % 5 < 3;
    pts.insert(pts.end(), {u(rng), floor ? 0.0f : u(rng), u(rng)});
  }
  Histogram h = histogram(pts.data(), 20000, 1, 1024);
  const int P = 40;
  auto raw = make_thresholds(h, P, 1, 0, 1, false);
  auto guarded = make_thresholds(h, P, 1, 0, 1, true);
  int raw_in_floor = 0;
  for (float t : raw) raw_in_floor += t <= 0.6f ? 1 : 0;
  CHECK(raw_in_floor >= P / 2);
  // Guarded: the first threshold is at least two bins above the floor, so a query 0.5 mm above
  // the floor hashes to the floor's cell.
  CHECK(guarded[0] > 2 * 555.0f / 1024 - 1e-3f);
  CHECK(hash_coord(guarded.data(), P, 0.5f) == hash_coord(guarded.data(), P, 0.0f));
  for (int i = 1; i < P; ++i) CHECK((guarded[i - 1] < guarded[i] || std::isinf(guarded[i])));
}

TEST_CASE("blockhash tables: every point's block is in its cell's bucket unless it overflowed") {
  for (const char* pr : {"paper", "auto"}) {
    for (int B : {-1, 2}) {
      CAPTURE(pr);
      CAPTURE(B);
      auto pts = datasets::clustered(8000, 7, 6, 0.03f);
      TableBuildParams p = preset(pr);
      p.B = B;
      auto s = cut(pts, p);
      derive_params(p, *s);
      build_thresholds(p, *s);
      TableStats st = build_tables(*s);
      const std::size_t N = 8000, X = std::size_t(s->info.X);
      // Recount from scratch: distinct blocks and points per (table, cell).
      std::size_t overflowed_seen = 0;
      for (int t = 0; t < s->info.L; ++t) {
        std::map<std::uint32_t, std::map<std::int32_t, int>> cells;
        for (std::size_t i = 0; i < N; ++i) {
          float q[3];
          s->point(i, q);
          ++cells[s->point_cell(t, q)][std::int32_t(i / X)];
        }
        for (const auto& [key, blocks] : cells) {
          long bi = s->find_bucket(t, key);
          REQUIRE(bi >= 0);
          const bhcl_bh_bucket& bk = s->buckets[bi];
          const int D = int(blocks.size()), Bv = s->info.B;
          const int kept = std::min(D, Bv), over = std::max(0, D - Bv);
          // Q bookkeeping.
          REQUIRE(int(bk.n_refs) == kept);
          REQUIRE(bk.q == Bv - kept - over);
          REQUIRE(bool(bk.flags & BHCL_BH_FLAG_OVERFLOWED) == (over > 0));
          overflowed_seen += over > 0;
          std::set<std::int32_t> held(s->refs.begin() + bk.first_ref, s->refs.begin() + bk.first_ref + bk.n_refs);
          REQUIRE(held.size() == bk.n_refs);  // each block once
          for (std::int32_t b : held) REQUIRE(blocks.count(b));
          if (!over) {
            for (const auto& kv : blocks) REQUIRE(held.count(kv.first));
          } else if (s->info.keep_top_count) {
            // Kept blocks hold at least as many of the cell's points as any dropped one.
            int min_kept = 1 << 30, max_dropped = 0;
            for (const auto& kv : blocks) {
              if (held.count(kv.first)) min_kept = std::min(min_kept, kv.second);
              else max_dropped = std::max(max_dropped, kv.second);
            }
            REQUIRE(min_kept >= max_dropped);
          } else {
            // Drop new: the first B blocks in insertion (block) order.
            auto it = blocks.begin();
            for (int j = 0; j < kept; ++j, ++it) REQUIRE(held.count(it->first));
          }
        }
        if (!s->info.direct_addressing) REQUIRE(cells.size() == s->table_starts[t + 1] - s->table_starts[t]);
      }
      std::size_t nonempty = 0;
      for (const auto& bk : s->buckets) nonempty += bk.n_refs ? 1 : 0;
      CHECK(st.occupied_cells == nonempty);
      if (!s->info.direct_addressing) CHECK(nonempty == s->buckets.size());
      CHECK(st.overflowed == overflowed_seen);
      if (B == 2) CHECK(overflowed_seen > 0);
      s->validate("built structure");
    }
  }
}

TEST_CASE("blockhash params: paper-cells keeps the talk's L, X and B and puts k / 4 points in the median cell") {
  // Points on the faces of a box, like a photon map (at 200k photons P = ln N puts 180 in a cell).
  auto pts = datasets::cornell_photons(40000, 3);
  TableBuildParams paper = preset("paper"), cells = preset("paper-cells");
  for (TableBuildParams* p : {&paper, &cells}) {
    p->design_A = 16;
    p->design_k = 50;
  }
  auto sp = cut(pts, paper), sc = cut(pts, cells);
  derive_params(paper, *sp);
  derive_params(cells, *sc);
  CHECK(sc->info.L == sp->info.L);
  CHECK(sc->info.X == sp->info.X);
  CHECK(sc->info.B == sp->info.B);  // the talk's B > A k / (X ln N)
  CHECK(sp->info.P == int(std::lround(std::log(40000.0))));
  CHECK_FALSE(sc->info.direct_addressing);  // the directory: (P+1)^3 buckets would not fit
  CHECK_FALSE(sc->info.keep_top_count);
  CHECK_FALSE(sc->info.guard_thresholds);
  const double med_paper = median_cell_points(*sp, paper, sp->info.P, 1);
  const double med_cells = median_cell_points(*sc, cells, sc->info.P, 1);
  CAPTURE(sc->info.P);
  CHECK(med_paper > 2 * med_cells);  // the talk's P: cells larger than the k / 4 aimed at
  CHECK(med_cells >= 50 / 4.0 / 2);
  CHECK(med_cells <= 50 / 4.0 * 2);
  // target_cell_points overrides the k / 4.
  cells.target_cell_points = 100;
  auto st = cut(pts, cells);
  derive_params(cells, *st);
  CHECK(st->info.P < sc->info.P);
  CHECK(BlockHashBuildParams::parse_preset("paper-cells") == BlockHashBuildParams::Preset::PaperCells);
  CHECK(std::string(BlockHashBuildParams::preset_name(BlockHashBuildParams::Preset::PaperCells)) == "paper-cells");
  CHECK_THROWS_WITH_AS(BlockHashBuildParams::parse_preset("papers"), doctest::Contains("paper-cells"), Error);
}

TEST_CASE("blockhash options: the paper presets' B is sized for the search asked, other builds untouched") {
  SearchParams p;
  p.k = 50;
  p.A = 16;
  MethodOptions paper;
  paper.set("preset", "paper");
  MethodOptions sized = paper_options_for_search(paper, p);
  CHECK(sized.text("design-k") == "50");
  CHECK(std::stod(sized.text("design-A")) == 16.0);
  paper.set("preset", "paper-cells");
  CHECK(paper_options_for_search(paper, p).has("design-A"));
  p.A = 0;  // the index default, 8
  CHECK(std::stod(paper_options_for_search(paper, p).text("design-A")) == 8.0);
  p.A = INFINITY;  // no A at build: the design A stays the option's default
  CHECK_FALSE(paper_options_for_search(paper, p).has("design-A"));
  CHECK(paper_options_for_search(paper, p).text("design-k") == "50");
  p.A = 4;
  MethodOptions given = paper;
  given.set("B", "3");  // the caller's B wins
  CHECK_FALSE(paper_options_for_search(given, p).has("design-A"));
  MethodOptions autop;  // auto (the grid) has no B
  CHECK(paper_options_for_search(autop, p).values == autop.values);
  // The sized options build an index whose B follows the talk's rule for that A and k.
  auto pts = datasets::cornell_photons(20000, 5);
  BlockHashBuildParams bp;
  apply_build_options(blockhash::option_table(), paper_options_for_search(paper, p), &bp, "blockhash");
  auto idx = BlockHashIndex::build(test::runtime(), pts.data(), 20000, bp);
  CHECK(idx->B() == int(std::ceil(4.0 * 50 / (10 * std::log(20000.0)))) + 1);
}

TEST_CASE("blockhash params: the talk's formulas for paper, data-driven auto, overrides") {
  auto pts = datasets::uniform(20000, 4);
  TableBuildParams p = preset("paper");
  p.design_A = 16;
  p.design_k = 50;
  auto s = cut(pts, p);
  derive_params(p, *s);
  const double ln = std::log(20000.0);  // 9.9
  CHECK(s->info.L == 10);
  CHECK(s->info.P == 10);
  CHECK(s->info.X == 10);
  CHECK(s->info.B == int(std::ceil(16.0 * 50 / (10 * ln))) + 1);
  CHECK(s->info.B > 16.0 * 50 / (10 * ln));
  CHECK(s->info.direct_addressing);
  CHECK_FALSE(s->info.keep_top_count);
  CHECK_FALSE(s->info.neighbour_probes);

  // auto's L tables (the block stages run as grid = 0 builds them): four tables, the median
  // occupied cell near 100 points.
  TableBuildParams a = preset("auto");
  auto sa = cut(pts, a);
  derive_params(a, *sa);
  CHECK(sa->info.L == 4);
  CHECK(sa->info.X == 16);
  // P puts the median occupied cell near 100 points: (P+1)^3 ~ 200 cells for 20000 points.
  double med = median_cell_points(*sa, a, sa->info.P, 1);
  CHECK(med >= 50);
  CHECK(med <= 200);
  CHECK(sa->info.keep_top_count);
  CHECK_FALSE(sa->info.direct_addressing);
  CHECK(sa->info.B >= 1);

  TableBuildParams o = preset("auto");
  o.L = 3;
  o.P = 7;
  o.B = 5;
  o.X = 12;
  auto so = cut(pts, o);
  derive_params(o, *so);
  CHECK(so->info.L == 3);
  CHECK(so->info.P == 7);
  CHECK(so->info.B == 5);
  CHECK(so->info.X == 12);
  o.P = 5000;
  CHECK_THROWS_WITH_AS(derive_params(o, *so), doctest::Contains("P must be"), Error);
  CHECK_THROWS_AS(BlockHashBuildParams::parse_preset("fast"), Error);
}
