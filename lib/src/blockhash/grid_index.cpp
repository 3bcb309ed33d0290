// GridIndex: the grid's build, upload, save / load and rebuild, its search side (parameter
// checks, kernel options and arguments, the kNN and radius dispatch, the host reference); its
// updates are grid_update.cpp, its build stages grid_build.cpp.
#include "blockhash_cl/grid_index.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>

#include "bhcl_shared.h"
#include "blockhash/build.hpp"
#include "blockhash/grid_io.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/kernel_forms.hpp"
#include "core/device_util.hpp"
#include "core/kernel_defines.hpp"

namespace bhcl {
namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

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

// The grid's ranges (the option table's, for a caller that builds a GridIndex directly).
void check_grid_params(const GridBuildParams& p) {
  if (!(p.cell_size == -1 || (p.cell_size > 0 && p.cell_size <= 1e30)))
    throw Error("blockhash: cell_size must be -1 (derive) or a length in (0, 1e30], got " + std::to_string(p.cell_size));
  if (!(p.target_cell_points == -1 || (p.target_cell_points >= 1 && p.target_cell_points <= 1e6)))
    throw Error("blockhash: target_cell_points must be -1 (derive) or in [1, 1e6], got " + std::to_string(p.target_cell_points));
  if (!(p.max_cells_per_point >= 0.01 && p.max_cells_per_point <= 1024))
    throw Error("blockhash: max_cells_per_point must be in [0.01, 1024], got " + std::to_string(p.max_cells_per_point));
  if (p.grid_directory < -1 || p.grid_directory > 1)
    throw Error("blockhash: grid_directory must be -1 (by max_cells_per_point), 0 or 1, got " +
                std::to_string(p.grid_directory));
}

}  // namespace

GridIndex::GridIndex(std::shared_ptr<Runtime> runtime, const float* points, std::size_t n_points,
                     const GridBuildParams& params)
    : BlockHashIndex(std::move(runtime), n_points), params_(params) {
  check_grid_params(params);
  build_layout(points, n_points, params.cell_size);
}

GridIndex::~GridIndex() = default;

void GridIndex::build_layout(const float* points, std::size_t n_points, double cell_size) {
  auto t0 = std::chrono::steady_clock::now();
  std::vector<float> scaled;
  points = begin_build(points, n_points, scaled);
  blockhash::GridInput in;
  in.xyz = points;
  in.n_aos = n_points;
  build_scaled(in, cell_size, t0);
}

