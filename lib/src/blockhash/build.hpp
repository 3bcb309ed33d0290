// Block hashing, host side: the built structure and one function per build stage, so that the
// tests can call each stage on its own. The stages, in order (blockhash/index.cpp runs them):
//   sfc/hilbert.cpp           quantise in the bounding box, 3D Hilbert keys, stable sort
//   blockhash/blocks.cpp      cut the sorted points into blocks of X, a bounding box per block
//   blockhash/params.cpp      derive L, P, B, X (paper formulas or auto from the data)
//   blockhash/thresholds.cpp  histogram, CDF, stratified jittered inversion, guards; h_T(t)
//   blockhash/tables.cpp      L tables of buckets: insertion, overflow, Q
//   blockhash/query_ref.cpp   the host reference of the kernel's query
//   blockhash/io.cpp          save / load
#pragma once

#include <cstddef>
#include <algorithm>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/block_tables.hpp"
#include "blockhash_cl/blockhash.hpp"
#include "bhcl_arith.h"
#include "blockhash_layout.h"
#include "blockhash/grid.hpp"
#include "sfc/hilbert.hpp"

namespace bhcl::blockhash {

struct Structure;

// ---- Stage 1: Hilbert keys -------------------------------------------------------------------

// The curve is the sfc module's (sfc/hilbert.hpp): its quantiser, keys and stable sort, named here
// as the stage's own.
using sfc::Quantiser;
using sfc::make_quantiser;
using sfc::hilbert_encode;
using sfc::hilbert_decode;
using sfc::hilbert_keys;
using sfc::hilbert_order;

// The whole stage on a structure: s.order, s.block_keys (the key of each block's first point, for
// X = s.info.X) and the query quantiser (s.q_*).
void sort_points(const float* xyz, std::size_t n, int bits, Structure& s);

// ---- Stage 2: blocks -------------------------------------------------------------------------

// Cuts the points, taken in `order`, into blocks of X (the last one partial), each with its box.
void make_blocks(const float* xyz, const std::vector<std::int32_t>& order, int X,
                 std::vector<bhcl_bh_block>& blocks, std::vector<bhcl_bh_box>& boxes);
// One block of the points order[first, end) (at most 16) and its box; unused slots NaN / -1.
void fill_block(const float* xyz, const std::vector<std::int32_t>& order, std::size_t first,
                std::size_t end, bhcl_bh_block& blk, bhcl_bh_box& box);

// ---- Stage 3: thresholds ---------------------------------------------------------------------

struct Histogram {
  double lo = 0, hi = 0;  // range of the bins (the data's extent along the dimension)
  std::vector<std::uint64_t> counts;
  std::uint64_t total = 0;
  double edge(int e) const { return lo + (hi - lo) * double(e) / double(counts.size()); }
};
// sorted_xyz: points in any order; dim 0..2. stride selects every stride-th point (sampling).
Histogram histogram(const float* xyz, std::size_t n, int dim, int bins, std::size_t stride = 1);

// P thresholds from the histogram's CDF inverted at the stratified samples (i + r_i) / P, r_i
// uniform in [0, 1) from (seed, table, dim). guarded: snapped to bin edges, thresholds on the
// range's ends dropped, a threshold bordering a heavy bin (holding more than N / P points) moved
// one bin away from it, duplicates removed; the removed slots are +inf. The result is ascending.
std::vector<float> make_thresholds(const Histogram& h, int P, std::uint64_t seed, int table,
                                   int dim, bool guarded);

// h_T(t) = #{i : t_i <= t}: 0 below t_0, P at or above the last threshold (the clamp). The
// kernels' bh_hash (kernels/bhcl_arith.h).
inline std::uint32_t hash_coord(const float* thr, std::uint32_t P, float t) { return bh_hash(thr, P, t); }

// ---- Stage 4: tables -------------------------------------------------------------------------

struct TableStats {
  std::size_t occupied_cells = 0, overflowed = 0, refs = 0;
  std::vector<std::uint32_t> cell_points;  // table 0 only: points per occupied cell
  std::vector<std::uint32_t> cell_blocks;  // table 0 only: distinct blocks per occupied cell
};

// ---- The structure ---------------------------------------------------------------------------

struct Structure {
  BlockHashBuildInfo info;
  std::size_t n_points = 0;
  int scale_exp = 0;                     // stored coordinates = caller's * 2^-scale_exp (knn.hpp)
  std::vector<std::int32_t> order;       // Hilbert position -> caller's index
  std::vector<bhcl_bh_block> blocks;
  std::vector<bhcl_bh_box> boxes;
  std::vector<float> thresholds;         // L * 3 * P
  std::vector<std::uint32_t> table_starts;  // L + 1 offsets into keys/buckets
  std::vector<std::uint32_t> keys;       // auto: sorted occupied cell keys per table; paper: empty
  std::vector<bhcl_bh_bucket> buckets;
  std::vector<std::int32_t> refs;
  // Hilbert seeding: the key of each block's first point, and the query-side quantiser in float
  // (the kernel and the reference compute the query's key with exactly these values).
  std::vector<std::uint64_t> block_keys;
  float q_origin[3] = {0, 0, 0};
  float q_scale = 0;
  int q_bits = 21;
  std::shared_ptr<Grid> grid;           // the grid layout (auto): the arrays above stay empty

