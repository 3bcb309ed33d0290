// BlockHashIndex's search side: the parameter checks and the tuned A, the kernels' options and
// arguments, the kNN and radius dispatch, and the host reference of the same query.
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <sstream>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "core/kernel_defines.hpp"
#include "blockhash_cl/kernel_forms.hpp"

namespace bhcl {
bool BlockHashIndex::table_probes(int neighbour_probes) const {
  return neighbour_probes < 0 ? info_.neighbour_probes : neighbour_probes == 1;
}

void BlockHashIndex::add_layout_args(detail::KernelArgs& args, int neighbour_probes) const {
  args.add(blocks_).add(boxes_).add(thresholds_).add(cl_uint(info_.P)).add(keys_);
  args.add(table_starts_).add(buckets_).add(refs_).add(cl_uint(table_probes(neighbour_probes) ? 1 : 0));
}

std::uint32_t BlockHashIndex::budget(const SearchParams& p) {
  double b = std::ceil(double(p.A) * double(p.k));
  return static_cast<std::uint32_t>(std::min(b, 4294967295.0));
}

void BlockHashIndex::check_params(const SearchParams& p) const {
  Index::check_params(p);
  if (info_.grid) {
    // The rings reach every cell within the bound: the probes are an option of the L tables,
    // refused here rather than accepted and ignored.
    if (p.neighbour_probes != -1)
      throw Error("blockhash: neighbour_probes (probes) is an option of the L tables (grid = 0, preset paper); "
                  "the grid's rings reach every cell within the bound: leave it -1, got " +
                  std::to_string(p.neighbour_probes));
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

std::optional<BlockHashIndex::RecallTuning> BlockHashIndex::recall_tuning(const SearchParams& p) const {
  if (!(p.recall_target > 0)) return std::nullopt;
  if (info_.grid && p.recall_target >= 1) {  // the grid's exact mode: nothing to tune
    RecallTuning exact;
    exact.A = INFINITY;
    exact.recall = 1;
    exact.reached = true;
    return exact;
  }
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
  if (p.recall_target > 0) return recall_tuning(p)->A;  // the grid at a target of 1: its exact mode
  if (p.A == 0) return info_.grid ? INFINITY : 8.0f;  // the index's default (SearchParams::A)
  return p.A;
}

detail::DefineValues BlockHashIndex::kernel_options(int kmax) const {
  if (info_.grid) {
    // The device's row of the forms table (core/kernel_forms.cpp); the scalar list past 64 entries.
    const detail::GridKernelForm& f = detail::grid_kernel_form(runtime().info());
    detail::DefineValues v = {{"BHCL_KMAX", kmax},
                              {"BHCL_GRID_VTOPK", f.vtopk && kmax <= 64 ? 1 : 0},
                              {"BHCL_GRID_PREFETCH", f.prefetch},
                              {"BHCL_GRID_ROWCAP", f.row_cap},
                              {"BHCL_GRID_WALKCAP", f.walk_cap}};
    if (f.fill_sort >= 0) v.push_back({"BHCL_GRID_FILLSORT", f.fill_sort});
    if (f.prefetch_lines >= 0) v.push_back({"BHCL_GRID_PREFETCH_LINES", f.prefetch_lines});
    return v;
  }
  const long long cap = blockhash::scan_cap(kmax, info_.X);
  // Only the defines the variant uses, so that indexes differing elsewhere share a program.
  return {{"BHCL_KMAX", kmax},
          {"BHCL_BH_L", info_.L},
          {"BHCL_BH_DIRECT", info_.direct_addressing ? 1 : 0},
          {"BHCL_BH_BOXSKIP", info_.box_skip && !info_.box_order ? 1 : 0},
          {"BHCL_BH_BOXORDER", info_.box_order ? 1 : 0},
          {info_.box_order ? "BHCL_BH_MAXKEEP" : "BHCL_BH_SCANCAP", cap}};
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
    const std::string file = std::string(gname) + ".cl";
    cl::Kernel kernel =
        runtime().kernel(file, gname, detail::kernel_build_options(file, kernel_options(kmax), params.kernel_defines));
    detail::KernelArgs args(kernel, gname);
    add_grid_args(args);
    args.add_queries(queries, first, count, params)
        .add(cl_uint(blockhash::grid_budget(budget(params), s_->grid->n_points, info_.holes)))
        .add_results(out)
        .add(examined ? *examined : dummy_)
        .add(cl_uint(examined ? 1 : 0));
    return detail::launch_1d(queue, kernel, count, local_size, wait, gname);
  }
  const char* name = "blockhash_knn";
  const std::string file = std::string(name) + ".cl";
  cl::Kernel kernel =
      runtime().kernel(file, name, detail::kernel_build_options(file, kernel_options(kmax), params.kernel_defines));
  detail::KernelArgs args(kernel, name);
  add_layout_args(args, params.neighbour_probes);
  args.add(block_keys_)
      .add(cl_uint(s_->blocks.size()))
      .add(cl_float4{{s_->q_origin[0], s_->q_origin[1], s_->q_origin[2], s_->q_scale}})
      .add(cl_uint(s_->q_bits))
      .add(cl_uint(blockhash::seed_side(info_.hilbert_seed, params.k, info_.X)));
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
    const std::string file = std::string(gname) + ".cl";
    cl::Kernel kernel = runtime().kernel(file, gname, detail::kernel_build_options(file, {}, params.kernel_defines));
    detail::KernelArgs args(kernel, gname);
    add_grid_args(args);
    args.add(cl_uint(params.budget)).add_radius(queries, first, count, r2, pass, out, params.count_examined);
    return detail::launch_1d(queue, kernel, count, local_size, wait, gname);
  }
  const char* name = "blockhash_radius";
  const detail::DefineValues values = {
      {"BHCL_BH_L", info_.L},
      {"BHCL_BH_DIRECT", info_.direct_addressing ? 1 : 0},
      {"BHCL_BH_SCANCAP", static_cast<long long>(blockhash::scan_cap(kMaxK, info_.X))}};
  const std::string file = std::string(name) + ".cl";
  cl::Kernel kernel = runtime().kernel(file, name, detail::kernel_build_options(file, values, params.kernel_defines));
  detail::KernelArgs args(kernel, name);
  add_layout_args(args, params.neighbour_probes);
  args.add(cl_uint(params.budget)).add_radius(queries, first, count, r2, pass, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, name);
}

blockhash::GridTraversal BlockHashIndex::traversal_for(const SearchParams& p) const {
  const detail::GridKernelForm& f = detail::grid_kernel_form(runtime().info());
  return {detail::caller_define_value(p.kernel_defines, "BHCL_GRID_ROWCAP", f.row_cap),
          detail::caller_define_value(p.kernel_defines, "BHCL_GRID_FINE_RINGS", BHCL_GRID_FINE_RINGS),
          detail::caller_define_value(p.kernel_defines, "BHCL_GRID_WALKCAP", f.walk_cap)};
}

void BlockHashIndex::add_grid_args(detail::KernelArgs& args) const {
  const bhcl_grid_geom& g = s_->grid->geom;
  args.add(g_starts_).add(g_x_).add(g_y_).add(g_z_).add(g_ids_).add(g_occ_)
      .add(cl_float4{{g.ox, g.oy, g.oz, g.h}})
      .add(cl_float4{{g.inv_h, g.margin, 0.0f, 0.0f}})
      .add(cl_uint4{{g.nx, g.ny, g.nz, g.sparse}})
      .add(cl_float4{{s_->grid->dbox.lx, s_->grid->dbox.ly, s_->grid->dbox.lz, 0.0f}})
      .add(cl_float4{{s_->grid->dbox.hx, s_->grid->dbox.hy, s_->grid->dbox.hz, 0.0f}});
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
                                    blockhash::grid_budget(budget(params), s_->grid->n_points, info_.holes),
                                    traversal_for(params), out, examined, threads);
  } else {
    blockhash::reference_query(*s_, queries, n, params, table_probes(params.neighbour_probes), out, examined,
                               threads);
  }
  distances_to_caller(out.dist2.data(), out.dist2.size());
  return out;
}

}  // namespace bhcl
