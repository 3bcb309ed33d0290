// BlockHashIndex: runs the build stages, uploads the arrays, dispatches the query kernel.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <cstring>
#include <sstream>

#include "bhcl_shared.h"
#include "blockhash/build.hpp"
#include "blockhash/grid_io.hpp"
#include "blockhash/options.hpp"
#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"

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

std::string BlockHashBuildInfo::summary() const {
  char buf[512];
  if (grid) {
    std::snprintf(buf, sizeof buf,
                  "preset auto (grid)  cells %d x %d x %d of side %.4g  occupied %zu  mean cell %.1f points%s  "
                  "%s directory %.1f MB  build %.3f s (tune %.3f, cells %.3f, bucket %.3f, sort %.3f, upload %.3f)",
                  grid_dims[0], grid_dims[1], grid_dims[2], cell_size, occupied_cells, mean_cell_points,
                  grid_capped ? " (cells grown to fit the table)" : "", grid_two_level ? "two-level" : "direct",
                  double(grid_directory_bytes) / 1e6, t_total, t_tune, t_cells, t_count, t_scatter, t_upload);
    return buf;
  }
  std::snprintf(buf, sizeof buf,
                "preset %s%s  L %d  P %d  B %d  X %d  blocks %zu  occupied cells %zu  overflowed %zu  "
                "refs %zu (%.2f/point)  median cell %.0f points / %.0f blocks (p90 %.0f)  build %.2f s "
                "(hilbert %.2f, blocks %.2f, params %.2f, thresholds %.2f, tables %.2f, upload %.2f)",
                BlockHashBuildParams::preset_name(preset), cell_aligned ? " (cell-aligned)" : (box_order ? " (box order)" : ""), L, P, B, X, n_blocks, occupied_cells,
                overflowed_buckets, block_refs, n_points ? double(block_refs) / n_points : 0.0,
                median_cell_points, median_cell_blocks, p90_cell_blocks, t_total, t_hilbert,
                t_blocks, t_params, t_thresholds, t_tables, t_upload);
  return buf;
}

namespace {

// The build info a grid's geometry determines (a fresh build and a load fill it alike).
void grid_geometry_info(const blockhash::Structure& s, BlockHashBuildInfo& in) {
  const bhcl_grid_geom& g = s.grid->geom;
  in.preset = BlockHashBuildParams::Preset::Auto;
  in.grid = true;
  in.grid_dims[0] = int(g.nx);
  in.grid_dims[1] = int(g.ny);
  in.grid_dims[2] = int(g.nz);
  in.cell_size = std::ldexp(double(g.h), s.scale_exp);
  in.L = 1;
  in.P = int(std::max({g.nx, g.ny, g.nz})) - 1;
  for (int d = 0; d < 3; ++d) in.axis_P[d] = in.grid_dims[d] - 1;
  in.n_points = s.n_points;
}

// The grid unless the caller asked for a block layout (docs in blockhash.hpp).
bool wants_grid(const BlockHashBuildParams& p) {
  const bool block_fields = p.L > 0 || p.P > 0 || p.B > 0 || p.X > 0 || p.cell_aligned >= 0 ||
                            p.box_order >= 0 || p.box_skip >= 0 || p.direct_addressing >= 0 ||
                            p.guard_thresholds >= 0 || p.keep_top_count >= 0 || p.hilbert_seed >= 0;
  if (p.grid == 1) {
    if (p.preset == BlockHashBuildParams::Preset::Paper)
      throw Error("blockhash: grid = 1 is the auto preset's layout; the paper preset has its own");
    if (block_fields)
      throw Error("blockhash: grid = 1 takes none of L, P, B, X, cell_aligned, box_order, box_skip, "
                  "direct_addressing, guard_thresholds, keep_top_count, hilbert_seed (block layouts)");
    return true;
  }
  if (p.grid != -1 && p.grid != 0) throw Error("blockhash: grid must be -1 (preset), 0 or 1, got " + std::to_string(p.grid));
  return p.grid == -1 && p.preset == BlockHashBuildParams::Preset::Auto && !block_fields;
}

}  // namespace

