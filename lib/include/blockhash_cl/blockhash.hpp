// Block Hashing (Ma & McCool, Graphics Hardware 2002): approximate kNN through locality-sensitive
// hash tables of 256-byte blocks of points, answered by an OpenCL kernel, one work-item per query.
// One method (`blockhash`), two algorithms, each its own class behind BlockHashIndex::build: the
// grid (GridIndex, blockhash_cl/grid_index.hpp) and the L tables (BlockTablesIndex,
// blockhash_cl/block_tables.hpp). Presets (docs/DESIGN.md, "Block hashing, as we build it"):
//   auto   (default) the grid layout, the talk's "alternative clustering" future work
//          (docs/DESIGN.md, "The grid"): the blocks are the cells of one grid of equal cubic cells
//          (side from a sample, so that a point's cell holds ~24 points), the points sorted by
//          cell with a parallel counting sort (no Hilbert sort), the cells of a row adjacent in
//          memory. A query scans the rings of rows around its cell, each row one contiguous run
//          clipped to the current k-th distance, and stops exactly once the k-th sphere lies
//          inside the rings visited, or once A k points are examined (kernels/grid_search.h,
//          kernels/blockhash_grid_knn.cl). Past the first rings, a query far from the points
//          walks an occupancy pyramid over the cells instead (one bit test per empty node).
//          A = +inf (or recall_target = 1) is an exact mode.
//   paper  the talk's scheme and defaults: L = P = round(ln N), X = 10, B = ceil(A k / (X ln N)) + 1
//          for the design A and k, direct addressing of all (P+1)^3 cells, a full bucket drops
//          new blocks, no neighbour probes, no bounding-box skipping (kernels/blockhash_knn.cl).
//          B is fixed at build: set design_A and design_k to the A and k the queries will use
//          (bhcl render and blockhash_accuracy do), a larger A examines no more than B allows.
//   paper-cells  paper with one departure (docs/ACCURACY.md, "Where the talk's rules do not
//          carry over"): P is chosen from the data so that the median occupied cell holds about
//          design_k / 4 points (a cell's side then about the k-th neighbour distance) instead of
//          ln N, and the buckets are in a directory of the occupied cells (memory only: the same
//          buckets). On surfaces P = ln N makes cells of hundreds of points that B blocks only
//          sample.
// The L tables with auto's rules (grid = 0; their fields L, P, B, X, box_order, ... are refused on
// the grid, the grid's on them): the talk's L-table layout with guarded thresholds, a directory of
// the occupied cells, neighbour probes and box-ordered scans (kernels/blockhash_knn.cl). The
// layout of blocks aligned to one table's cells, auto's default before the grid, was retired: the
// grid answered 1.40-3.64x faster at equal recall on every measured row
// (bench/results/layouts/grid_vs_cells_1M.txt).
// Every derived value can be overridden (-1 = derive). Query parameters (k, A or recall_target,
// max_radius, neighbour_probes) live in SearchParams; a query examines at most ceil(A k) points
// (counted over the runs or blocks it scans: a run is scanned while fewer were examined before it)
// and returns the k nearest of them under the result contract. Distances are squared.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <tuple>
#include <string>
#include <vector>

#include "blockhash_cl/knn.hpp"
#include "blockhash_cl/options.hpp"

