// Block hashing described once: its options (build, search, radius; name, kind, range, default,
// help and the field each sets), its capabilities and its maker. The registry lists it; the
// library's range checks (derive_params), bhcl, the Python module, the benchmarks and the tests
// read this table.
#include "blockhash/options.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdint>
#include <limits>

#include "blockhash_cl/block_tables.hpp"
#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/grid_index.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/knn.hpp"
#include "blockhash_cl/numbers.hpp"
#include "blockhash_layout.h"

namespace bhcl::blockhash {
namespace {

using P = BlockHashBuildParams;
constexpr long long kIntMax = std::numeric_limits<int>::max();
constexpr double kHuge = std::numeric_limits<double>::max();

// -1: the preset decides; 0 off; 1 on.
OptionInfo flag(const char* name, const char* help) {
  return option::integer(name, std::string(help) + " (0 off, 1 on, -1: the preset decides)", 0, 1, "-1").or_unset();
}

// Every 64-bit seed is valid in the struct; the text form takes 0 .. 2^63 - 1.
OptionInfo seed() {
  OptionInfo o = BHCL_BUILD_OPTION(P, seed, option::integer("seed", "seed of the threshold jitter", 0,
                                                            std::numeric_limits<long long>::max(), "1"));
  o.get = [](const void* p, OptionValue& v) {
    const std::uint64_t s = static_cast<const P*>(p)->seed;
    v.integer = static_cast<long long>(std::min<std::uint64_t>(s, std::numeric_limits<long long>::max()));
    v.number = double(v.integer);
  };
  return o;
}

// An option of the block layouts (grid = 0, or preset paper / paper-cells): the grid refuses it.
OptionInfo block(OptionInfo o) {
  o.help += " (block layouts: grid = 0 or preset paper, paper-cells)";
  return o.needing("grid=0");
}

std::vector<OptionInfo> make_table() {
  OptionInfo preset = option::choice("preset", "parameter preset (paper: the talk's rules; paper-cells: the same with P from the data, docs/ACCURACY.md)", {"auto", "paper", "paper-cells"}, "auto");
  preset.field = "BlockHashBuildParams::preset";
  preset.get = [](const void* p, OptionValue& v) { v.text = P::preset_name(static_cast<const P*>(p)->preset); };
  preset.set = [](void* p, const OptionValue& v) { static_cast<P*>(p)->preset = P::parse_preset(v.text); };
  return {
      preset,
      block(BHCL_BUILD_OPTION(P, L, option::integer("L", "hash tables (-1: the preset decides)", 1, 64, "-1").or_unset())),
      block(BHCL_BUILD_OPTION(P, P, option::integer("P", "thresholds per dimension (-1: the preset decides)", 1, BHCL_BH_MAX_P, "-1").or_unset())),
      block(BHCL_BUILD_OPTION(P, B, option::integer("B", "block references per bucket (-1: the preset decides)", 1, 65535, "-1").or_unset())),
      block(BHCL_BUILD_OPTION(P, X, option::integer("X", "points per block (-1: the preset decides)", 1, BHCL_BH_BLOCK_SLOTS, "-1").or_unset())),
      seed(),
      BHCL_BUILD_OPTION(P, grid, option::integer("grid", "the layout: -1 the preset's (auto: the grid, exact by default; paper, paper-cells: the talk's tables), 0 the block layouts (their options need it), 1 the grid", 0, 1, "-1").or_unset()),
      BHCL_BUILD_OPTION(P, cell_size, option::number("cell-size", "grid: the cells' side in the points' units (-1: chosen so a point's cell holds ~target-cell-points)", 0, 1e30, "-1", true).or_unset()),
      BHCL_BUILD_OPTION(P, max_cells_per_point, option::number("max-cells-per-point", "grid: the most cells per point of the direct table (past it a two-level directory of up to 16x as many, then the cells grow)", 0.01, 1024, "8")),
      BHCL_BUILD_OPTION(P, grid_directory, option::integer("grid-directory", "grid: the cell directory (-1: by max-cells-per-point, 0: direct, 1: two-level)", 0, 1, "-1").or_unset()),
      BHCL_BUILD_OPTION(P, target_cell_points, option::number("target-cell-points", "auto, paper-cells: the cell population aimed at (-1: 24, for the grid its device's kernel form's, 24 on every row so far; grid: a point's cell, block layouts: the median occupied cell, 100 for L tables; paper-cells design-k / 4)", 1, 1e6, "-1").or_unset()),
      block(BHCL_BUILD_OPTION(P, b_percentile, option::number("b-percentile", "auto: B is this percentile of the distinct blocks per occupied cell", 0, 1, "0.9", true))),
      block(BHCL_BUILD_OPTION(P, design_A, option::number("design-A", "paper presets: the A of the talk's rule for B (bhcl render and knn: the A asked)", 0, kHuge, "8", true))),
      block(BHCL_BUILD_OPTION(P, design_k, option::integer("design-k", "paper presets: the k of the talk's rule for B, and paper-cells' cell population k / 4 (bhcl render and knn: the k asked)", 1, kIntMax, "10"))),
      block(BHCL_BUILD_OPTION(P, hist_bins, option::integer("hist-bins", "histogram bins per dimension of the threshold CDFs", 2, 1 << 22, "1024"))),
      block(BHCL_BUILD_OPTION(P, hilbert_bits, option::integer("hilbert-bits", "bits per dimension of the Hilbert keys", 1, 21, "21"))),
      block(BHCL_BUILD_OPTION(P, guard_thresholds, flag("guard-thresholds", "thresholds snapped to bin edges, de-duplicated, off heavy bins"))),
      block(BHCL_BUILD_OPTION(P, keep_top_count, flag("keep-top-count", "a full bucket keeps the blocks holding most of the cell's points"))),
      block(BHCL_BUILD_OPTION(P, direct_addressing, flag("direct-addressing", "all (P+1)^3 cells, not only the occupied ones"))),
      block(BHCL_BUILD_OPTION(P, box_skip, flag("box-skip", "skip blocks whose box is farther than the k-th distance"))),
      block(BHCL_BUILD_OPTION(P, box_order, flag("box-order", "scan blocks in order of box distance with an early stop"))),
      block(BHCL_BUILD_OPTION(P, hilbert_seed, option::integer("hilbert-seed", "box order: blocks gathered on each side of the query's Hilbert key (-1: the preset decides)", 0, 64, "-1").or_unset())),
      block(BHCL_BUILD_OPTION(P, neighbour_probes, flag("default-probes", "the neighbour probes of a query that leaves them to the index"))),
      option::file("load-index", "load this saved index instead of building"),
      option::file("save-index", "save the built index to this file"),
      option::search<&SearchParams::A, nullptr>(
          option::number("A", "examine at most A*k points per query (accuracy against speed; inf: exact on "
                              "the grid; 0: the index default, exact on auto's grid, 8 on the block layouts)", 0,
                         std::numeric_limits<double>::infinity(), "0"),
          "SearchParams::A"),
      option::search<&SearchParams::recall_target, nullptr>(
          option::number("recall", "a recall@k to reach instead of A (e.g. 0.95): the index tunes A for this k "
                                   "on a sample of its points (0: use A)", 0, 1, "0")
              .with_keyword("recall_target"),
          "SearchParams::recall_target"),
      option::search<&SearchParams::neighbour_probes, &RadiusParams::neighbour_probes>(
          option::integer("probes", "L tables: 0 the query's cell, 1 and its near-side neighbours (the grid refuses it: its "
                                    "rings need none; -1: the preset decides)", 0, 1, "-1")
              .or_unset(),
          "SearchParams::neighbour_probes"),
      option::search<nullptr, &RadiusParams::budget>(
          option::integer("budget", "examine at most this many points per query (0: every point within the radius "
                                    "on the grid, exact; every block the probes reach on the block layouts)", 0, 4294967295LL, "0"),
          "RadiusParams::budget"),
  };
}

// Options of retired layouts: refused with what replaced them, not skipped as another method's.
void refuse_retired(const MethodOptions& options) {
  if (options.has("cell-aligned"))
    throw Error("blockhash: cell-aligned: the cell-aligned block layout was retired (the grid, auto's default, "
                "answered 1.40-3.64x faster at equal recall on every row of "
                "bench/results/layouts/grid_vs_cells_1M.txt); drop the option for the grid, or use grid=0 for "
                "auto's L tables or preset=paper for the talk's");
}

std::unique_ptr<Index> make(std::shared_ptr<Runtime> runtime, const float* points, std::size_t n_points,
                            const MethodOptions& options) {
  refuse_retired(options);
  // A saved index replaces the build (its build parameters are the saved ones).
  std::unique_ptr<BlockHashIndex> bh;
  const std::string load = options.load_index(), save = options.save_index();
  if (!load.empty()) {
    bh = BlockHashIndex::load(std::move(runtime), load, static_cast<std::int64_t>(n_points));
    // The point set gives the point of every id issued (after removals, a removed id's row is
    // not read): id_bound() rows, size() of them live.
    if (std::size_t(bh->id_bound()) != n_points)
      throw Error(load + ": the saved index holds " + std::to_string(bh->size()) + " points" +
                  (bh->removed_count() ? " of ids 0 .. " + std::to_string(bh->id_bound() - 1) +
                                             " (give a row for every id, removed ones included)"
                                       : std::string()) +
                  ", the point set " + std::to_string(n_points));
    if (long i = bh->first_mismatch(points, n_points); i >= 0)
      throw Error(load + ": the saved index was built from other points (point " + std::to_string(i) + " differs)");
  } else {
    BlockHashBuildParams bp;
    apply_build_options(option_table(), options, &bp, "blockhash");
    bh = BlockHashIndex::build(std::move(runtime), points, n_points, bp);
  }
  if (!save.empty()) bh->save(save);
  return bh;
}

std::string json_bool(bool b) { return b ? "true" : "false"; }
std::string json_real(double x) {
  std::string s = detail::format_general(x, 17);  // "%.17g", locale-free: Python's json reads it
  if (s.find_first_of(".eEn") == std::string::npos) s += ".0";  // stays a real number
  return s;
}
std::string json_text(const std::string& t) {
  std::string s = "\"";
  for (char c : t) s += (c == '"' || c == '\\') ? std::string("\\") + c : std::string(1, c);
  return s + "\"";
}

// After updates (Index::insert/remove) their statistics beside the build's figures (only then: an
// index never updated reports what it did before).
MethodInfo::Used with_updates(const BlockHashIndex& index, MethodInfo::Used u) {
  const BlockHashBuildInfo& i = index.info();
  if (i.holes || i.merges || i.compactions || i.update_rebuilds) {
    u.insert(u.end() - 1, {{"holes", std::to_string(i.holes)},
                           {"merges", std::to_string(i.merges)},
                           {"compactions", std::to_string(i.compactions)},
                           {"update_rebuilds", std::to_string(i.update_rebuilds)},
                           {"retunes", std::to_string(i.retunes)},
                           {"update_seconds", json_real(i.t_update)},
                           {"id_bound", std::to_string(index.id_bound())},
                           {"removed", std::to_string(index.removed_count())}});
  }
  return u;
}

MethodInfo::Used grid_build_fields(const BlockHashBuildInfo& i) {
  return {{"preset", json_text(P::preset_name(i.preset))},
          {"grid", "true"},
          {"grid_dims", "[" + std::to_string(i.grid_dims[0]) + ", " + std::to_string(i.grid_dims[1]) + ", " +
                            std::to_string(i.grid_dims[2]) + "]"},
          {"cell_size", json_real(i.cell_size)},
          {"occupied_cells", std::to_string(i.occupied_cells)},
          {"mean_cell_points", json_real(i.mean_cell_points)},
          {"cells_grown", json_bool(i.grid_capped)},
          {"two_level_directory", json_bool(i.grid_two_level)},
          {"directory_bytes", std::to_string(i.grid_directory_bytes)},
          {"summary", json_text(i.summary())}};
}

MethodInfo::Used table_build_fields(const BlockHashBuildInfo& i) {
  return {{"preset", json_text(P::preset_name(i.preset))},
          {"L", std::to_string(i.L)},
          {"P", std::to_string(i.P)},
          {"B", std::to_string(i.B)},
          {"X", std::to_string(i.X)},
          {"guard_thresholds", json_bool(i.guard_thresholds)},
          {"keep_top_count", json_bool(i.keep_top_count)},
          {"direct_addressing", json_bool(i.direct_addressing)},
          {"box_skip", json_bool(i.box_skip)},
          {"neighbour_probes", json_bool(i.neighbour_probes)},
          {"box_order", json_bool(i.box_order)},
          {"hilbert_seed", std::to_string(i.hilbert_seed)},
          {"n_blocks", std::to_string(i.n_blocks)},
          {"occupied_cells", std::to_string(i.occupied_cells)},
          {"overflowed_buckets", std::to_string(i.overflowed_buckets)},
          {"block_refs", std::to_string(i.block_refs)},
          {"median_cell_points", json_real(i.median_cell_points)},
          {"summary", json_text(i.summary())}};
}

// The A a search ran with (both layouts; the L tables add their probes).
MethodInfo::Used used_A(const BlockHashIndex& bh, const SearchParams& p) {
  if (p.recall_target > 0) {
    // The A the index tuned for this target (cached by the query that ran: no second tuning).
    const BlockHashIndex::RecallTuning t = *bh.recall_tuning(p);
    return {{"recall_target", json_real(p.recall_target)},
            {"A", std::isinf(t.A) ? json_text("inf") : json_real(t.A)},
            {"tuned_sample_recall", json_real(t.recall)},
            {"tuned_reached", json_bool(t.reached)}};
  }
  if (p.A == 0) {
    // The index's default: the exact mode (JSON has no infinity: "exact"), else 8.
    if (bh.exact_mode()) return {{"A", json_text("inf")}, {"exact", "true"}};
    return {{"A", json_real(8.0)}};
  }
  if (std::isinf(p.A)) return {{"A", json_text("inf")}, {"exact", json_bool(bh.exact_mode())}};
  return {{"A", json_real(p.A)}};
}

}  // namespace

const std::vector<OptionInfo>& option_table() {
  static const std::vector<OptionInfo> table = [] {
    std::vector<OptionInfo> t = make_table();
    for (OptionInfo& o : device_search_options()) t.push_back(o);
    return t;
  }();
  return table;
}

namespace {
// The grid's kNN program, before the index (a saved index's layout is known once it is loaded).
void prepare_grid_knn(const Runtime& rt, const MethodOptions& options, const SearchParams& search) {
  if (!options.load_index().empty()) return;
  refuse_retired(options);
  BlockHashBuildParams bp;
  apply_build_options(option_table(), options, &bp, "blockhash");
  BlockHashIndex::prepare_knn(rt, bp, search);
}
}  // namespace

// name, summary, exact, on a device, saves, options, maker; the kNN program ahead of the build.
MethodInfo describe() {
  MethodInfo m{"blockhash", "block hashing (Ma & McCool 2002): exact by default on auto's grid; examines at most A*k points per query with A",
               false, true, true, option_table(), make};
  m.prepare_knn = prepare_grid_knn;
  return m;
}

}  // namespace bhcl::blockhash