BlockHashIndex::BlockHashIndex(std::shared_ptr<Runtime> runtime, const float* points,
                               std::size_t n_points, const BlockHashBuildParams& params)
    : Index(std::move(runtime), n_points), s_(std::make_unique<blockhash::Structure>()), params_(params) {
  check_build_fields(blockhash::option_table(), &params, "blockhash");  // every range, from the table
  if (wants_grid(params)) {
    if (!(params.cell_size == -1 || (params.cell_size > 0 && params.cell_size <= 1e30)))
      throw Error("blockhash: cell_size must be -1 (derive) or a length in (0, 1e30], got " + std::to_string(params.cell_size));
    if (!(params.target_cell_points == -1 || (params.target_cell_points >= 1 && params.target_cell_points <= 1e6)))
      throw Error("blockhash: target_cell_points must be -1 (derive) or in [1, 1e6], got " + std::to_string(params.target_cell_points));
    if (!(params.max_cells_per_point >= 0.01 && params.max_cells_per_point <= 1024))
      throw Error("blockhash: max_cells_per_point must be in [0.01, 1024], got " + std::to_string(params.max_cells_per_point));
    build_grid_layout(points, n_points, params.cell_size);
  } else {
    build_blocks(points, n_points);
  }
}

void BlockHashIndex::build_grid_layout(const float* points, std::size_t n_points, double cell_size) {
  using namespace blockhash;
  auto t0 = std::chrono::steady_clock::now();
  std::vector<float> scaled;
  points = prepare_points(points, n_points, scaled);  // validates; extreme scales
  Structure& s = *s_;
  s.n_points = n_points;
  s.scale_exp = scale_exponent();
  if (!s.grid) s.grid = std::make_shared<Grid>();
  GridBuildParams gp;
  // The cell side is kept in the caller's units; the grid is built in the index's coordinates.
  gp.cell_size = cell_size > 0 ? std::ldexp(cell_size, -s.scale_exp) : -1.0;
  gp.target_cell_points = params_.target_cell_points > 0 ? params_.target_cell_points : 24.0;
  gp.max_cells_per_point = params_.max_cells_per_point;
  gp.directory = params_.grid_directory;
  gp.threads = params_.threads;
  GridBuildStats st;
  build_grid(points, n_points, gp, *s.grid, &st);
  BlockHashBuildInfo& in = s.info;
  in = BlockHashBuildInfo{};
  grid_geometry_info(s, in);
  in.occupied_cells = st.occupied;
  in.mean_cell_points = st.mean_cell_points;
  in.grid_capped = st.capped;
  in.grid_two_level = s.grid->geom.sparse != 0;
  in.grid_directory_bytes = s.grid->starts.size() * 4;
  in.t_tune = st.t_tune;
  in.t_cells = st.t_cells;
  in.t_count = st.t_count;
  in.t_scatter = st.t_scatter;
  auto t = std::chrono::steady_clock::now();
  upload_grid();
  in.t_upload = seconds_since(t);
  in.t_total = seconds_since(t0);
  info_ = in;
  set_build_seconds(in.t_total);
  if (params_.verbose) std::fprintf(stderr, "blockhash: %s\n", in.summary().c_str());
}

void BlockHashIndex::rebuild(const float* points, std::size_t n_points) {
  id_pos_.clear();  // a new point set: ids 0 .. n - 1 again (set_size), no update state
  grid_build_mean_ = 0;
  if (info_.grid) {
    // The previous build's cell side (caller units) and the same table limits.
    set_size(n_points);
    build_grid_layout(points, n_points, info_.cell_size);
    return;
  }
  set_size(n_points);
  s_ = std::make_unique<blockhash::Structure>();
  build_blocks(points, n_points);
}