namespace bhcl {

namespace detail {
class KernelArgs;
}
namespace blockhash {
struct Structure;  // the host copy of every built array (lib/src/blockhash/build.hpp)
}

// The user's parameters of either layout (the option table, lib/src/blockhash/options.cpp, fills
// them): BlockHashIndex::build refuses the other layout's fields and hands the chosen one its own
// (GridBuildParams, TableBuildParams).
struct BlockHashBuildParams {
  enum class Preset { Auto, Paper, PaperCells };
  Preset preset = Preset::Auto;
  int L = -1;  // tables
  int P = -1;  // thresholds per dimension (cells per dimension: P + 1), <= 1024
  int B = -1;  // block references per bucket
  int X = -1;  // points per block, 1..16 (16 fills the 256-byte block)
  // auto and paper-cells: P is chosen so that the median occupied cell holds about this many
  // points (-1: the grid 24 per point's cell, auto's L tables 100; paper-cells design_k / 4).
  double target_cell_points = -1.0;
  // auto: B is this percentile of the distinct blocks touching an occupied cell.
  double b_percentile = 0.90;
  // paper presets: B follows the talk's rule B > A k / (X ln N) for this design A and k (B is
  // fixed at build: a query with a larger A k examines no more); paper-cells: the median occupied
  // cell holds about design_k / 4 points (target_cell_points overrides it).
  double design_A = 8.0;
  int design_k = 10;
  int hist_bins = 1024;       // histogram bins per dimension for the threshold CDFs
  int hilbert_bits = 21;      // bits per dimension of the Hilbert keys (3 x 21 = 63-bit keys)
  // -1 = preset default (paper: off; auto: on).
  int guard_thresholds = -1;  // snap to bin edges, de-duplicate, keep off heavy bins
  int keep_top_count = -1;    // overflow keeps the blocks holding most of the cell's points
  int direct_addressing = -1; // all (P+1)^3 cells (paper) vs occupied cells only (auto)
  int box_skip = -1;          // skip blocks whose bounding box is farther than the k-th distance
  // Scan order of the gathered blocks: 0 = bucket order (the talk's, GPU-friendly), 1 = ascending
  // bounding-box distance with an early stop (docs/DESIGN.md, "The CPU form (box order)"; needs no box_skip).
  int box_order = -1;
  // Box order: also gather the blocks around the query's own Hilbert key (binary search over the
  // blocks' first keys), this many on each side (at least enough for k points); 0 = off. A query
  // whose cells are all empty (far from the data) still gets k answers. -1: auto 1, paper 0.
  int hilbert_seed = -1;
  int neighbour_probes = -1;  // default for SearchParams::neighbour_probes == -1 (block layouts)
  // The layout: -1 the preset's (auto: the grid; paper: its tables), 0 auto's L tables, 1 the
  // grid. A field of another layout than the one chosen is refused (bhcl::Error), never ignored.
  int grid = -1;
  // Grid: the cells' side in the points' units (> 0), or -1 to choose it from a sample so that
  // the point-weighted mean cell population is target_cell_points (-1: the device's kernel form's
  // cell_target, kernel_forms.hpp: 24 on every row so far).
  double cell_size = -1;
  // Grid: the most cells per point of the direct cell table; past it the directory is two-level
  // (up to 16x as many cells: 4 bytes per 16 cells plus 64 per occupied 16), past that the cells
  // grow to fit.
  double max_cells_per_point = 8;
  // Grid: the cell directory. -1: by the rule above; 0: direct only (the cells grow to fit);
  // 1: two-level always.
  int grid_directory = -1;
  unsigned threads = 0;       // build threads (0: all hardware threads)
  std::uint64_t seed = 1;     // threshold jitter (a different jitter per table)
  bool verbose = false;       // progress of the build stages on stderr