namespace bhcl {

UsedFields GridIndex::build_used() const { return blockhash::with_updates(*this, blockhash::grid_build_fields(info_)); }
UsedFields GridIndex::search_used(const SearchParams& p) const { return blockhash::used_A(*this, p); }
UsedFields BlockTablesIndex::build_used() const {
  return blockhash::with_updates(*this, blockhash::table_build_fields(info_));
}
UsedFields BlockTablesIndex::search_used(const SearchParams& p) const {
  UsedFields u = blockhash::used_A(*this, p);
  const int probes = p.neighbour_probes >= 0 ? p.neighbour_probes : (info_.neighbour_probes ? 1 : 0);
  u.emplace_back("neighbour_probes", std::to_string(probes));
  return u;
}

MethodOptions paper_options_for_search(const MethodOptions& options, const SearchParams& params) {
  const std::string preset = options.text("preset", "auto");
  if (preset != "paper" && preset != "paper-cells") return options;
  if (options.has("B") || options.has("design-A") || options.has("design-k")) return options;
  if (!options.load_index().empty()) return options;  // a saved index has its B
  MethodOptions out = options;
  out.set("design-k", std::to_string(params.k));
  const double A = params.recall_target > 0 ? 0.0 : (params.A == 0 ? 8.0 : params.A);
  if (A > 0 && std::isfinite(A)) out.set("design-A", blockhash::json_real(A));
  return out;
}

}  // namespace bhcl
