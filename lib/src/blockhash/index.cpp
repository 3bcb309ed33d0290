// BlockHashIndex: runs the build stages, uploads the arrays, saves and loads; the search side is
// search.cpp.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <cstring>
#include <initializer_list>
#include <sstream>
#include <utility>

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
                  "%s directory %.1f MB  build %.3f s (tune %.3f, cells %.3f, bucket %.3f, sort %.3f, occupancy %.3f, upload %.3f)",
                  grid_dims[0], grid_dims[1], grid_dims[2], cell_size, occupied_cells, mean_cell_points,
                  grid_capped ? " (cells grown to fit the table)" : "", grid_two_level ? "two-level" : "direct",
                  double(grid_directory_bytes) / 1e6, t_total, t_tune, t_cells, t_count, t_scatter, t_occupancy, t_upload);
    return buf;
  }
  std::snprintf(buf, sizeof buf,
                "preset %s%s  L %d  P %d  B %d  X %d  blocks %zu  occupied cells %zu  overflowed %zu  "
                "refs %zu (%.2f/point)  median cell %.0f points / %.0f blocks (p90 %.0f)  build %.2f s "
                "(hilbert %.2f, blocks %.2f, params %.2f, thresholds %.2f, tables %.2f, upload %.2f)",
                BlockHashBuildParams::preset_name(preset), box_order ? " (box order)" : "", L, P, B, X, n_blocks, occupied_cells,
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
  in.n_points = s.n_points;
}

// The names of the fields marked set, comma separated ("" for none).
std::string names_set(std::initializer_list<std::pair<bool, const char*>> fields) {
  std::string s;
  for (const auto& [set, name] : fields)
    if (set) s += (s.empty() ? "" : ", ") + std::string(name);
  return s;
}

// The block-layout fields the caller set.
std::string block_fields_set(const BlockHashBuildParams& p) {
  const BlockHashBuildParams d;
  return names_set({{p.L > 0, "L"},
                    {p.P > 0, "P"},
                    {p.B > 0, "B"},
                    {p.X > 0, "X"},
                    {p.box_order >= 0, "box_order"},
                    {p.box_skip >= 0, "box_skip"},
                    {p.direct_addressing >= 0, "direct_addressing"},
                    {p.guard_thresholds >= 0, "guard_thresholds"},
                    {p.keep_top_count >= 0, "keep_top_count"},
                    {p.hilbert_seed >= 0, "hilbert_seed"},
                    {p.b_percentile != d.b_percentile, "b_percentile"},
                    {p.design_A != d.design_A, "design_A"},
                    {p.design_k != d.design_k, "design_k"},
                    {p.hist_bins != d.hist_bins, "hist_bins"},
                    {p.hilbert_bits != d.hilbert_bits, "hilbert_bits"},
                    {p.neighbour_probes >= 0, "neighbour_probes"}});
}

// The grid's own fields the caller set.
std::string grid_fields_set(const BlockHashBuildParams& p) {
  return names_set({{p.cell_size != -1, "cell_size"},
                    {p.max_cells_per_point != BlockHashBuildParams{}.max_cells_per_point, "max_cells_per_point"},
                    {p.grid_directory != -1, "grid_directory"}});
}

// Refuses fields of another layout: "blockhash: F is an option of <whose>" ("F, G are options").
[[noreturn]] void refuse_fields(const std::string& fields, const std::string& whose) {
  throw Error("blockhash: " + fields + (fields.find(',') == std::string::npos ? " is an option" : " are options") +
              " of " + whose);
}