  static Preset parse_preset(const std::string& name);  // "auto" | "paper" | "paper-cells"; throws otherwise
  static const char* preset_name(Preset p);
  // The talk's L tables (paper, paper-cells), not auto's layouts.
  static bool is_paper(Preset p) { return p == Preset::Paper || p == Preset::PaperCells; }
};

// The values a build actually used (derived ones filled in) and what it cost.
struct BlockHashBuildInfo {
  BlockHashBuildParams::Preset preset = BlockHashBuildParams::Preset::Auto;
  int L = 0, P = 0, B = 0, X = 0;
  bool guard_thresholds = false, keep_top_count = false, direct_addressing = false;
  bool box_skip = false, neighbour_probes = false, box_order = false;
  int hilbert_seed = 0;
  // Grid layout: cells per axis, their side (index coordinates, see knn.hpp's scaling), the
  // point-weighted mean population, whether the cells were grown to fit the table, stage times.
  bool grid = false;
  int grid_dims[3] = {0, 0, 0};
  double cell_size = 0;
  double mean_cell_points = 0;
  bool grid_capped = false;
  bool grid_two_level = false;           // the two-level directory (grid_search.h)
  std::size_t grid_directory_bytes = 0;  // the directory's size
  double t_tune = 0, t_cells = 0, t_count = 0, t_scatter = 0;
  double t_occupancy = 0;                // the grid's occupancy pyramid (the far-query skip)
  std::size_t n_points = 0, n_blocks = 0;
  std::size_t occupied_cells = 0;      // over all tables
  std::size_t overflowed_buckets = 0;  // over all tables
  std::size_t block_refs = 0;          // stored references (paper: used slots), all tables
  double median_cell_points = 0;       // table 0, occupied cells
  double median_cell_blocks = 0;       // table 0: distinct blocks touching an occupied cell
  double p90_cell_blocks = 0;
  // Stage timings (seconds) and the total.
  double t_hilbert = 0, t_blocks = 0, t_params = 0, t_thresholds = 0, t_tables = 0, t_upload = 0;
  double t_total = 0;
  // Updates (Index::insert/remove; lib/src/blockhash/grid_update.cpp). holes: removed points
  // still stored (grid: +inf coordinates, dropped by the next merge or compaction); merges:
  // inserts sorted into the existing cells; compactions; update_rebuilds: full builds updates
  // made, at most one per update (grid: points outside the grid's box, an insert into the
  // two-level directory, or a mean cell population past 1.1x / below 0.9x of the tuned one, each
  // a fresh build over the live points with the build's own parameters; block layouts: every
  // update); retunes: those rebuilds the band caused or whose cell side changed; t_update:
  // seconds spent in updates so far.
  std::size_t holes = 0, merges = 0, compactions = 0, update_rebuilds = 0, retunes = 0;
  double t_update = 0;
  std::string summary() const;  // one line
};

// Block hashing's family: what the grid (GridIndex, blockhash_cl/grid_index.hpp) and the L
// tables (BlockTablesIndex, blockhash_cl/block_tables.hpp) share: the built structure and its
// info, the coordinate scaling, the recall tuning and its caches, the batch tuning and its exact
// kd-tree, save / load dispatch and the host reference's path. What differs is virtual.
class BlockHashIndex : public Index {
 public:
  // The one way to build block hashing from the user's parameters: the layout they choose (the
  // grid by default and for grid = 1; grid = 0 or a paper preset the L tables), built from that
  // layout's own parameters; a field of the other layout is refused with a bhcl::Error naming it.
  // points: N x 3 floats in the caller's order (copied). Throws for N == 0, N >= 2^31,
  // non-finite points or parameters out of range.
  static std::unique_ptr<BlockHashIndex> build(std::shared_ptr<Runtime> runtime, const float* points,
                                               std::size_t n_points, const BlockHashBuildParams& params = {});
  // Builds ahead, on rt, the kNN program a query with `search` on the index build(params) makes
  // will use, where the layout's program does not depend on the points (the grid); else nothing.
  // Throws what build would for bad parameters.
  static void prepare_knn(const Runtime& rt, const BlockHashBuildParams& params, const SearchParams& search);
  ~BlockHashIndex() override;

  // A saved index (versioned, checksummed), as the class its file holds. Throws bhcl::Error naming
  // the file and the field for a missing, truncated, corrupt or foreign file. rows >= 0: the
  // caller's point count, which must be the file's id bound; checked before the index allocates
  // anything by that bound (its id table).
  static std::unique_ptr<BlockHashIndex> load(std::shared_ptr<Runtime> runtime,
                                              const std::string& path, std::int64_t rows = -1);
  bool saves() const override { return true; }
  // rebuild(): the next frame's points with this build's parameters (the grid keeps its cell
  // side), the host and device arrays reused (no reallocation when n and the cell count do not
  // grow): the same answers as a fresh build with those parameters. The L tables: a fresh build
  // with the same build parameters. Not safe concurrently with queries on this index.
  bool rebuilds_in_place() const override { return true; }

