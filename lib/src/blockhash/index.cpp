// BlockHashIndex, the family's shared part: the factory that picks the layout and hands it its own
// parameters, load's dispatch, the build's opening, the indexed points and the update hooks'
// shared part. The layouts: grid_index.cpp (GridIndex), tables_index.cpp (BlockTablesIndex).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <initializer_list>
#include <utility>

#include "blockhash/build.hpp"
#include "blockhash/grid_io.hpp"
#include "blockhash/options.hpp"
#include "blockhash_cl/block_tables.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/grid_index.hpp"
#include "core/device_util.hpp"

namespace bhcl {

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

// The names of the fields marked set, comma separated ("" for none).
std::string names_set(std::initializer_list<std::pair<bool, const char*>> fields) {
  std::string s;
  for (const auto& [set, name] : fields)
    if (set) s += (s.empty() ? "" : ", ") + std::string(name);
  return s;
}

// The L tables' fields the caller set.
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

// The grid's fields of the user's parameters (the list names each field the two structs share).
GridBuildParams grid_params(const BlockHashBuildParams& from) {
  GridBuildParams to;
#define BHCL_COPY_FIELD(f) to.f = from.f;
  BHCL_COPY_FIELD(cell_size) BHCL_COPY_FIELD(target_cell_points) BHCL_COPY_FIELD(max_cells_per_point)
  BHCL_COPY_FIELD(grid_directory) BHCL_COPY_FIELD(threads) BHCL_COPY_FIELD(verbose)
#undef BHCL_COPY_FIELD
  return to;
}

}  // namespace

std::unique_ptr<BlockHashIndex> BlockHashIndex::build(std::shared_ptr<Runtime> runtime, const float* points,
                                                      std::size_t n_points, const BlockHashBuildParams& params) {
  check_build_fields(blockhash::option_table(), &params, "blockhash");  // every range, from the table
  if (wants_grid(params)) return std::make_unique<GridIndex>(std::move(runtime), points, n_points, grid_params(params));
  return std::make_unique<BlockTablesIndex>(std::move(runtime), points, n_points, blockhash::table_params(params));
}

void BlockHashIndex::prepare_knn(const Runtime& rt, const BlockHashBuildParams& params, const SearchParams& search) {
  check_build_fields(blockhash::option_table(), &params, "blockhash");
  if (wants_grid(params)) GridIndex::prepare_knn_program(rt, search);
}

BlockHashIndex::BlockHashIndex(std::shared_ptr<Runtime> runtime, std::size_t n_points)
    : Index(std::move(runtime), n_points), s_(std::make_unique<blockhash::Structure>()) {}

BlockHashIndex::BlockHashIndex(std::shared_ptr<Runtime> runtime, std::unique_ptr<blockhash::Structure> s)
    : Index(std::move(runtime), s->n_points), s_(std::move(s)) {
  set_scale_exponent(s_->scale_exp);
}

BlockHashIndex::~BlockHashIndex() = default;

const float* BlockHashIndex::begin_build(const float* points, std::size_t n_points, std::vector<float>& scaled) {
  points = prepare_points(points, n_points, scaled);  // validates; extreme scales
  forget_tunings();  // a rebuild over other points: nothing tuned on the old ones holds
  s_->n_points = n_points;
  s_->scale_exp = scale_exponent();
  return points;
}

void BlockHashIndex::upload_dummy() {
  if (!dummy_()) dummy_ = detail::upload_vector(runtime_ptr(), std::vector<std::int32_t>(1, 0), "blockhash dummy");
}

// The caller's points give a row per id issued: a file whose id bound differs is refused before
// anything is sized by that bound (issue 38: a crafted bound of 2^31 - 2 in a few KB).
void BlockHashIndex::check_rows(const std::string& path, std::int64_t rows, std::int64_t bound, std::size_t live) {
  if (rows < 0 || rows == bound) return;
  throw Error(path + ": the saved index holds " + std::to_string(live) + " points" +
              (std::size_t(bound) != live ? " of ids 0 .. " + std::to_string(bound - 1) +
                                                " (give a row for every id, removed ones included)"
                                          : std::string()) +
              ", the point set " + std::to_string(rows));
}

std::unique_ptr<BlockHashIndex> BlockHashIndex::load(std::shared_ptr<Runtime> runtime,
                                                     const std::string& path, std::int64_t rows) {
  if (blockhash::is_grid_file(path)) return GridIndex::load_saved(std::move(runtime), path, rows);
  return BlockTablesIndex::load_saved(std::move(runtime), path, rows);
}

std::vector<float> BlockHashIndex::indexed_points(std::vector<std::int32_t>* ids) const {
  const int e = s_->scale_exp;
  // Slot of each id (ids after updates are sparse in [0, id_bound()); holes carry the empty-slot
  // id and are skipped), then the points in ascending id order.
  const std::size_t bound = std::size_t(id_bound());
  std::vector<float> byid(3 * bound, NAN);
  std::vector<char> have(bound, 0);
  visit_stored_points([&](std::int32_t id, float x, float y, float z) {
    if (id < 0 || std::size_t(id) >= bound) return;  // a hole
    byid[3 * std::size_t(id)] = std::ldexp(x, e);
    byid[3 * std::size_t(id) + 1] = std::ldexp(y, e);
    byid[3 * std::size_t(id) + 2] = std::ldexp(z, e);
    have[std::size_t(id)] = 1;
  });
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
  return first_stored_mismatch(points);
}

void BlockHashIndex::insert_points(const float* points, const float* scaled, std::size_t n, std::int32_t first) {
  const auto t0 = std::chrono::steady_clock::now();
  check_cl(runtime_ptr()->queue().finish(), "clFinish", "blockhash insert");
  insert_stored(points, scaled, n, first);
  forget_tunings();
  info_.t_update += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void BlockHashIndex::remove_points(const std::int32_t* ids, std::size_t n) {
  const auto t0 = std::chrono::steady_clock::now();
  check_cl(runtime_ptr()->queue().finish(), "clFinish", "blockhash remove");
  remove_stored(ids, n);
  forget_tunings();
  info_.t_update += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void BlockHashIndex::forget_tunings() {
  // The recall tunings (tune_for_recall's and params_for_batch's) and the exact kd-tree over the
  // indexed points that params_for_batch checks its tunings against: after an update a cached
  // tuning, or a tuning against the old points' exact answers, would pick A for another set.
  std::lock_guard<std::mutex> lock(tune_mutex_);
  tuned_.clear();
  batch_tuned_.clear();
  exact_.reset();
  exact_ids_.clear();
}

double BlockHashIndex::talk_overhead(std::size_t N, double A, int k, int X) {
  double n = double(N), l = std::log(std::max(n, 2.0));
  return (4.0 * (A * k / X) * l * l * l + 12.0 * l * l + 1.6 * n) / (24.0 * n);
}

}  // namespace bhcl