// Which layout a build makes, chosen explicitly: the auto preset's grid (grid -1 or 1), auto's L
// tables with grid = 0, the paper presets' L tables. An option of another layout is refused, never obeyed silently (a
// block-layout field used to switch auto off the grid).
bool wants_grid(const BlockHashBuildParams& p) {
  if (p.grid != -1 && p.grid != 0 && p.grid != 1)
    throw Error("blockhash: grid must be -1 (preset), 0 or 1, got " + std::to_string(p.grid));
  const bool paper = BlockHashBuildParams::is_paper(p.preset);
  if (paper && p.grid == 1)
    throw Error(std::string("blockhash: grid = 1 is the auto preset's layout; the ") +
                BlockHashBuildParams::preset_name(p.preset) + " preset has its own");
  const bool grid = !paper && p.grid != 0;
  const std::string other = grid ? block_fields_set(p) : grid_fields_set(p);
  if (!other.empty() && grid)
    refuse_fields(other, "the block layouts; the auto preset builds the grid (set grid = 0 for auto's "
                         "L tables, or preset = paper for the talk's)");
  if (!other.empty())
    refuse_fields(other, std::string("the grid (the auto preset's layout), not of the ") +
                             (paper ? "paper preset's tables" : "block layouts (grid = 0)"));
  return grid;
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

std::unique_ptr<BlockHashIndex> BlockHashIndex::build(std::shared_ptr<Runtime> runtime, const float* points,
                                                      std::size_t n_points, const BlockHashBuildParams& params) {
  return std::make_unique<BlockHashIndex>(std::move(runtime), points, n_points, params);
}

const float* BlockHashIndex::begin_build(const float* points, std::size_t n_points, std::vector<float>& scaled) {
  points = prepare_points(points, n_points, scaled);  // validates; extreme scales
  s_->n_points = n_points;
  s_->scale_exp = scale_exponent();
  return points;
}

void BlockHashIndex::build_grid_layout(const float* points, std::size_t n_points, double cell_size) {
  auto t0 = std::chrono::steady_clock::now();
  std::vector<float> scaled;
  points = begin_build(points, n_points, scaled);
  blockhash::GridInput in;
  in.xyz = points;
  in.n_aos = n_points;
  build_grid_scaled(in, cell_size, t0);
}

void BlockHashIndex::build_grid_scaled(const blockhash::GridInput& input, double cell_size,
                                       std::chrono::steady_clock::time_point t0) {
  using namespace blockhash;
  Structure& s = *s_;
  s.n_points = input.size();
  if (!s.grid) s.grid = std::make_shared<Grid>();
  release_grid_views();  // the build rewrites the arrays a device view may still show
  GridBuildParams gp;
  // The cell side is kept in the caller's units; the grid is built in the index's coordinates.
  gp.cell_size = cell_size > 0 ? std::ldexp(cell_size, -s.scale_exp) : -1.0;
  gp.target_cell_points = params_.target_cell_points > 0 ? params_.target_cell_points : 24.0;
  gp.max_cells_per_point = params_.max_cells_per_point;
  gp.directory = params_.grid_directory;
  gp.threads = params_.threads;
  GridBuildStats st;
  build_grid(input, gp, *s.grid, &st);
  ++grid_builds_;  // an update's stats count its builds from this (grid_update.cpp)
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
  in.t_occupancy = st.t_occupancy;
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

bool BlockHashIndex::grid_in_place() const { return runtime_ptr()->quirks().host_ptr_in_place; }

void BlockHashIndex::release_grid_views() {
  if (!grid_in_place()) return;
  g_starts_ = g_x_ = g_y_ = g_z_ = g_ids_ = g_occ_ = cl::Buffer();
  g_starts_cap_ = g_points_cap_ = g_occ_cap_ = 0;
}

void BlockHashIndex::upload_grid() {
  const auto& rt = runtime_ptr();
  const blockhash::Grid& g = *s_->grid;
  if (grid_in_place()) {
    // Views of the host arrays, no copy: the kernels only read them, and the host writes them
    // only after release_grid_views (every build and update calls it first).
    auto view = [&](cl::Buffer& buf, const void* data, std::size_t bytes, const char* what) {
      cl_int err = CL_SUCCESS;
      buf = cl::Buffer(rt->context(), CL_MEM_READ_ONLY | CL_MEM_USE_HOST_PTR, std::max<std::size_t>(bytes, 4),
                       const_cast<void*>(data), &err);
      check_cl(err, "clCreateBuffer", std::string(what) + " (in place), " + std::to_string(bytes) + " bytes");
    };
    view(g_starts_, g.starts.data(), g.starts.size() * 4, "blockhash grid cells");
    view(g_x_, g.x.data(), g.x.size() * 4, "blockhash grid x");
    view(g_y_, g.y.data(), g.y.size() * 4, "blockhash grid y");
    view(g_z_, g.z.data(), g.z.size() * 4, "blockhash grid z");
    view(g_ids_, g.ids.data(), g.ids.size() * 4, "blockhash grid ids");
    view(g_occ_, g.occ.data(), g.occ.size(), "blockhash grid occupancy");
    g_starts_cap_ = g.starts.size() * 4;
    g_occ_cap_ = g.occ.size();
    g_points_cap_ = g.x.size() * 4;
    if (!dummy_()) dummy_ = detail::upload_vector(rt, std::vector<std::int32_t>(1, 0), "blockhash dummy");
    return;
  }
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
  std::size_t ocap = g_occ_cap_;
  put(g_occ_, ocap, g.occ.data(), g.occ.size(), grow(ocap, g.occ.size()), "blockhash grid occupancy");
  g_occ_cap_ = ocap;
  if (!dummy_()) dummy_ = detail::upload_vector(rt, std::vector<std::int32_t>(1, 0), "blockhash dummy");
}

void BlockHashIndex::build_blocks(const float* points, std::size_t n_points) {
  const BlockHashBuildParams& params = params_;
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

namespace {
// The caller's points give a row per id issued: a file whose id bound differs is refused before
// anything is sized by that bound (issue 38: a crafted bound of 2^31 - 2 in a few KB).
void check_rows(const std::string& path, std::int64_t rows, std::int64_t bound, std::size_t live) {
  if (rows < 0 || rows == bound) return;
  throw Error(path + ": the saved index holds " + std::to_string(live) + " points" +
              (std::size_t(bound) != live ? " of ids 0 .. " + std::to_string(bound - 1) +
                                                " (give a row for every id, removed ones included)"
                                          : std::string()) +
              ", the point set " + std::to_string(rows));
}
}  // namespace

std::unique_ptr<BlockHashIndex> BlockHashIndex::load(std::shared_ptr<Runtime> runtime,
                                                     const std::string& path, std::int64_t rows) {
  if (blockhash::is_grid_file(path)) {
    blockhash::GridIdState st;
    blockhash::GridFile f = blockhash::load_grid(path, &st);
    check_rows(path, rows, st.id_bound, st.live);
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
  check_rows(path, rows, bound, s->n_points);
  std::unique_ptr<BlockHashIndex> bh(new BlockHashIndex(std::move(runtime), std::move(s)));
  if (bound != std::int64_t(bh->size())) bh->loaded_update_state(bound);  // sparse ids after removals
  // An update rebuilds a block layout (blocks_update) from the build parameters: the saved
  // layout's preset and kind (the others as their defaults derive them).
  bh->params_.preset = bh->info_.preset;
  if (bh->info_.preset == BlockHashBuildParams::Preset::Auto) {
    bh->params_.grid = 0;  // auto's L tables
    bh->params_.L = bh->info_.L;
  }
  if (bh->info_.preset == BlockHashBuildParams::Preset::PaperCells) {
    // Its P and B came from the design k and A, which the file does not hold: keep the saved ones.
    bh->params_.P = bh->info_.P;
    bh->params_.B = bh->info_.B;
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
}

std::size_t BlockHashIndex::memory_bytes() const {
  if (s_->grid) return s_->grid->device_bytes();
  return s_->device_bytes();
}

std::size_t BlockHashIndex::host_bytes() const {
  // The grid's host vectors mirror its device arrays one for one; a block layout keeps its
  // structure's arrays and the Hilbert order.
  // The grid also keeps its build scratch (cells, records: 20 B per point) for rebuilds, and an
  // insert's merge arrays (16 B per point) once it has had one.
  if (s_->grid) {
    const blockhash::Grid& g = *s_->grid;
    std::size_t scratch = 0;
    if (g.scratch) {
      const blockhash::GridScratch& sc = *g.scratch;
      scratch = (sc.cell.capacity() + sc.rec.capacity()) * 4 +
                (sc.x.capacity() + sc.y.capacity() + sc.z.capacity() + sc.ids.capacity()) * 4;
    }
    // Read in place by the device (Quirks::host_ptr_in_place): the arrays are memory_bytes().
    return (grid_in_place() ? 0 : g.device_bytes()) + scratch;
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

}  // namespace bhcl