void BlockHashIndex::upload_grid() {
  const auto& rt = runtime_ptr();
  const blockhash::Grid& g = *s_->grid;
  // Rebuilds write into the buffers they have when the arrays fit (no reallocation).
  auto put = [&](cl::Buffer& buf, std::size_t& cap, const void* data, std::size_t bytes, std::size_t want_cap,
                 const char* what) {
    if (buf() && bytes <= cap) {
      check_cl(rt->queue().enqueueWriteBuffer(buf, CL_TRUE, 0, bytes, data), "clEnqueueWriteBuffer", what);
      return;
    }
    cl_int err = CL_SUCCESS;
    buf = cl::Buffer(rt->context(), CL_MEM_READ_ONLY, std::max<std::size_t>(want_cap, 4), nullptr, &err);
    check_cl(err, "clCreateBuffer", std::string(what) + ", " + std::to_string(want_cap) + " bytes");
    cap = want_cap;
    check_cl(rt->queue().enqueueWriteBuffer(buf, CL_TRUE, 0, bytes, data), "clEnqueueWriteBuffer", what);
  };
  const std::size_t sb = g.starts.size() * 4, pb = g.x.size() * 4;
  // Capacity grows geometrically past the current size, so a growing sequence reallocates rarely.
  auto grow = [](std::size_t have, std::size_t want) { return have && want > have ? std::max(want, have + have / 2) : want; };
  std::size_t scap = g_starts_cap_, pcap = g_points_cap_;
  const std::size_t sw = grow(scap, sb), pw = grow(pcap, pb);
  put(g_starts_, scap, g.starts.data(), sb, sw, "blockhash grid cells");
  std::size_t c = pcap;
  put(g_x_, c, g.x.data(), pb, pw, "blockhash grid x");
  c = pcap;
  put(g_y_, c, g.y.data(), pb, pw, "blockhash grid y");
  c = pcap;
  put(g_z_, c, g.z.data(), pb, pw, "blockhash grid z");
  c = pcap;
  put(g_ids_, c, g.ids.data(), pb, pw, "blockhash grid ids");
  g_starts_cap_ = scap;
  g_points_cap_ = c;
  if (!dummy_()) dummy_ = detail::upload_vector(rt, std::vector<std::int32_t>(1, 0), "blockhash dummy");
}