  // The first caller index whose point differs from the indexed one (bit for bit), -1 when the
  // index holds exactly these n points, -2 when n is not id_bound() (no point compared). points
  // holds a row per id issued; after removals a removed id's row is not compared. A loaded index
  // is checked against the caller's points.
  long first_mismatch(const float* points, std::size_t n) const;

  std::string method() const override { return "blockhash"; }
  bool exact() const override { return false; }
  // Whether A = +inf is an exact search and the default (A = 0) is it (the grid's rings); where
  // not (the L tables), A = 0 means 8 and A must be finite.
  virtual bool exact_mode() const = 0;
  // memory_bytes(): every device array, points included. host_bytes(): host memory the index
  // keeps besides them (its reference search, save() and first_mismatch() read it). On PoCL both
  // are the process's memory; the Python package's memory_bytes reports their sum.
  std::string build_summary() const override { return info_.summary(); }
  double memory_per_point() const { return double(memory_bytes()) / double(size()); }
  // The talk's memory overhead (4 (Ak/X)(ln N)^3 + 12 (ln N)^2 + 1.6 N) / 24N, and ours measured
  // the same way: bytes beyond the points' own (24 B per talk photon) over 24 N.
  static double talk_overhead(std::size_t N, double A, int k, int X);
  virtual double measured_overhead() const = 0;

  const BlockHashBuildInfo& info() const { return info_; }
  int L() const { return info_.L; }
  int P() const { return info_.P; }
  int B() const { return info_.B; }
  int X() const { return info_.X; }

  // The host reference of the query: the same candidates in the same order and the same float
  // arithmetic as the kernel, so its results equal the kernel's bit for bit. It takes query()'s
  // path (validation, recall target, coordinate scaling: distances in the caller's units).
  // examined (optional) gets the points examined per query. threads 0 = all hardware threads.
  KnnResult reference_query(const float* queries, std::size_t n, const SearchParams& params,
                            std::vector<std::int32_t>* examined = nullptr,
                            unsigned threads = 0) const;

  // A recall target instead of a budget. From `sample` of the indexed points (every N/sample-th,
  // each moved off its point by half the distance to its nearest other point, so that it is not
  // its own answer), their exact k nearest (the kd-tree kernel) and the block-hash answers for
  // A in {1, 1.5, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 128}, picks the smallest A whose recall@k
  // on the sample reaches target. reached is false (and A the largest) when none does.
  using RecallTuning = bhcl::RecallTuning;
  RecallTuning tune_for_recall(double target, const SearchParams& params,
                               std::size_t sample = 2000) const;
  // The tuning a query with params.recall_target > 0 uses: computed on first use per (k, probes,
  // target), without the radius, and cached.
  std::optional<RecallTuning> recall_tuning(const SearchParams& params) const override;

  // Recall on the caller's queries. The search parameters a host-array batch should run with:
  // when a recall is asked (params.recall_target in (0, 1)), or when neither A nor a target is
  // given on a layout where a budget applies (the L tables; their default target is
  // kDefaultRecallTarget), A is tuned on a sample of THIS batch: at most 2000 of its finite
  // queries, evenly spread over it, and at most an eighth of it (the bound on the tuning's share
  // of the call; at least min(n, 256)), answered exactly by a kd-tree over the indexed points
  // (built once per index) and by block hashing at A of tune_for_recall's ladder carried on to
  // 1024, searched by bisection (recall grows with A; about 5 passes instead of up to 17): the
  // smallest A whose recall@k on the sample clears the target by 1.5 standard errors wins. The
  // result is cached per (k, probes, target, the batch's distribution: its box within the
  // index's box, quantised to eighths, and the sample's median distance to its nearest indexed
  // point over the points' mean spacing, quantised to half octaves), so a later batch of the
  // same kind costs the signature only. Returns params with A set and recall_target 0; `info`
  // (optional) says what was done. Other parameters (an explicit A, the grid's exact default)
  // come back as they are. Index::query itself keeps A = 0 as 8 on the L tables (its callers'
  // parameters are not changed under them): the Python package and bhcl call this.
  static constexpr double kDefaultRecallTarget = 0.95;
  using BatchTuning = bhcl::BatchTuning;
  SearchParams params_for_batch(const float* queries, std::size_t n, const SearchParams& params,
                                BatchTuning* info = nullptr) const override;

