// The L-table layout of block hashing: the talk's scheme (Ma & McCool 2002) of L jittered hash
// tables over Hilbert-ordered blocks of X points, as the paper and paper-cells presets build it
// and with auto's rules (grid = 0: guarded thresholds, a directory of the occupied cells,
// neighbour probes, box-ordered scans; kernels/blockhash_knn.cl). A query examines at most
// ceil(A k) points (A = 0: 8); no exact mode. An update is a fresh build over the live points.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/blockhash.hpp"

namespace bhcl {


// The L tables' own build parameters (BlockHashBuildParams' table fields; the same meanings and
// defaults). preset Auto: auto's L tables (what grid = 0 builds).
struct TableBuildParams {
  using Preset = BlockHashBuildParams::Preset;
  Preset preset = Preset::Auto;
  int L = -1, P = -1, B = -1, X = -1;
  double target_cell_points = -1.0;  // -1: auto 100, paper-cells design_k / 4
  double b_percentile = 0.90;
  double design_A = 8.0;
  int design_k = 10;
  int hist_bins = 1024;
  int hilbert_bits = 21;
  int guard_thresholds = -1, keep_top_count = -1, direct_addressing = -1, box_skip = -1, box_order = -1;
  int hilbert_seed = -1;
  int neighbour_probes = -1;
  std::uint64_t seed = 1;
  bool verbose = false;
};

class BlockTablesIndex final : public BlockHashIndex {
 public:
  // points: N x 3 floats in the caller's order (copied). Throws for N == 0, N >= 2^31,
  // non-finite points or parameters out of range.
  BlockTablesIndex(std::shared_ptr<Runtime> runtime, const float* points, std::size_t n_points,
                   const TableBuildParams& params = {});
  ~BlockTablesIndex() override;

  const TableBuildParams& params() const { return params_; }
  bool exact_mode() const override { return false; }
  // rebuild(): a fresh build with the same parameters.
  BHCL_BLOCKHASH_LAYOUT_API

 protected:
  BHCL_BLOCKHASH_LAYOUT_HOOKS

 private:
  friend class BlockHashIndex;  // load() makes loaded tables
  BlockTablesIndex(std::shared_ptr<Runtime> runtime, std::unique_ptr<blockhash::Structure> s);
  static std::unique_ptr<BlockTablesIndex> load_saved(std::shared_ptr<Runtime> runtime, const std::string& path,
                                                      std::int64_t rows);
  void build_blocks(const float* points, std::size_t n_points);  // the stages (build.hpp)
  void upload();
  // The library's defines of the kNN kernel variant of at most kmax (kernel_defines.hpp).
  std::vector<std::pair<const char*, long long>> kernel_options(int kmax) const;
  bool table_probes(int neighbour_probes) const;  // 0 or 1 (-1: the build's default)
  // The arguments the kernels (kNN and radius) begin with, up to the probes.
  void add_layout_args(detail::KernelArgs& args, int neighbour_probes) const;
  // An update: a fresh build over the live points less `removed` plus the new ones, ids kept.
  void blocks_update(const float* points, std::size_t n, std::int32_t first, const std::int32_t* removed,
                     std::size_t n_removed);

  TableBuildParams params_;
  cl::Buffer blocks_, boxes_, thresholds_, keys_, table_starts_, buckets_, refs_, block_keys_;
};

}  // namespace bhcl
