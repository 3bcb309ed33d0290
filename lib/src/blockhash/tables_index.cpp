// BlockTablesIndex: the L tables' build stages run in order (build.hpp), upload, save / load,
// updates (a fresh build over the live points) and the search side (parameter checks, kernel
// options and arguments, the kNN and radius dispatch, the host reference).
#include "blockhash_cl/block_tables.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <cstring>

#include "bhcl_shared.h"
#include "blockhash/build.hpp"
#include "blockhash/options.hpp"
#include "blockhash/update_counters.hpp"
#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "core/kernel_defines.hpp"

// The host's view of the device layouts (kernels/blockhash_layout.h) must match OpenCL C's.
static_assert(sizeof(bhcl_bh_block) == 256, "a block is one 256-byte memory unit");
static_assert(offsetof(bhcl_bh_block, y) == 64 && offsetof(bhcl_bh_block, z) == 128 &&
                  offsetof(bhcl_bh_block, id) == 192,
              "bhcl_bh_block: structure of arrays, 64 bytes each");
static_assert(sizeof(bhcl_bh_box) == 32 && offsetof(bhcl_bh_box, count) == 12 &&
                  offsetof(bhcl_bh_box, hi_x) == 16 && offsetof(bhcl_bh_box, first) == 28,
              "bhcl_bh_box layout");
static_assert(sizeof(bhcl_bh_bucket) == 16 && offsetof(bhcl_bh_bucket, q) == 8,
              "bhcl_bh_bucket layout");