  // ceil(A k): the points a query may examine.
  static std::uint32_t budget(const SearchParams& params);

  const blockhash::Structure& structure() const { return *s_; }
  // SearchParams::count_examined: every query's examined points come back with its row.
  bool counts_examined() const override { return true; }

 protected:
  // A build: an empty structure for n points. A load: the saved structure, its scale kept.
  BlockHashIndex(std::shared_ptr<Runtime> runtime, std::size_t n_points);
  BlockHashIndex(std::shared_ptr<Runtime> runtime, std::unique_ptr<blockhash::Structure> s);

  // Updates: the shared part (the device idle, the recall tunings dropped, the time counted)
  // around the layout's own.
  BHCL_INDEX_UPDATE_HOOKS
  virtual void insert_stored(const float* points, const float* scaled, std::size_t n, std::int32_t first) = 0;
  virtual void remove_stored(const std::int32_t* ids, std::size_t n) = 0;
  // The host reference on queries and parameters already in the structure's coordinates.
  virtual void reference_scaled(const float* queries, std::size_t n, const SearchParams& params, KnnResult& out,
                                std::vector<std::int32_t>* examined, unsigned threads) const = 0;
  // first_mismatch() past the size check; every stored point (id and the structure's
  // coordinates), holes skipped.
  virtual long first_stored_mismatch(const float* points) const = 0;
  using PointVisitor = std::function<void(std::int32_t id, float x, float y, float z)>;
  virtual void visit_stored_points(const PointVisitor& visit) const = 0;

  // The opening of both layouts' builds: the points validated (extreme scales: a rescaled copy in
  // `scaled`), the structure's size and scale set; returns the points to build from.
  const float* begin_build(const float* points, std::size_t n_points, std::vector<float>& scaled);
  // A saved file's id bound against the caller's rows (load's rows), before anything is sized by it.
  static void check_rows(const std::string& path, std::int64_t rows, std::int64_t bound, std::size_t live);
  // SearchParams::recall_target: the A tuned per (k, probes, target), computed on first use; A = 0
  // the layout's default (exact_mode()). resolved(): params with that A and no target.
  float resolved_A(const SearchParams& params) const;
  SearchParams resolved(const SearchParams& params) const;
  // The indexed points in ascending id order and the caller's coordinates; ids (optional) gets
  // their ids (0 .. N - 1 unless updates removed some).
  std::vector<float> indexed_points(std::vector<std::int32_t>* ids = nullptr) const;
  // The one-int buffer a kernel's unused examined-count argument points at.
  void upload_dummy();
  // Radius search, one dispatch for both layouts: the layout's kernel (its name and the library's
  // defines) and the arguments it begins with, then the budget and the radius arguments.
  cl::Event enqueue_radius_batch(const cl::CommandQueue& queue, const cl::Buffer& queries, std::size_t first,
                                 std::size_t count, float r2, int pass, const RadiusBuffers& out,
                                 const RadiusParams& params, std::size_t local_size,
                                 const std::vector<cl::Event>* wait) const override;
  struct RadiusKernel {
    const char* name;
    std::vector<std::pair<const char*, long long>> defines;
  };
  virtual RadiusKernel radius_kernel() const = 0;
  virtual void add_radius_layout_args(detail::KernelArgs& args, const RadiusParams& params) const = 0;
  // The kernel `name` (in name.cl) with the library's defines and the caller's (kernel_defines.hpp).
  cl::Kernel layout_kernel(const char* name, const std::vector<std::pair<const char*, long long>>& defines,
                           const std::string& caller_defines) const;
  // The arguments a kNN kernel ends with: the results and the examined counts (or the dummy).
  void add_knn_results(detail::KernelArgs& args, const ResultBuffers& out, bool count_examined) const;