void BlockHashIndex::build_blocks(const float* points, std::size_t n_points) {
  const BlockHashBuildParams& params = params_;
  using namespace blockhash;
  auto t0 = std::chrono::steady_clock::now();
  std::vector<float> scaled;
  points = prepare_points(points, n_points, scaled);  // validates; extreme scales
  Structure& s = *s_;
  s.n_points = n_points;
  s.scale_exp = scale_exponent();
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
  TableStats st = s.info.cell_aligned ? build_cell_aligned(points, s) : build_tables(s);
  if (s.info.cell_aligned) {
    s.info.n_blocks = s.blocks.size();
    std::uint32_t longest = 1;
    for (const auto& b : s.buckets) longest = std::max(longest, b.n_refs);
    s.info.B = static_cast<int>(std::min<std::uint32_t>(longest, 65535));
  }
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

BlockHashIndex::BlockHashIndex(std::shared_ptr<Runtime> runtime, std::unique_ptr<blockhash::Structure> s)
    : Index(std::move(runtime), s->n_points), s_(std::move(s)) {
  auto t0 = std::chrono::steady_clock::now();
  set_scale_exponent(s_->scale_exp);
  if (s_->grid) {
    BlockHashBuildInfo& in = s_->info;
    grid_geometry_info(*s_, in);
    double sum2 = 0;
    const blockhash::Grid& gr = *s_->grid;
    for (std::size_t c = 0, a = gr.start(0); c < gr.ncells(); ++c) {
      const std::size_t b = gr.start(c + 1);
      const double v = double(b - a);
      in.occupied_cells += v > 0 ? 1 : 0;
      sum2 += v * v;
      a = b;
    }
    in.grid_two_level = gr.geom.sparse != 0;
    in.grid_directory_bytes = gr.starts.size() * 4;
    in.mean_cell_points = sum2 / double(s_->n_points);
    upload_grid();
    in.t_upload = seconds_since(t0);
    info_ = in;
    set_build_seconds(seconds_since(t0));
    return;
  }
  count_tables(*s_);
  upload();
  s_->info.t_upload = seconds_since(t0);
  info_ = s_->info;
  set_build_seconds(seconds_since(t0));
}

BlockHashIndex::~BlockHashIndex() = default;

std::unique_ptr<BlockHashIndex> BlockHashIndex::load(std::shared_ptr<Runtime> runtime,
                                                     const std::string& path) {
  if (blockhash::is_grid_file(path)) {
    blockhash::GridIdState st;
    blockhash::GridFile f = blockhash::load_grid(path, &st);
    auto s = std::make_unique<blockhash::Structure>();
    s->n_points = f.grid.n_points;
    s->scale_exp = f.scale_exp;
    s->grid = std::make_shared<blockhash::Grid>(std::move(f.grid));
    std::unique_ptr<BlockHashIndex> bh(new BlockHashIndex(std::move(runtime), std::move(s)));
    bh->params_.target_cell_points = f.target_cell_points;
    bh->loaded_update_state(st);  // grid_update.cpp
    return bh;
  }
  std::int64_t bound = -1;
  auto s = blockhash::load_structure(path, &bound);
  std::unique_ptr<BlockHashIndex> bh(new BlockHashIndex(std::move(runtime), std::move(s)));
  if (bound != std::int64_t(bh->size())) bh->loaded_update_state(bound);  // sparse ids after removals
  // An update rebuilds a block layout (blocks_update) from the build parameters: the saved
  // layout's preset and kind (the others as their defaults derive them).
  bh->params_.preset = bh->info_.preset;
  if (bh->info_.preset == BlockHashBuildParams::Preset::Auto) {
    bh->params_.cell_aligned = bh->info_.cell_aligned ? 1 : 0;
    if (!bh->info_.cell_aligned) bh->params_.L = bh->info_.L;
  }
  return bh;
}

void BlockHashIndex::save(const std::string& path) const {
  // After updates the files hold the id bound and the live ids as they are (the grid its holes
  // too: grid_io.cpp, io.cpp): a load answers as this index, with the same ids.
  ReadLock lock(*this);
  if (info_.grid) {
    blockhash::GridFile f;
    f.grid = *s_->grid;
    f.scale_exp = s_->scale_exp;
    f.target_cell_points = params_.target_cell_points;
    blockhash::save_grid(f, grid_update_state(), path);  // grid_update.cpp
    return;
  }
  blockhash::save_structure(*s_, path, id_bound());
}

std::vector<float> BlockHashIndex::indexed_points(std::vector<std::int32_t>* ids) const {
  const blockhash::Structure& s = *s_;
  // Slot of each id (ids after updates are sparse in [0, id_bound()); holes carry the empty-slot
  // id and are skipped), then the points in ascending id order.
  const std::size_t bound = std::size_t(id_bound());
  std::vector<float> byid(3 * bound, NAN);
  std::vector<char> have(bound, 0);
  auto put = [&](std::int32_t id, float x, float y, float z) {
    if (id < 0 || std::size_t(id) >= bound) return;  // a hole
    byid[3 * std::size_t(id)] = std::ldexp(x, s.scale_exp);
    byid[3 * std::size_t(id) + 1] = std::ldexp(y, s.scale_exp);
    byid[3 * std::size_t(id) + 2] = std::ldexp(z, s.scale_exp);
    have[std::size_t(id)] = 1;
  };
  if (s.grid) {
    const blockhash::Grid& g = *s.grid;
    for (std::size_t i = 0; i < g.n_points; ++i) put(g.ids[i], g.x[i], g.y[i], g.z[i]);
  } else {
    for (std::size_t b = 0; b < s.blocks.size(); ++b)
      for (std::int32_t j = 0; j < s.boxes[b].count; ++j)
        put(s.blocks[b].id[j], s.blocks[b].x[j], s.blocks[b].y[j], s.blocks[b].z[j]);
  }
  if (ids) ids->clear();
  std::vector<float> pts;
  pts.reserve(3 * size());
  for (std::size_t id = 0; id < bound; ++id) {
    if (!have[id]) continue;
    pts.insert(pts.end(), byid.begin() + 3 * id, byid.begin() + 3 * id + 3);
    if (ids) ids->push_back(static_cast<std::int32_t>(id));
  }
  return pts;
}

long BlockHashIndex::first_mismatch(const float* points, std::size_t n) const {
  // points[id] for every id issued (after removals the removed ids' rows are not compared).
  if (n != std::size_t(id_bound())) return -2;  // not an index: the sizes differ
  if (s_->grid) {
    const blockhash::Grid& g = *s_->grid;
    for (std::size_t i = 0; i < g.n_points; ++i) {
      if (g.ids[i] == BHCL_EMPTY_SLOT_ID) continue;  // a hole
      const float* u = points + 3 * static_cast<std::size_t>(g.ids[i]);
      const float c[3] = {std::ldexp(u[0], -s_->scale_exp), std::ldexp(u[1], -s_->scale_exp),
                          std::ldexp(u[2], -s_->scale_exp)};
      const float p[3] = {g.x[i], g.y[i], g.z[i]};
      if (std::memcmp(p, c, sizeof p) != 0) return g.ids[i];
    }
    return -1;
  }
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

void BlockHashIndex::upload() {
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
  dummy_ = detail::upload_vector(rt, std::vector<std::int32_t>(1, 0), "blockhash dummy");
  // The direct cell table where it is small: at most 2^20 cells or 2 per point (8 bytes each).
  blockhash::CellTable ct = blockhash::make_cell_table(s, std::max<std::size_t>(std::size_t(1) << 20, 2 * s.n_points));
  cell_dy_ = ct.dy;
  cell_dz_ = ct.dz;
  cell_table_bytes_ = ct.runs.size() * 4;
  if (ct.runs.empty()) ct.runs.assign(2, 0);
  cell_table_ = detail::upload_vector(rt, ct.runs, "blockhash cell table");
}

std::size_t BlockHashIndex::memory_bytes() const {
  if (s_->grid) return s_->grid->device_bytes();
  return s_->device_bytes() + cell_table_bytes_;
}

std::size_t BlockHashIndex::host_bytes() const {
  // The grid's host vectors mirror its device arrays one for one; a block layout keeps its
  // structure's arrays and the Hilbert order (the cell table lives on the device only).
  // The grid also keeps its build scratch (cells, records: 24 B per point) for rebuilds.
  if (s_->grid) {
    const blockhash::Grid& g = *s_->grid;
    std::size_t scratch = 0;
    if (g.scratch) scratch = g.scratch->cell.capacity() * 4 + g.scratch->rec.capacity() * 4 + g.scratch->rec_cell.capacity() * 4;
    return g.device_bytes() + scratch;
  }
  return s_->device_bytes() + s_->order.size() * sizeof(std::int32_t);
}

double BlockHashIndex::talk_overhead(std::size_t N, double A, int k, int X) {
  double n = double(N), l = std::log(std::max(n, 2.0));
  return (4.0 * (A * k / X) * l * l * l + 12.0 * l * l + 1.6 * n) / (24.0 * n);
}

double BlockHashIndex::measured_overhead() const {
  // Everything beyond the points' own records, over the talk's 24 bytes per photon.
  double points = 24.0 * double(size());
  if (s_->grid) return (double(memory_bytes()) - 16.0 * double(size())) / points;
  return (double(memory_bytes()) - double(s_->blocks.size() * sizeof(bhcl_bh_block))) / points;
}

std::uint32_t BlockHashIndex::cells_probes(const SearchParams& p) const {
  if (p.neighbour_probes >= 0) return static_cast<std::uint32_t>(p.neighbour_probes);
  // The octant, then the rest of the 4 x 4 x 4 block only for queries whose k-th distance still
  // reaches past the octant (phase 2 of the kernel): it costs a comparison when not needed.
  return info_.neighbour_probes ? 2u : 0u;
}

std::uint32_t BlockHashIndex::budget(const SearchParams& p) {
  double b = std::ceil(double(p.A) * double(p.k));
  return static_cast<std::uint32_t>(std::min(b, 4294967295.0));
}

void BlockHashIndex::check_params(const SearchParams& p) const {
  Index::check_params(p);
  if (info_.grid) {
    // The rings reach every cell within the bound: the probes of the block layouts do not apply.
    if (p.neighbour_probes < -1 || p.neighbour_probes > 2)
      throw Error("blockhash: neighbour_probes must be -1, 0, 1 or 2, got " + std::to_string(p.neighbour_probes));
    if (!(p.recall_target >= 0 && p.recall_target <= 1))
      throw Error("blockhash: recall_target must be in [0, 1] (0 = use A, 1 = exact), got " + std::to_string(p.recall_target));
    if (p.recall_target > 0 && p.recall_target < 1) {
      resolved_A(p);
      return;
    }
    if (!(p.A >= 0))
      throw Error("blockhash: A must be positive (+inf: exact; 0: the default, exact), got " + std::to_string(p.A));
    return;
  }
  const int top = info_.cell_aligned ? 2 : 1;
  if (p.neighbour_probes < -1 || p.neighbour_probes > top)
    throw Error("blockhash: neighbour_probes must be -1 (preset), 0 or 1" +
                std::string(info_.cell_aligned ? " or 2 (cell-aligned: two near-side cells and the far one)" : "") +
                ", got " + std::to_string(p.neighbour_probes));
  if (!(p.recall_target >= 0 && p.recall_target <= 1))
    throw Error("blockhash: recall_target must be in [0, 1] (0 = use A), got " + std::to_string(p.recall_target));
  if (p.recall_target > 0) {
    resolved_A(p);  // tunes now (once per k and target), outside any dispatch lock
    return;
  }
  if (!(p.A >= 0) || !std::isfinite(p.A))
    throw Error("blockhash: A must be a positive finite number (0: the default, 8), got " + std::to_string(p.A));
}

BlockHashIndex::RecallTuning BlockHashIndex::recall_tuning(const SearchParams& p) const {
  // Tuned without the radius (in whichever coordinates the caller's path holds it): the budget
  // a recall needs does not depend on it.
  auto key = std::make_tuple(p.k, p.neighbour_probes, p.recall_target);
  SearchParams tp = p;
  tp.max_radius = INFINITY;
  std::lock_guard<std::mutex> lock(tune_mutex_);
  auto it = tuned_.find(key);
  if (it != tuned_.end()) return it->second;
  RecallTuning t = tune_for_recall(p.recall_target, tp);
  tuned_[key] = t;
  return t;
}

float BlockHashIndex::resolved_A(const SearchParams& p) const {
  if (info_.grid && p.recall_target >= 1) return INFINITY;  // the exact mode
  if (p.recall_target > 0) return recall_tuning(p).A;
  if (p.A == 0) return info_.grid ? INFINITY : 8.0f;  // the index's default (SearchParams::A)
  return p.A;
}

std::string BlockHashIndex::kernel_options(int kmax) const {
  std::ostringstream os;
  if (info_.grid) {
    // The register list and the prefetch where the compiler vectorises (CPU devices: the quirks
    // list); the scalar list on GPUs and past 64 entries.
    const bool cpu = runtime().quirks().vector_scan;
    os << "-DBHCL_KMAX=" << kmax << " -DBHCL_GRID_VTOPK=" << (cpu && kmax <= 64 ? 1 : 0)
       << " -DBHCL_GRID_PREFETCH=" << (cpu ? 2 : 0) << " -DBHCL_GRID_ROWCAP=" << blockhash::grid_row_cap(cpu);
    return os.str();
  }
  if (info_.cell_aligned) {
    os << "-DBHCL_KMAX=" << kmax << " -DBHCL_BH_MAXKEEP=" << blockhash::scan_cap(kmax, info_.X)
       << " -DBHCL_BH_VECSCAN=" << (runtime().quirks().vector_scan ? 1 : 0);
    return os.str();
  }
  os << "-DBHCL_KMAX=" << kmax << " -DBHCL_BH_L=" << info_.L
     << " -DBHCL_BH_DIRECT=" << (info_.direct_addressing ? 1 : 0)
     << " -DBHCL_BH_BOXSKIP=" << (info_.box_skip && !info_.box_order ? 1 : 0)
     << " -DBHCL_BH_BOXORDER=" << (info_.box_order ? 1 : 0);
  // Only the defines the variant uses, so that indexes differing elsewhere share a program.
  if (info_.box_order) os << " -DBHCL_BH_MAXKEEP=" << blockhash::scan_cap(kmax, info_.X);
  else os << " -DBHCL_BH_SCANCAP=" << blockhash::scan_cap(kmax, info_.X);
  return os.str();
}

cl::Event BlockHashIndex::enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                        std::size_t first, std::size_t count,
                                        const ResultBuffers& out, const SearchParams& params_in,
                                        std::size_t local_size,
                                        const std::vector<cl::Event>* wait) const {
  const cl::Buffer* examined = params_in.count_examined ? &out.examined : nullptr;
  SearchParams params = params_in;
  params.A = resolved_A(params_in);
  params.recall_target = 0;
  int kmax = kmax_variant(params.k);
  // The arguments both block-hash kernels end with: the queries, k, radius, budget, the blocks a
  // query keeps, the results and the examined counts.
  auto add_query_args = [&](detail::KernelArgs& args) {
    args.add_queries(queries, first, count, params)
        .add(cl_uint(budget(params)))
        .add(cl_uint(blockhash::keep_blocks(budget(params), kmax, info_.X)))
        .add_results(out)
        .add(examined ? *examined : dummy_)
        .add(cl_uint(examined ? 1 : 0));
  };
  if (info_.grid) {
    const char* gname = "blockhash_grid_knn";
    cl::Kernel kernel = runtime().kernel(std::string(gname) + ".cl", gname,
                                         detail::with_defines(kernel_options(kmax), params));
    detail::KernelArgs args(kernel, gname);
    add_grid_args(args);
    args.add_queries(queries, first, count, params)
        .add(cl_uint(budget(params)))
        .add_results(out)
        .add(examined ? *examined : dummy_)
        .add(cl_uint(examined ? 1 : 0));
    return detail::launch_1d(queue, kernel, count, local_size, wait, gname);
  }
  // The two layouts' kernels share their first and last arguments.
  const char* name = info_.cell_aligned ? "blockhash_cells_knn" : "blockhash_knn";
  cl::Kernel kernel = runtime().kernel(std::string(name) + ".cl", name,
                                       detail::with_defines(kernel_options(kmax), params));
  detail::KernelArgs args(kernel, name);
  args.add(blocks_).add(boxes_).add(thresholds_).add(cl_uint(info_.P)).add(keys_);
  if (info_.cell_aligned) {
    args.add(cl_uint(s_->keys.size()))
        .add(buckets_)
        .add(cell_table_)
        .add(cl_uint(cell_dy_))
        .add(cl_uint(cell_dz_))
        .add(cl_uint(cells_probes(params)))
        .add(block_keys_)
        .add(cl_uint(s_->blocks.size()))
        .add(cl_uint(s_->cell_bits()))
        .add(cl_uint(blockhash::cells_seed_side(info_.hilbert_seed, params.k)));
  } else {
    bool probes = params.neighbour_probes < 0 ? info_.neighbour_probes : params.neighbour_probes == 1;
    args.add(table_starts_)
        .add(buckets_)
        .add(refs_)
        .add(cl_uint(probes ? 1 : 0))
        .add(block_keys_)
        .add(cl_uint(s_->blocks.size()))
        .add(cl_float4{{s_->q_origin[0], s_->q_origin[1], s_->q_origin[2], s_->q_scale}})
        .add(cl_uint(s_->q_bits))
        .add(cl_uint(blockhash::seed_side(info_.hilbert_seed, params.k, info_.X)));
  }
  add_query_args(args);
  return detail::launch_1d(queue, kernel, count, local_size, wait, name);
}

cl::Event BlockHashIndex::enqueue_radius_batch(const cl::CommandQueue& queue,
                                               const cl::Buffer& queries, std::size_t first,
                                               std::size_t count, float r2, int pass,
                                               const RadiusBuffers& out, const RadiusParams& params,
                                               std::size_t local_size,
                                               const std::vector<cl::Event>* wait) const {
  if (info_.grid) {
    const char* gname = "blockhash_grid_radius";
    cl::Kernel kernel = runtime().kernel(std::string(gname) + ".cl", gname, params.kernel_defines);
    detail::KernelArgs args(kernel, gname);
    add_grid_args(args);
    args.add(cl_uint(params.budget)).add_radius(queries, first, count, r2, pass, out, params.count_examined);
    return detail::launch_1d(queue, kernel, count, local_size, wait, gname);
  }
  SearchParams sp;
  sp.neighbour_probes = params.neighbour_probes;
  const char* name = info_.cell_aligned ? "blockhash_cells_radius" : "blockhash_radius";
  std::ostringstream options;
  if (!info_.cell_aligned)
    options << "-DBHCL_BH_L=" << info_.L << " -DBHCL_BH_DIRECT=" << (info_.direct_addressing ? 1 : 0)
            << " -DBHCL_BH_SCANCAP=" << blockhash::scan_cap(kMaxK, info_.X);
  if (!params.kernel_defines.empty()) options << " " << params.kernel_defines;
  cl::Kernel kernel = runtime().kernel(std::string(name) + ".cl", name, options.str());
  detail::KernelArgs args(kernel, name);
  args.add(blocks_).add(boxes_).add(thresholds_).add(cl_uint(info_.P)).add(keys_);
  if (info_.cell_aligned) {
    args.add(cl_uint(s_->keys.size()))
        .add(buckets_)
        .add(cell_table_)
        .add(cl_uint(cell_dy_))
        .add(cl_uint(cell_dz_))
        .add(cl_uint(cells_probes(sp)));
  } else {
    bool probes = params.neighbour_probes < 0 ? info_.neighbour_probes : params.neighbour_probes == 1;
    args.add(table_starts_).add(buckets_).add(refs_).add(cl_uint(probes ? 1 : 0));
  }
  args.add(cl_uint(params.budget)).add_radius(queries, first, count, r2, pass, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, name);
}

std::uint32_t BlockHashIndex::row_cap_for(const SearchParams& p) const {
  // The kernel's BHCL_GRID_ROWCAP: the device's, unless the caller's defines override it (the last
  // -D of a name wins, as in the OpenCL compiler).
  std::uint32_t cap = blockhash::grid_row_cap(runtime().quirks().vector_scan);
  const std::string key = "-DBHCL_GRID_ROWCAP=";
  for (std::size_t at = p.kernel_defines.find(key); at != std::string::npos; at = p.kernel_defines.find(key, at + 1))
    cap = static_cast<std::uint32_t>(std::strtoul(p.kernel_defines.c_str() + at + key.size(), nullptr, 10));
  return cap;
}

void BlockHashIndex::add_grid_args(detail::KernelArgs& args) const {
  const bhcl_grid_geom& g = s_->grid->geom;
  args.add(g_starts_).add(g_x_).add(g_y_).add(g_z_).add(g_ids_)
      .add(cl_float4{{g.ox, g.oy, g.oz, g.h}})
      .add(cl_float4{{g.inv_h, g.margin, 0.0f, 0.0f}})
      .add(cl_uint4{{g.nx, g.ny, g.nz, g.sparse}});
}

KnnResult BlockHashIndex::reference_query(const float* queries, std::size_t n,
                                          const SearchParams& params_in,
                                          std::vector<std::int32_t>* examined,
                                          unsigned threads) const {
  check_params(params_in);
  // The same path as query(): the tuned A, queries and radius in the structure's coordinates,
  // distances back in the caller's.
  SearchParams params = scaled(params_in);
  params.A = resolved_A(params_in);
  params.recall_target = 0;
  std::vector<float> storage;
  queries = to_structure(queries, n, storage);
  KnnResult out;
  if (info_.grid) {
    blockhash::reference_query_grid(*s_->grid, queries, n, params.k, detail::squared_radius(params.max_radius),
                                    budget(params), row_cap_for(params), out, examined, threads);
  } else if (info_.cell_aligned) {
    blockhash::reference_query_cells(*s_, queries, n, params, cells_probes(params), out, examined, threads);
  } else {
    bool probes = params.neighbour_probes < 0 ? info_.neighbour_probes : params.neighbour_probes == 1;
    blockhash::reference_query(*s_, queries, n, params, probes, out, examined, threads);
  }
  distances_to_caller(out.dist2.data(), out.dist2.size());
  return out;
}


}  // namespace bhcl
