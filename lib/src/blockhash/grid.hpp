// Block hashing, grid layout (the auto preset): the built arrays, the counting-sort build, the
// host reference of the query and save/load. The layout and the search are described in
// kernels/grid_search.h, which the kernels and the host reference share.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <new>
#include <string>
#include <utility>
#include <vector>

#include "blockhash_cl/knn.hpp"
#include "grid_search.h"

namespace bhcl::blockhash {

// Entries past the last point in x, y, z (+inf) and ids (-1), so that a 16-lane load at any point
// stays inside the arrays.
inline constexpr std::size_t kGridPad = 16;

// A vector whose resize leaves new elements uninitialised (the build writes every element in
// parallel: a serial zero fill first would only cost time and fault every page on one core), and
// whose large arrays sit on transparent huge pages where the system offers them (the build's
// scatters write to hundreds of places at once: with 4 KiB pages each is a TLB miss).
// Large blocks (4 MiB and up) freed are kept, up to a bound, for the next allocation that fits
// (grid_memory.cpp: a rebuild's fresh pages cost a third or more of it on this VM); `bytes` is
// the size the block was allocated with.
void* grid_allocate(std::size_t bytes);
void grid_deallocate(void* p, std::size_t bytes) noexcept;
// The cache of freed large blocks (grid_memory.cpp; bhcl::release_host_cache empties it): its
// bound set (bytes, 0: no cache; BHCL_HOST_CACHE_MB sets it once, at first use), the blocks over
// it freed oldest first, the old bound returned; and what it holds.
std::size_t host_cache_set_limit(std::size_t bytes);
struct HostCacheState {
  std::size_t bytes = 0, blocks = 0, limit = 0;
};
HostCacheState host_cache_state();
// The bound BHCL_HOST_CACHE_MB's value `env` sets: env MiB, or where env is null, empty or not
// a number, min(512 MiB, an eighth of physical memory).
std::size_t host_cache_limit_from(const char* env);
template <typename T>
struct NoInitAllocator {
  using value_type = T;
  NoInitAllocator() = default;
  template <typename U>
  NoInitAllocator(const NoInitAllocator<U>&) {}
  T* allocate(std::size_t n) {
    if (n > std::size_t(-1) / sizeof(T)) throw std::bad_alloc();
    return static_cast<T*>(grid_allocate(n * sizeof(T)));
  }
  void deallocate(T* p, std::size_t n) noexcept { grid_deallocate(p, n * sizeof(T)); }
  template <typename U, typename... Args>
  void construct(U* p, Args&&... args) {
    if constexpr (sizeof...(Args) == 0) ::new (static_cast<void*>(p)) U;
    else ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
  }
  template <typename U>
  bool operator==(const NoInitAllocator<U>&) const { return true; }
  template <typename U>
  bool operator!=(const NoInitAllocator<U>&) const { return false; }
};
template <typename T>
using GridVec = std::vector<T, NoInitAllocator<T>>;

// The build's scratch, kept with the grid so that a rebuild allocates nothing.
struct GridScratch {
  GridVec<std::uint32_t> cell;     // each input point's cell
  GridVec<float> rec;              // (x, y, z, index bits) per point, bucketed by cell range
  GridVec<float> x, y, z;          // an insert's merged arrays (grid_update.cpp), then swapped
  GridVec<std::int32_t> ids;       //   with the grid's
  GridVec<std::uint32_t> count;    // an insert's per-range cell counts (grid_update.cpp)
  GridVec<std::uint32_t> add;      // an insert's new points before each cell
};

struct Grid {
  bhcl_grid_geom geom{};
  std::size_t n_points = 0;
  // The directory (grid_search.h): direct, ncells + 1 entries, or two-level (geom.sparse).
  GridVec<std::uint32_t> starts;
  GridVec<float> x, y, z;          // n + kGridPad, sorted by cell (ties by caller index)
  GridVec<std::int32_t> ids;       // n + kGridPad: the caller's index of each sorted point
  // The occupancy pyramid (grid_search.h): rebuilt from the directory by build_grid_occupancy
  // whenever the cells change (build, load, insert, compaction); not saved.
  GridVec<std::uint8_t> occ;
  // The box of the live points (grid_search.h); no clipping until set.
  bhcl_grid_dbox dbox{-INFINITY, -INFINITY, -INFINITY, INFINITY, INFINITY, INFINITY};
  std::shared_ptr<GridScratch> scratch;  // build only; not saved, not uploaded
  std::size_t ncells() const { return std::size_t(geom.nx) * geom.ny * geom.nz; }
  // The first sorted point of cell c (c = ncells: n_points), through the directory.
  std::uint32_t start(std::size_t c) const {
    return bhcl_grid_start(starts.data(), geom.sparse, static_cast<std::uint32_t>(c));
  }
  // The directory's entry count for this geometry and, when two-level, its occupied segments.
  static std::size_t top_entries(std::size_t ncells) { return (ncells >> BHCL_GRID_SEG_BITS) + 1; }
  std::size_t device_bytes() const {
    return starts.size() * 4 + (x.size() + y.size() + z.size()) * 4 + ids.size() * 4 + occ.size();
  }
  // Every invariant the kernel relies on; throws bhcl::Error naming `what` and the first violation.
  void validate(const std::string& what) const;
};

struct GridBuildArgs {
  double cell_size = -1;        // > 0: this side; else chosen from target_cell_points
  double target_cell_points = 24;  // the point-weighted mean cell population aimed at
  std::size_t sample = 16384;   // points the tuning looks at
  // The most cells per point of a direct table. Past it the directory is two-level (up to 16x
  // as many cells) and past that the cells grow until it fits.
  double max_cells_per_point = 8;
  int directory = -1;           // -1: by the rule above; 0: direct (cells grow); 1: two-level
  unsigned threads = 0;         // 0: all hardware threads
};

struct GridBuildStats {
  double t_tune = 0, t_cells = 0, t_count = 0, t_scatter = 0, t_occupancy = 0;
  std::size_t occupied = 0;     // cells holding at least one point
  std::size_t occupied_segments = 0;  // two-level directory: segments holding a point
  double mean_cell_points = 0;  // point-weighted mean population (each point's cell, averaged)
  bool capped = false;          // the cells were grown to fit max_cells_per_point
  bool from_cells = false;      // sorted from the SoA part's cell order (GridInput::soa_in_cells)
};

// A build's points (in the index's coordinates), in two parts taken in this order: first a
// structure-of-arrays part (an existing grid's arrays, holes dropped: an update's rebuild reads
// them where they are instead of gathering a copy), then an array-of-structures part (x, y, z per
// point). The ids stored: soa_ids[i], then aos_ids[i] (null: aos_first + i where aos_first >= 0,
// an update's consecutive new ids without an array of them; else the point's index in the whole
// input).
struct GridInput {
  const float *x = nullptr, *y = nullptr, *z = nullptr;
  const std::int32_t* soa_ids = nullptr;
  std::size_t n_soa = 0;
  float soa_lo[3] = {0, 0, 0}, soa_hi[3] = {0, 0, 0};  // a box holding the SoA part (with n_soa)
  const float* xyz = nullptr;
  const std::int32_t* aos_ids = nullptr;
  std::int64_t aos_first = -1;
  std::size_t n_aos = 0;
  // Called once the build has read the points (before it sizes its arrays): an update's rebuild
  // frees the old grid's arrays there, so that the new ones may take their memory.
  std::function<void()> release;
  // The SoA part is a grid's points in cell order (an update's rebuild): a direct table is then
  // sorted straight into the arrays, no records (build_grid), reading the input twice, so
  // release() comes once the points are placed and must leave g's arrays alone.
  bool soa_in_cells = false;
  std::size_t size() const { return n_soa + n_aos; }
};

// Builds g from the points. g's vectors keep their capacity (rebuilds allocate nothing when n and
// the cell count do not grow; past it they are freed, not copied); in must not point into g. The
// cell side's sample is strided over an AoS-only input (a caller's order), drawn at random
// positions of the SoA part (cell order: a stride there is a stratified sample, which gave 34
// points per cell for a target of 24).
void build_grid(const GridInput& in, const GridBuildArgs& p, Grid& g, GridBuildStats* stats);

// The occupancy pyramid's bytes for a geometry, and its build from g's directory (all of it, in
// parallel over `threads`: 0 all); every path that adds points to cells calls it.
std::size_t grid_occupancy_bytes(const bhcl_grid_geom& g);
void build_grid_occupancy(Grid& g, unsigned threads);
// The pyramid built in the bucket passes' placement (build_grid, direct directory): each worker
// places a contiguous range of buckets and, bucket by bucket while its cells and points are in
// cache, sets the level-1 bits and widens the level-2 boxes of the level-2 z slabs its range holds
// whole, in g.occ itself (no two workers share a slab). finish then makes the slabs no range held
// whole (at most one per pair of adjacent ranges) from the directory, and the levels above. The
// pass over the directory and the points it replaces read 25 MB again for Cornell 1M (2.5-4 ms
// of a 17 ms build on 2 threads); per-worker copies merged at the end cost as much in page faults.
struct PyramidGather {
  struct Range {
    std::size_t c_lo = 0, c_hi = 0;  // the cells of the slabs a worker holds whole
  };
  std::vector<std::uint8_t> owned;  // per level-2 z index: 1 when a worker's range held it whole
  // Whether a build of this geometry gathers (a direct directory with a level 2).
  static bool apply(const bhcl_grid_geom& g);
  void start(Grid& g);  // g.occ sized and zeroed for g.geom, before the placement
  // A worker's cells [c_lo, c_hi): the slabs it holds whole, marked owned, their boxes emptied.
  Range begin_range(Grid& g, std::size_t c_lo, std::size_t c_hi);
  // Cells [c0, c1) of the direct directory, placed: cell c0 + i's run ends at ends[i], the first
  // begins at slot a. Only the cells of r are marked.
  void add_cells(Grid& g, const Range& r, std::size_t c0, std::size_t c1, std::uint32_t a,
                 const std::uint32_t* ends) const;
  void finish(Grid& g, unsigned threads);  // after the placement: the rest of the pyramid
};
// The point boxes of the pyramid's nodes holding these cells made again from the points stored
// (holes left out): each level-2 node from its cells' points, each ancestor from its children.
// For a few cells whose points became holes (the growth room's corners after a rebuild); the
// bits are unchanged (a cell of holes stays marked).
void refresh_node_boxes(Grid& g, const std::vector<std::uint32_t>& cells);
// The fine cell holding point (x, y, z), as the kernels compute a query's (bhcl_grid_cell per
// axis): the one index every build pass, the insert and the rebuild file a point under.
inline std::uint32_t grid_cell_index(const bhcl_grid_geom& g, float x, float y, float z) {
  const std::uint32_t cx = bhcl_grid_cell(x, g.ox, g.inv_h, g.nx);
  const std::uint32_t cy = bhcl_grid_cell(y, g.oy, g.inv_h, g.ny);
  const std::uint32_t cz = bhcl_grid_cell(z, g.oz, g.inv_h, g.nz);
  return (cz * g.ny + cy) * g.nx + cx;
}

// b widened to hold the point (x, y, z).
inline void widen_box(bhcl_grid_dbox& b, float x, float y, float z) {
  b.lx = std::min(b.lx, x), b.ly = std::min(b.ly, y), b.lz = std::min(b.lz, z);
  b.hx = std::max(b.hx, x), b.hy = std::max(b.hy, y), b.hz = std::max(b.hz, z);
}
// b widened to hold box c (an inverted, empty c leaves it as it was).
inline void unite_box(bhcl_grid_dbox& b, const bhcl_grid_dbox& c) {
  b.lx = std::min(b.lx, c.lx), b.ly = std::min(b.ly, c.ly), b.lz = std::min(b.lz, c.lz);
  b.hx = std::max(b.hx, c.hx), b.hy = std::max(b.hy, c.hy), b.hz = std::max(b.hz, c.hz);
}

// The box of g's live points (holes left out): g.dbox on a load (a build takes its own box, an
// insert widens g.dbox by the new points', a remove refits the sides it took a point of).
bhcl_grid_dbox grid_points_box(const Grid& g, unsigned threads);
// The sides of box b that point (x, y, z) lies on, as bits: 1 low x, 2 high x, 4 low y, 8 high y,
// 16 low z, 32 high z.
inline unsigned box_faces_of(const bhcl_grid_dbox& b, float x, float y, float z) {
  return unsigned(x == b.lx) | unsigned(x == b.hx) << 1 | unsigned(y == b.ly) << 2 | unsigned(y == b.hy) << 3 |
         unsigned(z == b.lz) << 4 | unsigned(z == b.hz) << 5;
}
// g.dbox's sides in `faces` (box_faces_of's bits) made the live points' again after a remove took
// points off them (the other sides' extreme points are still live, so they stand). A point's cell
// is monotone in each coordinate (bhcl_grid_cell), so the live point farthest toward a side lies
// in the first plane of cells from that side that holds one: the planes are scanned inward from
// it, about N / n_axis points at uniform density, where the box of every live point read all N
// (as it still does when the planes would hold more cells than there are points).
void refit_box_faces(Grid& g, unsigned faces, unsigned threads);

// The traversal's form, the kNN kernel's defines of the same names: row_cap BHCL_GRID_ROWCAP (the
// runs of a ring scanned nearest first, at most BHCL_GRID_ROWBUF), fine_rings
// BHCL_GRID_FINE_RINGS, walk_cap BHCL_GRID_WALKCAP (the far walk's best-first queue, at most
// BHCL_GRID_WALKBUF; 0: depth-first).
struct GridTraversal {
  std::uint32_t row_cap, fine_rings, walk_cap;
};
// The form a device gets: on CPU devices the gathered rings and the best-first walk (private
// arrays are cheap there); on GPUs neither (no private array: the registers and stack sm_90
// keeps, bench/results/gpu/sm90_table.txt).
GridTraversal grid_traversal(bool cpu);

// The host reference of blockhash_grid_knn.cl (the same traversal, grid_search.h): rows equal
// to the kernel's bit for bit, and the points examined too for the same form. budget as the
// kernel's (0xffffffff: exact).
void reference_query_grid(const Grid& g, const float* queries, std::size_t n, int k, float max_r2,
                          std::uint32_t budget, const GridTraversal& form, KnnResult& out,
                          std::vector<std::int32_t>* examined, unsigned threads);
// The grid's budget over its stored slots, for a budget b of live points. A removed point stays
// a hole (examined, never returned) until the compaction at 1/8 holes, so the budget grows by
// stored / live: a query then examines about as many live points as over a fresh build of them
// (the exact mode's unlimited budget stays unlimited). Without it a tenth of the slots as holes
// cost 0.015 of recall at A = 4 and 8 (uniform 1M, k = 10; bench/update_bench).
inline std::uint32_t grid_budget(std::uint32_t b, std::size_t stored, std::size_t holes) {
  if (b == 0xffffffffu || holes == 0 || stored <= holes) return b;
  const double s = std::ceil(double(b) * double(stored) / double(stored - holes));
  return static_cast<std::uint32_t>(std::min(s, 4294967294.0));
}

// Save / load (blockhash/grid_io.cpp). The file starts with kGridMagic.
inline constexpr char kGridMagic[8] = {'B', 'H', 'C', 'L', 'G', 'R', 'I', 'D'};
struct GridFile {
  Grid grid;
  int scale_exp = 0;
  double target_cell_points = 0;
};
void save_grid(const GridFile& f, const std::string& path);
bool is_grid_file(const std::string& path);
GridFile load_grid(const std::string& path);
GridFile parse_grid(const std::string& data, const std::string& what);

}  // namespace bhcl::blockhash