void GridIndex::build_scaled(const blockhash::GridInput& input, double cell_size,
                             std::chrono::steady_clock::time_point t0) {
  using namespace blockhash;
  Structure& s = *s_;
  s.n_points = input.size();
  if (!s.grid) s.grid = std::make_shared<Grid>();
  release_grid_views();  // the build rewrites the arrays a device view may still show
  GridBuildArgs gp;
  // The cell side is kept in the caller's units; the grid is built in the index's coordinates.
  gp.cell_size = cell_size > 0 ? std::ldexp(cell_size, -s.scale_exp) : -1.0;
  // Unset: the device's kernel form's population (24 on every row measured so far).
  gp.target_cell_points = params_.target_cell_points > 0 ? params_.target_cell_points
                                                         : detail::grid_kernel_form(runtime().info()).cell_target;
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

void GridIndex::rebuild(const float* points, std::size_t n_points) {
  id_pos_.clear();  // a new point set: ids 0 .. n - 1 again (set_size), no update state
  grid_build_mean_ = 0;
  // The previous build's cell side (caller units) and the same table limits.
  set_size(n_points);
  build_layout(points, n_points, info_.cell_size);
}

bool GridIndex::grid_in_place() const { return runtime_ptr()->quirks().host_ptr_in_place; }

void GridIndex::release_grid_views() {
  if (!grid_in_place()) return;
  g_starts_ = g_x_ = g_y_ = g_z_ = g_ids_ = g_occ_ = cl::Buffer();
  g_starts_cap_ = g_points_cap_ = g_occ_cap_ = 0;
}

void GridIndex::upload_grid() {
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
    upload_dummy();
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
  upload_dummy();
}

GridIndex::GridIndex(std::shared_ptr<Runtime> runtime, std::unique_ptr<blockhash::Structure> s)
    : BlockHashIndex(std::move(runtime), std::move(s)) {
  auto t0 = std::chrono::steady_clock::now();
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
}

std::unique_ptr<GridIndex> GridIndex::load_saved(std::shared_ptr<Runtime> runtime, const std::string& path,
                                                 std::int64_t rows) {
  blockhash::GridIdState st;
  blockhash::GridFile f = blockhash::load_grid(path, &st);
  check_rows(path, rows, st.id_bound, st.live);
  auto s = std::make_unique<blockhash::Structure>();
  s->n_points = f.grid.n_points;
  s->scale_exp = f.scale_exp;
  s->grid = std::make_shared<blockhash::Grid>(std::move(f.grid));
  std::unique_ptr<GridIndex> g(new GridIndex(std::move(runtime), std::move(s)));
  g->params_.target_cell_points = f.target_cell_points;
  g->loaded_update_state(st);  // grid_update.cpp
  return g;
}

void GridIndex::save(const std::string& path) const {
  // After updates the file holds the id bound, the live ids and the holes as they are
  // (grid_io.cpp): a load answers as this index, with the same ids.
  ReadLock lock(*this);
  blockhash::GridFile f;
  f.grid = *s_->grid;
  f.scale_exp = s_->scale_exp;
  f.target_cell_points = params_.target_cell_points;
  blockhash::save_grid(f, grid_update_state(), path);  // grid_update.cpp
}

void GridIndex::visit_stored_points(const PointVisitor& visit) const {
  const blockhash::Grid& g = *s_->grid;
  for (std::size_t i = 0; i < g.n_points; ++i) visit(g.ids[i], g.x[i], g.y[i], g.z[i]);
}

long GridIndex::first_stored_mismatch(const float* points) const {
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

std::size_t GridIndex::memory_bytes() const { return s_->grid->device_bytes(); }

std::size_t GridIndex::host_bytes() const {
  // The host vectors mirror the device arrays one for one, and the build scratch (cells,
  // records: 20 B per point) is kept for rebuilds, with an insert's merge arrays (16 B per point)
  // once it has had one.
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

double GridIndex::measured_overhead() const {
  // Everything beyond the points' own records (16 B: x, y, z, id), over the talk's 24 per photon.
  return (double(memory_bytes()) - 16.0 * double(size())) / (24.0 * double(size()));
}

// ---- The search side ---------------------------------------------------------------------------

void GridIndex::check_params(const SearchParams& p) const {
  Index::check_params(p);
  // The rings reach every cell within the bound: the probes are an option of the L tables,
  // refused here rather than accepted and ignored.
  if (p.neighbour_probes != -1)
    throw Error("blockhash: neighbour_probes (probes) is an option of the L tables (grid = 0, preset paper); "
                "the grid's rings reach every cell within the bound: leave it -1, got " +
                std::to_string(p.neighbour_probes));
  if (!(p.recall_target >= 0 && p.recall_target <= 1))
    throw Error("blockhash: recall_target must be in [0, 1] (0 = use A, 1 = exact), got " + std::to_string(p.recall_target));
  if (p.recall_target > 0 && p.recall_target < 1) {
    resolved_A(p);  // tunes now (once per k and target), outside any dispatch lock
    return;
  }
  if (!(p.A >= 0))
    throw Error("blockhash: A must be positive (+inf: exact; 0: the default, exact), got " + std::to_string(p.A));
}

detail::DefineValues GridIndex::kernel_options(const Runtime& rt, int kmax) {
  // The device's row of the forms table (core/kernel_forms.cpp); the scalar list past 64 entries.
  const detail::GridKernelForm& f = detail::grid_kernel_form(rt.info());
  detail::DefineValues v = {{"BHCL_KMAX", kmax},
                            {"BHCL_GRID_VTOPK", f.vtopk && kmax <= 64 ? 1 : 0},
                            {"BHCL_GRID_PREFETCH", f.prefetch},
                            {"BHCL_GRID_ROWCAP", f.row_cap},
                            {"BHCL_GRID_WALKCAP", f.walk_cap}};
  if (f.fill_sort >= 0) v.push_back({"BHCL_GRID_FILLSORT", f.fill_sort});
  if (f.prefetch_lines >= 0) v.push_back({"BHCL_GRID_PREFETCH_LINES", f.prefetch_lines});
  // Only where it differs from the kernel's default (1): the other variants' programs, and their
  // binary-cache keys, stay as they were.
  if (f.prefetch > 0 && kmax < f.prefetch_ring_from) v.push_back({"BHCL_GRID_PREFETCH_RING", 0});
  return v;
}

namespace {
constexpr const char* kKnnKernel = "blockhash_grid_knn";  // in blockhash_grid_knn.cl
}

void GridIndex::prepare_knn_program(const Runtime& rt, const SearchParams& params) {
  // The program layout_kernel's enqueue_batch asks for (Runtime::program caches it by file and
  // options): the defines of the caller's k and the device's form.
  const std::string file = std::string(kKnnKernel) + ".cl";
  rt.program(file, detail::kernel_build_options(file, kernel_options(rt, kmax_variant(params.k)), params.kernel_defines));
}

cl::Event GridIndex::enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries, std::size_t first,
                                   std::size_t count, const ResultBuffers& out, const SearchParams& params_in,
                                   std::size_t local_size, const std::vector<cl::Event>* wait) const {
  const SearchParams params = resolved(params_in);
  const char* name = kKnnKernel;
  cl::Kernel kernel = layout_kernel(name, kernel_options(runtime(), kmax_variant(params.k)), params.kernel_defines);
  detail::KernelArgs args(kernel, name);
  add_grid_args(args);
  args.add_queries(queries, first, count, params)
      .add(cl_uint(blockhash::grid_budget(budget(params), s_->grid->n_points, info_.holes)));
  add_knn_results(args, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, name);
}

BlockHashIndex::RadiusKernel GridIndex::radius_kernel() const { return {"blockhash_grid_radius", {}}; }

void GridIndex::add_radius_layout_args(detail::KernelArgs& args, const RadiusParams&) const { add_grid_args(args); }

std::size_t GridIndex::default_local_size() const {
  const std::size_t form = detail::grid_kernel_form(runtime().info()).local_size;
  const std::size_t max = runtime().info().max_work_group_size;
  return form ? (max ? std::min(form, max) : form) : Index::default_local_size();
}

blockhash::GridTraversal GridIndex::traversal_for(const SearchParams& p) const {
  const detail::GridKernelForm& f = detail::grid_kernel_form(runtime().info());
  return {detail::caller_define_value(p.kernel_defines, "BHCL_GRID_ROWCAP", f.row_cap),
          detail::caller_define_value(p.kernel_defines, "BHCL_GRID_FINE_RINGS", BHCL_GRID_FINE_RINGS),
          detail::caller_define_value(p.kernel_defines, "BHCL_GRID_WALKCAP", f.walk_cap)};
}

void GridIndex::add_grid_args(detail::KernelArgs& args) const {
  const bhcl_grid_geom& g = s_->grid->geom;
  args.add(g_starts_).add(g_x_).add(g_y_).add(g_z_).add(g_ids_).add(g_occ_)
      .add(cl_float4{{g.ox, g.oy, g.oz, g.h}})
      .add(cl_float4{{g.inv_h, g.margin, 0.0f, 0.0f}})
      .add(cl_uint4{{g.nx, g.ny, g.nz, g.sparse}})
      .add(cl_float4{{s_->grid->dbox.lx, s_->grid->dbox.ly, s_->grid->dbox.lz, 0.0f}})
      .add(cl_float4{{s_->grid->dbox.hx, s_->grid->dbox.hy, s_->grid->dbox.hz, 0.0f}});
}

void GridIndex::reference_scaled(const float* queries, std::size_t n, const SearchParams& params, KnnResult& out,
                                 std::vector<std::int32_t>* examined, unsigned threads) const {
  blockhash::reference_query_grid(*s_->grid, queries, n, params.k, detail::squared_radius(params.max_radius),
                                  blockhash::grid_budget(budget(params), s_->grid->n_points, info_.holes),
                                  traversal_for(params), out, examined, threads);
}

}  // namespace bhcl