  std::unique_ptr<blockhash::Structure> s_;
  BlockHashBuildInfo info_;
  cl::Buffer dummy_;

 private:
  // Drops every tuning and the exact kd-tree they were checked against: they belong to the point
  // set they were measured on (every build, rebuild, insert and remove calls it).
  void forget_tunings();
  mutable std::mutex tune_mutex_;
  mutable std::map<std::tuple<int, int, double>, RecallTuning> tuned_;
  // params_for_batch: tunings per (k, probes, target, distribution), and the exact kd-tree
  // (over indexed_points(), built on the first tuning) they are checked against.
  mutable std::map<std::tuple<int, int, double, std::string>, RecallTuning> batch_tuned_;
  mutable std::shared_ptr<const Index> exact_;
  mutable std::vector<std::int32_t> exact_ids_;  // exact_'s point i is the index's id exact_ids_[i]
  mutable double exact_box_[6] = {0, 0, 0, 0, 0, 0};  // the indexed points' box (lo, hi)
  mutable double exact_spacing_ = 0;                  // their mean spacing (box measure / N)^(1/d)
};

// What each layout (GridIndex, BlockTablesIndex) implements: BHCL_BLOCKHASH_LAYOUT_API in its
// public part, BHCL_BLOCKHASH_LAYOUT_HOOKS in its protected part.
#define BHCL_BLOCKHASH_LAYOUT_API                                                                   \
  void save(const std::string& path) const override;                                               \
  void rebuild(const float* points, std::size_t n_points) override;                                \
  std::size_t memory_bytes() const override;                                                        \
  std::size_t host_bytes() const override;                                                          \
  double measured_overhead() const override;                                                        \
  UsedFields build_used() const override; /* blockhash/options.cpp */                               \
  UsedFields search_used(const SearchParams& params) const override;
#define BHCL_BLOCKHASH_LAYOUT_HOOKS                                                                 \
  cl::Event enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries, std::size_t first, \
                          std::size_t count, const ResultBuffers& out, const SearchParams& params,  \
                          std::size_t local_size, const std::vector<cl::Event>* wait) const override; \
  RadiusKernel radius_kernel() const override;                                                      \
  void add_radius_layout_args(detail::KernelArgs& args, const RadiusParams& params) const override; \
  void check_params(const SearchParams& params) const override;                                     \
  void insert_stored(const float* points, const float* scaled, std::size_t n, std::int32_t first)  \
      override;                                                                                     \
  void remove_stored(const std::int32_t* ids, std::size_t n) override;                              \
  void reference_scaled(const float* queries, std::size_t n, const SearchParams& params, KnnResult& out, \
                        std::vector<std::int32_t>* examined, unsigned threads) const override;      \
  long first_stored_mismatch(const float* points) const override;                                   \
  void visit_stored_points(const PointVisitor& visit) const override;

// The paper presets size B at build from design_A and design_k (the talk: B > A k / (X ln N)),
// so a query with a larger A k than the build's examines no more. For a search of `params` the
// options of a block-hashing build sized for it: design-A = the A asked (the index default, 8,
// for A = 0; unchanged for A = inf or a recall target, which have no A at build) and design-k =
// its k, where the preset is paper or paper-cells and the caller set none of B, design-A and
// design-k. Other presets and methods: `options` unchanged.
MethodOptions paper_options_for_search(const MethodOptions& options, const SearchParams& params);

}  // namespace bhcl
