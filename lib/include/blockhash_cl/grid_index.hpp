// The grid layout of block hashing, the auto preset's default (docs/DESIGN.md, "The grid"): the
// blocks are the cells of one grid of equal cubic cells, the points sorted by cell; a query scans
// the rings of rows around its cell and stops exactly once its k-th sphere lies inside the rings
// visited, or once A k points are examined (kernels/grid_search.h, kernels/blockhash_grid_knn.cl).
// A = +inf (the default, or recall_target = 1) is exact. Points are inserted and removed in place
// (lib/src/blockhash/grid_update.cpp).
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/blockhash.hpp"

struct bhcl_grid_dbox;  // a box of points (kernels/grid_search.h)

namespace bhcl {

namespace blockhash {
struct GridIdState;    // a grid file's ids and update state (lib/src/blockhash/grid_io.hpp)
struct GridTraversal;  // the grid traversal's form (lib/src/blockhash/grid.hpp)
struct GridInput;      // a build's points (lib/src/blockhash/grid.hpp)
}  // namespace blockhash

// The grid's own build parameters (BlockHashBuildParams' grid fields; the same meanings).
struct GridBuildParams {
  // The cells' side in the points' units (> 0), or -1 to choose it from a sample so that the
  // point-weighted mean cell population is target_cell_points (-1: the device's kernel form's
  // cell_target, kernel_forms.hpp: 24 on every row so far).
  double cell_size = -1;
  double target_cell_points = -1;
  // The most cells per point of the direct cell table; past it the directory is two-level (up
  // to 16x as many cells: 4 bytes per 16 cells plus 64 per occupied 16), past that the cells
  // grow to fit.
  double max_cells_per_point = 8;
  // The cell directory. -1: by the rule above; 0: direct only (the cells grow to fit); 1: two-level.
  int grid_directory = -1;
  unsigned threads = 0;  // build threads (0: all hardware threads)
  bool verbose = false;  // the build's summary on stderr
};

class GridIndex final : public BlockHashIndex {
 public:
  // points: N x 3 floats in the caller's order (copied), the cells tuned on them unless
  // params.cell_size fixes the side. Throws for N == 0, N >= 2^31, non-finite points or
  // parameters out of range.
  GridIndex(std::shared_ptr<Runtime> runtime, const float* points, std::size_t n_points,
            const GridBuildParams& params = {});
  ~GridIndex() override;

  bool exact_mode() const override { return true; }  // the rings stop exactly at A = +inf
  const GridBuildParams& params() const { return params_; }
  // rebuild(): the next frame with this build's cell side and table limits, the arrays reused.
  BHCL_BLOCKHASH_LAYOUT_API
  // Builds the kNN program a query with `params` on rt uses: it depends on the device and k, not
  // on the points, so it can be built before (or beside) the index (prepare_knn, factory.hpp).
  static void prepare_knn_program(const Runtime& rt, const SearchParams& params);

  // The device's kernel form's work-group size where it sets one, else the quirks'.
  std::size_t default_local_size() const override;

 protected:
  BHCL_BLOCKHASH_LAYOUT_HOOKS

 private:
  friend class BlockHashIndex;  // load() makes a loaded grid
  GridIndex(std::shared_ptr<Runtime> runtime, std::unique_ptr<blockhash::Structure> s);
  static std::unique_ptr<GridIndex> load_saved(std::shared_ptr<Runtime> runtime, const std::string& path,
                                               std::int64_t rows);
  void build_layout(const float* points, std::size_t n_points, double cell_size);
  // The grid from points in the structure's coordinates (scale set, points known finite; an
  // update's rebuild reads the old grid's arrays in place). t0: when the build began (t_total).
  void build_scaled(const blockhash::GridInput& input, double cell_size,
                    std::chrono::steady_clock::time_point t0 = std::chrono::steady_clock::now());
  void upload_grid();
  // Host-in-place devices (Quirks::host_ptr_in_place): the grid's buffers are views of its host
  // arrays, dropped before the host changes those arrays (a build, an update) and made again after.
  bool grid_in_place() const;
  void release_grid_views();
  // The library's defines of the kNN kernel variant of at most kmax on rt's device
  // (kernel_defines.hpp).
  static std::vector<std::pair<const char*, long long>> kernel_options(const Runtime& rt, int kmax);
  void add_grid_args(detail::KernelArgs& args) const;
  // The traversal the kNN kernel runs for p (the device's form, a caller's defines over it): the
  // host reference follows the same.
  blockhash::GridTraversal traversal_for(const SearchParams& p) const;

  // Updates (grid_update.cpp).
  void grid_insert(const float* scaled, std::size_t n, std::int32_t first);
  void grid_insert_two_level(const float* scaled, std::size_t n, std::int32_t first);  // merged, not rebuilt
  void grid_remove(const std::int32_t* ids, std::size_t n);
  void grid_compact();  // drops the holes, in place
  // extra: m points in the structure's coordinates, ids first ...
  void grid_rebuild_live(const float* extra, std::size_t m, std::int32_t first, bool retune);
  void grid_upload_from(std::size_t point_from, std::size_t cell_from);
  void grid_positions();  // id -> position, from the grid's ids
  // The removed ids' slots found by one pass over the stored ids (many ids, or no position map).
  // faces: the sides of the points' box a removed point lay on (blockhash::box_faces_of).
  void grid_mark_holes_by_scan(const std::int32_t* ids, std::size_t n, std::size_t& lo, std::size_t& hi,
                               unsigned& faces);
  // Save / load after updates (grid_update.cpp): the state a grid file keeps, and the id state,
  // holes and counters of a loaded file.
  blockhash::GridIdState grid_update_state() const;
  void loaded_update_state(const blockhash::GridIdState& st);
  std::vector<std::int32_t> id_pos_;  // after updates: id -> sorted position (-1: none)
  double grid_build_mean_ = 0;        // the mean cell population of the last full build
  std::size_t grid_builds_ = 0;       // builds made (the constructor's, rebuilds, updates')

  GridBuildParams params_;
  // starts, x, y, z, ids, the occupancy pyramid (grid_search.h) and their capacities.
  cl::Buffer g_starts_, g_x_, g_y_, g_z_, g_ids_, g_occ_;
  std::size_t g_starts_cap_ = 0, g_points_cap_ = 0, g_occ_cap_ = 0;
};

// The grid index keeps the large host arrays (4 MiB and up) it frees, up to min(512 MiB, an
// eighth of physical memory), and reuses them for the next arrays that fit: pages a process gave
// back can be slow to touch again (on a VM that reports free pages to its host, a third or more
// of a rebuild's time). BHCL_HOST_CACHE_MB sets the bound in MiB (0: no cache), read once.
// release_host_cache frees what the cache holds now and returns the bytes released. Thread-safe.
std::size_t release_host_cache();

}  // namespace bhcl