namespace bhcl {
namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

double median_u32(std::vector<std::uint32_t> v) {
  if (v.empty()) return 0;
  auto mid = v.begin() + v.size() / 2;
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

double percentile_u32(std::vector<std::uint32_t> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  std::size_t idx = static_cast<std::size_t>(std::ceil(p * v.size()));
  return v[std::min(v.size() - 1, idx ? idx - 1 : 0)];
}

void count_tables(blockhash::Structure& s) {
  BlockHashBuildInfo& in = s.info;
  in.occupied_cells = in.overflowed_buckets = in.block_refs = 0;
  for (const auto& b : s.buckets) {
    in.occupied_cells += b.n_refs ? 1 : 0;
    in.overflowed_buckets += (b.flags & BHCL_BH_FLAG_OVERFLOWED) ? 1 : 0;
    in.block_refs += b.n_refs;
  }
}

}  // namespace

BlockTablesIndex::BlockTablesIndex(std::shared_ptr<Runtime> runtime, const float* points, std::size_t n_points,
                                   const TableBuildParams& params)
    : BlockHashIndex(std::move(runtime), n_points), params_(params) {
  // Every range, from the option table, before the first stage reads one (a caller may build
  // these tables directly, not through BlockHashIndex::build).
  const BlockHashBuildParams user = blockhash::user_params(params);
  check_build_fields(blockhash::option_table(), &user, "blockhash");
  build_blocks(points, n_points);
}

BlockTablesIndex::~BlockTablesIndex() = default;

void BlockTablesIndex::build_blocks(const float* points, std::size_t n_points) {
  const TableBuildParams& params = params_;
  using namespace blockhash;
  auto t0 = std::chrono::steady_clock::now();
  std::vector<float> scaled;
  points = begin_build(points, n_points, scaled);
  Structure& s = *s_;
  s.info.preset = params.preset;
  s.info.n_points = n_points;
  s.info.X = derive_x(params);
  auto say = [&](const char* stage) {
    if (params.verbose) std::fprintf(stderr, "blockhash: %s (%.2f s)\n", stage, seconds_since(t0));
  };

  auto t = std::chrono::steady_clock::now();
  sort_points(points, n_points, params.hilbert_bits, s);
  s.info.t_hilbert = seconds_since(t);
  say("Hilbert keys sorted");

  t = std::chrono::steady_clock::now();
  make_blocks(points, s.order, s.info.X, s.blocks, s.boxes);
  s.info.n_blocks = s.blocks.size();
  s.info.t_blocks = seconds_since(t);
  say("blocks cut");

  t = std::chrono::steady_clock::now();
  derive_params(params, s);
  s.info.t_params = seconds_since(t);
  say("parameters derived");

  t = std::chrono::steady_clock::now();
  build_thresholds(params, s);
  s.info.t_thresholds = seconds_since(t);
  say("thresholds built");

  t = std::chrono::steady_clock::now();
  TableStats st = build_tables(s);
  s.info.median_cell_points = median_u32(st.cell_points);
  s.info.median_cell_blocks = median_u32(st.cell_blocks);
  s.info.p90_cell_blocks = percentile_u32(st.cell_blocks, 0.9);
  count_tables(s);
  s.info.t_tables = seconds_since(t);
  say("tables filled");

  t = std::chrono::steady_clock::now();
  upload();
  s.info.t_upload = seconds_since(t);
  s.info.t_total = seconds_since(t0);
  info_ = s.info;
  set_build_seconds(s.info.t_total);
  say("uploaded");
}

void BlockTablesIndex::rebuild(const float* points, std::size_t n_points) {
  set_size(n_points);
  s_ = std::make_unique<blockhash::Structure>();
  build_blocks(points, n_points);
}

void BlockTablesIndex::upload() {
  const auto& rt = runtime_ptr();
  const blockhash::Structure& s = *s_;
  blocks_ = detail::upload_vector(rt, s.blocks, "blockhash blocks");
  boxes_ = detail::upload_vector(rt, s.boxes, "blockhash boxes");
  thresholds_ = detail::upload_vector(rt, s.thresholds, "blockhash thresholds");
  keys_ = detail::upload_vector(rt, s.keys, "blockhash directory keys");
  table_starts_ = detail::upload_vector(rt, s.table_starts, "blockhash table starts");
  buckets_ = detail::upload_vector(rt, s.buckets, "blockhash buckets");
  refs_ = detail::upload_vector(rt, s.refs, "blockhash block references");
  block_keys_ = detail::upload_vector(rt, s.block_keys, "blockhash block keys");
  upload_dummy();
}

BlockTablesIndex::BlockTablesIndex(std::shared_ptr<Runtime> runtime, std::unique_ptr<blockhash::Structure> s)
    : BlockHashIndex(std::move(runtime), std::move(s)) {
  auto t0 = std::chrono::steady_clock::now();
  count_tables(*s_);
  upload();
  s_->info.t_upload = seconds_since(t0);
  info_ = s_->info;
  set_build_seconds(seconds_since(t0));
}

std::unique_ptr<BlockTablesIndex> BlockTablesIndex::load_saved(std::shared_ptr<Runtime> runtime,
                                                               const std::string& path, std::int64_t rows) {
  std::int64_t bound = -1;
  auto s = blockhash::load_structure(path, &bound);
  check_rows(path, rows, bound, s->n_points);
  std::unique_ptr<BlockTablesIndex> t(new BlockTablesIndex(std::move(runtime), std::move(s)));
  if (bound != std::int64_t(t->size())) {  // sparse ids after removals
    std::vector<std::int32_t> live(t->s_->order.begin(), t->s_->order.end());
    std::sort(live.begin(), live.end());
    t->set_id_state(static_cast<std::int32_t>(bound), live);
  }
  // An update rebuilds the tables (blocks_update) from the build parameters: the saved layout's
  // preset (and auto's L; the others as their defaults derive them).
  t->params_.preset = t->info_.preset;
  if (t->info_.preset == BlockHashBuildParams::Preset::Auto) t->params_.L = t->info_.L;
  if (t->info_.preset == BlockHashBuildParams::Preset::PaperCells) {
    // Its P and B came from the design k and A, which the file does not hold: keep the saved ones.
    t->params_.P = t->info_.P;
    t->params_.B = t->info_.B;
  }
  return t;
}

void BlockTablesIndex::save(const std::string& path) const {
  // After updates the file holds the id bound and the live ids as they are (io.cpp): a load
  // answers as this index, with the same ids.
  ReadLock lock(*this);
  blockhash::save_structure(*s_, path, id_bound());
}

void BlockTablesIndex::visit_stored_points(const PointVisitor& visit) const {
  const blockhash::Structure& s = *s_;
  for (std::size_t b = 0; b < s.blocks.size(); ++b)
    for (std::int32_t j = 0; j < s.boxes[b].count; ++j)
      visit(s.blocks[b].id[j], s.blocks[b].x[j], s.blocks[b].y[j], s.blocks[b].z[j]);
}

long BlockTablesIndex::first_stored_mismatch(const float* points) const {
  for (std::size_t i = 0; i < s_->n_points; ++i) {
    float p[3];
    s_->point(i, p);
    const float* u = points + 3 * static_cast<std::size_t>(s_->order[i]);
    const float c[3] = {std::ldexp(u[0], -s_->scale_exp), std::ldexp(u[1], -s_->scale_exp),
                        std::ldexp(u[2], -s_->scale_exp)};
    if (std::memcmp(p, c, sizeof p) != 0) return s_->order[i];
  }
  return -1;
}

std::size_t BlockTablesIndex::memory_bytes() const { return s_->device_bytes(); }

std::size_t BlockTablesIndex::host_bytes() const {
  // The structure's arrays and the Hilbert order.
  return s_->device_bytes() + s_->order.size() * sizeof(std::int32_t);
}

double BlockTablesIndex::measured_overhead() const {
  // Everything beyond the blocks holding the points, over the talk's 24 bytes per photon.
  return (double(memory_bytes()) - double(s_->blocks.size() * sizeof(bhcl_bh_block))) / (24.0 * double(size()));
}

// ---- Updates: the Hilbert blocks and tables have no cheap insert --------------------------------

void BlockTablesIndex::insert_stored(const float* points, const float*, std::size_t n, std::int32_t first) {
  blocks_update(points, n, first, nullptr, 0);
}

void BlockTablesIndex::remove_stored(const std::int32_t* ids, std::size_t n) { blocks_update(nullptr, 0, 0, ids, n); }

void BlockTablesIndex::blocks_update(const float* points, std::size_t n, std::int32_t first,
                                     const std::int32_t* removed, std::size_t n_removed) {
  std::vector<std::int32_t> ids, kept_ids;
  std::vector<float> pts = indexed_points(&ids), kept;
  if (n_removed) {  // removed: ascending, as ids
    kept.reserve(pts.size());
    std::size_t j = 0;
    for (std::size_t i = 0; i < ids.size(); ++i) {
      while (j < n_removed && removed[j] < ids[i]) ++j;
      if (j < n_removed && removed[j] == ids[i]) continue;
      kept.insert(kept.end(), pts.begin() + 3 * i, pts.begin() + 3 * i + 3);
      kept_ids.push_back(ids[i]);
    }
    pts.swap(kept);
    ids.swap(kept_ids);
  }
  pts.insert(pts.end(), points, points + 3 * n);
  for (std::size_t i = 0; i < n; ++i) ids.push_back(first + static_cast<std::int32_t>(i));
  const blockhash::UpdateCounters keep(info_);
  auto fresh = std::make_unique<blockhash::Structure>();
  std::swap(s_, fresh);
  try {
    build_blocks(pts.data(), ids.size());
  } catch (...) {
    std::swap(s_, fresh);
    upload();
    throw;
  }
  // The build numbers the points 0 .. n - 1 in the order given (ascending ids): their ids, in the
  // blocks the kernels read and in the order a reference query and a save read.
  blockhash::Structure& s = *s_;
  for (auto& o : s.order) o = ids[std::size_t(o)];
  for (std::size_t b = 0; b < s.blocks.size(); ++b)
    for (std::int32_t j = 0; j < s.boxes[b].count; ++j) s.blocks[b].id[j] = ids[std::size_t(s.blocks[b].id[j])];
  upload();
  keep.put(info_);
  ++info_.update_rebuilds;
  s.info = info_;
}

// ---- The search side ---------------------------------------------------------------------------

void BlockTablesIndex::check_params(const SearchParams& p) const {
  Index::check_params(p);
  if (p.neighbour_probes < -1 || p.neighbour_probes > 1)
    throw Error("blockhash: neighbour_probes must be -1 (preset), 0 or 1 on the L tables, got " +
                std::to_string(p.neighbour_probes));
  if (!(p.recall_target >= 0 && p.recall_target <= 1))
    throw Error("blockhash: recall_target must be in [0, 1] (0 = use A), got " + std::to_string(p.recall_target));
  if (p.recall_target > 0) {
    resolved_A(p);  // tunes now (once per k and target), outside any dispatch lock
    return;
  }
  if (!(p.A >= 0) || !std::isfinite(p.A))
    throw Error("blockhash: A must be a positive finite number (0: the default, 8), got " + std::to_string(p.A));
}

bool BlockTablesIndex::table_probes(int neighbour_probes) const {
  return neighbour_probes < 0 ? info_.neighbour_probes : neighbour_probes == 1;
}

void BlockTablesIndex::add_layout_args(detail::KernelArgs& args, int neighbour_probes) const {
  args.add(blocks_).add(boxes_).add(thresholds_).add(cl_uint(info_.P)).add(keys_);
  args.add(table_starts_).add(buckets_).add(refs_).add(cl_uint(table_probes(neighbour_probes) ? 1 : 0));
}

detail::DefineValues BlockTablesIndex::kernel_options(int kmax) const {
  const long long cap = blockhash::scan_cap(kmax, info_.X);
  // Only the defines the variant uses, so that indexes differing elsewhere share a program.
  return {{"BHCL_KMAX", kmax},
          {"BHCL_BH_L", info_.L},
          {"BHCL_BH_DIRECT", info_.direct_addressing ? 1 : 0},
          {"BHCL_BH_BOXSKIP", info_.box_skip && !info_.box_order ? 1 : 0},
          {"BHCL_BH_BOXORDER", info_.box_order ? 1 : 0},
          {info_.box_order ? "BHCL_BH_MAXKEEP" : "BHCL_BH_SCANCAP", cap}};
}

cl::Event BlockTablesIndex::enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                          std::size_t first, std::size_t count, const ResultBuffers& out,
                                          const SearchParams& params_in, std::size_t local_size,
                                          const std::vector<cl::Event>* wait) const {
  const SearchParams params = resolved(params_in);
  const int kmax = kmax_variant(params.k);
  const char* name = "blockhash_knn";
  cl::Kernel kernel = layout_kernel(name, kernel_options(kmax), params.kernel_defines);
  detail::KernelArgs args(kernel, name);
  add_layout_args(args, params.neighbour_probes);
  args.add(block_keys_)
      .add(cl_uint(s_->blocks.size()))
      .add(cl_float4{{s_->q_origin[0], s_->q_origin[1], s_->q_origin[2], s_->q_scale}})
      .add(cl_uint(s_->q_bits))
      .add(cl_uint(blockhash::seed_side(info_.hilbert_seed, params.k, info_.X)));
  // The queries, k, radius, budget, the blocks a query keeps, then the results.
  args.add_queries(queries, first, count, params)
      .add(cl_uint(budget(params)))
      .add(cl_uint(blockhash::keep_blocks(budget(params), kmax, info_.X)));
  add_knn_results(args, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, name);
}

BlockHashIndex::RadiusKernel BlockTablesIndex::radius_kernel() const {
  return {"blockhash_radius",
          {{"BHCL_BH_L", info_.L},
           {"BHCL_BH_DIRECT", info_.direct_addressing ? 1 : 0},
           {"BHCL_BH_SCANCAP", static_cast<long long>(blockhash::scan_cap(kMaxK, info_.X))}}};
}

void BlockTablesIndex::add_radius_layout_args(detail::KernelArgs& args, const RadiusParams& params) const {
  add_layout_args(args, params.neighbour_probes);
}

void BlockTablesIndex::reference_scaled(const float* queries, std::size_t n, const SearchParams& params,
                                        KnnResult& out, std::vector<std::int32_t>* examined, unsigned threads) const {
  blockhash::reference_query(*s_, queries, n, params, table_probes(params.neighbour_probes), out, examined, threads);
}

}  // namespace bhcl