  const float* thr(int table, int dim) const {
    return thresholds.data() + (std::size_t(table) * 3 + dim) * std::size_t(info.P);
  }
  std::uint32_t cell_key(const std::uint32_t h[3]) const {
    std::uint32_t s = std::uint32_t(info.P) + 1;
    return (h[0] * s + h[1]) * s + h[2];
  }
  // The bucket index of a cell of a table, or -1 when the cell has no bucket (auto: unoccupied).
  long find_bucket(int table, std::uint32_t key) const;
  // The coordinates of a sorted point (position i in the point order): blocks of X, the last partial.
  void point(std::size_t i, float p[3]) const {
    const std::size_t bi = i / static_cast<std::size_t>(info.X);
    const bhcl_bh_block& b = blocks[bi];
    const std::size_t j = i - bi * static_cast<std::size_t>(info.X);
    p[0] = b.x[j]; p[1] = b.y[j]; p[2] = b.z[j];
  }
  // The cell of a point in a table.
  std::uint32_t point_cell(int table, const float p[3]) const {
    std::uint32_t h[3];
    for (int d = 0; d < 3; ++d) h[d] = hash_coord(thr(table, d), std::uint32_t(info.P), p[d]);
    return cell_key(h);
  }
  // Device bytes of every array.
  std::size_t device_bytes() const;
  // Checks every invariant the kernel relies on (indices in range, sorted keys, ...); throws
  // bhcl::Error naming `what` and the first violation. Used after load.
  void validate(const std::string& what) const;
};

// The L tables' fields of the user's parameters (BlockHashIndex::build), and the user's
// parameters of an L-table build (the option table, which checks every range, reads those).
TableBuildParams table_params(const BlockHashBuildParams& p);
BlockHashBuildParams user_params(const TableBuildParams& p);

// Derives L, P, B, X and the flags (stage "params"): paper formulas, or auto from the data. The
// structure's blocks must be built (X is decided first, by derive_x).
int derive_x(const TableBuildParams& p);
void derive_params(const TableBuildParams& p, Structure& s);

// Fills s.thresholds for every table (needs s.info.P, L and the blocks).
void build_thresholds(const TableBuildParams& p, Structure& s);
// Fills table_starts, keys, buckets, refs (needs thresholds). Returns table 0's statistics.
TableStats build_tables(Structure& s);

// Population statistics of table-0-like cells for a candidate P (used by auto's bisection):
// median points per occupied cell over every stride-th sorted point.
double median_cell_points(const Structure& s, const TableBuildParams& p, int P,
                          std::size_t stride);
// The same for many P over one sample: the stride-th sorted points and their histograms.
struct CellSample {
  std::size_t stride;
  std::vector<float> pts;
  Histogram hist[3];
  CellSample(const Structure& s, const TableBuildParams& p, std::size_t stride);
  double median_points(const Structure& s, const TableBuildParams& p, int P) const;
};

// The host reference query. examined may be null.
void reference_query(const Structure& s, const float* queries, std::size_t n,
                     const SearchParams& params, bool probes, KnnResult& out,
                     std::vector<std::int32_t>* examined, unsigned threads);

// The scan cap of a kernel variant: at most this many blocks are scanned per query (enough for
// A <= 32 at k <= kmax; a larger budget stops here, in the kernel and the reference alike).
inline std::uint32_t scan_cap(int kmax, int X) {
  std::uint32_t c = std::uint32_t((32 * kmax + X - 1) / X + 1);
  return c > 4096 ? 4096 : c;
}

// The Hilbert key of a query, in float arithmetic (the kernel's bh_query_key).
std::uint64_t query_hilbert_key(const Structure& s, const float q[3]);

// Box order: blocks seeded on each side of the query's Hilbert position for k.
inline std::uint32_t seed_side(int hilbert_seed, int k, int X) {
  if (hilbert_seed <= 0) return 0;
  std::uint32_t need = std::uint32_t((k + 2 * X - 1) / (2 * X));
  return std::max<std::uint32_t>(std::uint32_t(hilbert_seed), need);
}

// Box order: the blocks a query keeps (the nearest distinct by box distance) and at most scans:
// ceil(budget / X) + 1 spend any budget (every block but the last holds X points), bounded by
// the kernel variant's scan cap.
inline std::uint32_t keep_blocks(std::uint32_t budget, int kmax, int X) {
  std::uint64_t c = (std::uint64_t(budget) + X - 1) / X + 1;
  return static_cast<std::uint32_t>(std::min<std::uint64_t>(c, scan_cap(kmax, X)));
}

// Save / load (blockhash/io.cpp).
// id_bound: one past the largest id issued (an index after Index::insert/remove: the ids in
// order and the blocks are sparse in [0, id_bound)); -1 on save: n_points. Loaded: the file's
// (version 4 files: n_points).
void save_structure(const Structure& s, const std::string& path);
void save_structure(const Structure& s, const std::string& path, std::int64_t id_bound);
std::unique_ptr<Structure> load_structure(const std::string& path);
std::unique_ptr<Structure> load_structure(const std::string& path, std::int64_t* id_bound);
// The parse behind load_structure, on the file's bytes; `what` names the source in errors. The
// fuzz target turns the checksum test off so that its inputs reach the structural checks.
std::unique_ptr<Structure> parse_structure(const std::string& data, const std::string& what,
                                           bool verify_checksum = true, std::int64_t* id_bound = nullptr);

}  // namespace bhcl::blockhash
