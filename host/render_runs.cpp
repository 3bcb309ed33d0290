// The runs of `bhcl render` (render_runs.hpp).
#include "render_runs.hpp"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <sstream>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/numbers.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "commands.hpp"
#include "compare.hpp"
#include "density.hpp"
#include "embree_scene.hpp"
#include "exr_io.hpp"
#include "final_gather.hpp"
#include "photon_trace.hpp"
#include "png_io.hpp"
#include "progress.hpp"

namespace bhcl::cli::render_cmd {

double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

std::vector<float> parse_list(const std::string& s) {
  std::vector<float> v;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    double a = 0;  // locale-free (numbers.hpp)
    if (bhcl::detail::parse_double(item, a) != bhcl::detail::NumberParse::Ok || !(a > 0) || !(a < 0x1.ffffffp+127)) {
      throw UsageError("--compare-A expects positive numbers separated by commas, got '" + s + "'");
    }
    v.push_back(static_cast<float>(a));
  }
  if (v.empty()) throw UsageError("--compare-A is empty");
  return v;
}


std::string format_g(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%g", v);
  return b;
}

// "kth-cone": the estimator in file names.
std::string estimator_tag(const DensityEstimator& e) {
  return std::string(radius_estimator_name(e.radius)) + "-" + density_filter_name(e.filter);
}

// --estimator and --filter: one each, or (with --compare) comma lists whose every pair is shaded.
std::vector<DensityEstimator> parse_estimators(const Args& args, bool lists) {
  auto split = [&](const std::string& opt, const std::string& dflt) {
    std::vector<std::string> v;
    std::stringstream ss(args.str(opt, dflt));
    std::string item;
    while (std::getline(ss, item, ',')) v.push_back(item);
    if (v.empty()) throw UsageError("--" + opt + " is empty");
    if (v.size() > 1 && !lists) throw UsageError("--" + opt + " takes a list only with --compare");
    return v;
  };
  std::vector<DensityEstimator> out;
  for (const std::string& r : split("estimator", "kth"))
    for (const std::string& f : split("filter", "cone")) {
      DensityEstimator e;
      if (!parse_radius_estimator(r, e.radius))
        throw UsageError("--estimator: unknown radius estimator '" + r + "' (kth, mean, var)");
      if (!parse_density_filter(f, e.filter))
        throw UsageError("--filter: unknown filter '" + f + "' (box, cone, epanechnikov)");
      for (const auto& o : out)
        if (o == e) throw UsageError("--estimator/--filter: " + estimator_name(e) + " is listed twice");
      out.push_back(e);
    }
  return out;
}

// Builds the index of `method` on the (shared) photon maps and compiles its kernels, so that the
// query time excludes first-launch compiles.
RenderRun start_run(const std::string& label, const std::string& method, float A, PhotonMaps& maps,
                    const std::shared_ptr<Runtime>& rt, const MethodOptions& mopt, RenderOptions ropt) {
  RenderRun run;
  run.label = label;
  run.method = method;
  run.A = A;
  ropt.search.A = A;
  const auto t0 = Clock::now();
  // The paper presets size B for the A and k asked (the talk's rule), per map: one build per A.
  SearchParams cp = ropt.search;
  cp.k = ropt.caustic_k > 0 ? ropt.caustic_k : ropt.search.k;
  const bool bh = method == "blockhash";
  const MethodOptions gopt = bh ? paper_options_for_search(mopt, ropt.search) : mopt;
  maps.global->build_index(method, rt, gopt);
  if (maps.caustic) maps.caustic->build_index(method, rt, bh ? paper_options_for_search(mopt, cp) : mopt);
  run.build_s = maps.global->build_seconds() + (maps.caustic ? maps.caustic->build_seconds() : 0.0);
  if (maps.global->index()) {
    run.warm_s += maps.global->index()->warm_up(ropt.search);
    run.build = build_json(*maps.global->index(), gopt);
    run.search = search_json(*maps.global->index(), ropt.search);
  }
  if (maps.caustic && maps.caustic->index()) {
    run.warm_s += maps.caustic->index()->warm_up(cp);
  }
  run.total_s = since(t0);
  return run;
}

// Shades a traced frame with the maps' current indices (start_run), once per estimator.
void shade_run(RenderRun& run, const TracedFrame& frame, const std::vector<DensityEstimator>& ests,
               const PhotonMaps& maps, const EmbreeScene& es, const LightSampler& lights, RenderOptions ropt,
               bool quiet) {
  ropt.search.A = run.A;
  const auto t0 = Clock::now();
  FinalGatherRenderer renderer(es, lights, *maps.global, maps.caustic.get(), ropt);
  Progress bar("shade " + run.label, !quiet);
  run.images = renderer.shade(frame, ests, run.stats, &bar);
  bar.finish();
  run.total_s += since(t0);
}

// Traces and shades pass by pass (one pass in memory): the plain render.
RenderRun render_with(const std::string& label, const std::string& method, float A, PhotonMaps& maps,
                      const std::shared_ptr<Runtime>& rt, const MethodOptions& mopt,
                      const EmbreeScene& es, const LightSampler& lights, RenderOptions ropt,
                      bool quiet) {
  RenderRun run = start_run(label, method, A, maps, rt, mopt, ropt);
  ropt.search.A = A;
  const auto t0 = Clock::now();
  FinalGatherRenderer renderer(es, lights, *maps.global, maps.caustic.get(), ropt);
  Progress bar("render " + label, !quiet);
  run.images.push_back(renderer.render(run.stats, &bar));
  bar.finish();
  run.total_s += since(t0);
  return run;
}

// The ray counts of a frame traced once, for the skip report of every run that shaded it.
void add_trace_counts(RenderStats& s, const RenderStats& t) {
  s.camera_rays += t.camera_rays;
  s.visible_points += t.visible_points;
  s.shadow_rays += t.shadow_rays;
  s.gather_rays += t.gather_rays;
  s.gather_escaped += t.gather_escaped;
  s.gather_no_query += t.gather_no_query;
  s.passes = t.passes;
}


// What the render did not do, because the scene did not need it (item by item).
void print_skipped(const RenderRun& r, const PhotonMaps& maps) {
  const RenderStats& s = r.stats;
  const std::size_t samples = s.camera_rays;
  std::fprintf(stderr,
               "bhcl render: skipped [%s]: %zu of %zu camera samples saw no diffuse surface (the light, or "
               "nothing: no gather); %zu of %zu gather rays escaped and %zu ended on an emitter or a black "
               "surface (no query); caustic lookups: %s\n",
               r.label.c_str(), samples > s.visible_points ? samples - s.visible_points : 0, samples,
               s.gather_escaped, s.gather_rays, s.gather_no_query,
               maps.caustic ? "made" : "none (no specular surface, or no caustic photon stored)");
}

void print_split(const char* title, const RenderRun& r, double photon_s) {
  const RenderStats& s = r.stats;
  std::fprintf(stderr,
               "%s [%s]: photons %.2f s | index build %.2f s (+ kernel compile %.2f s) | camera+shadow+gather rays %.2f s | "
               "gather queries %.2f s (kernel %.2f s, %zu queries in %zu calls, %.0f q/s, %.1f result bytes a query back) | "
               "shading %.2f s\n",
               title, r.label.c_str(), photon_s, r.build_s, r.warm_s + s.compile_s, s.trace_s, s.query_s,
               s.query_kernel_s, s.queries + s.caustic_queries, s.index_calls,
               s.query_s > 0 ? (s.queries + s.caustic_queries) / s.query_s : 0.0,
               s.queries + s.caustic_queries ? double(s.result_bytes) / double(s.queries + s.caustic_queries) : 0.0,
               s.shade_s);
}

Json run_json(const RenderRun& r, const ImageDiff* d) {
  Json j;
  j["label"] = r.label;
  j["method"] = r.method;
  j["A"] = r.A;
  if (!r.build.is_null()) j["build"] = r.build;
  if (!r.search.is_null()) j["search"] = r.search;
  j["index_build_s"] = r.build_s;
  j["kernel_compile_s"] = r.warm_s + r.stats.compile_s;
  j["trace_s"] = r.stats.trace_s;
  j["query_s"] = r.stats.query_s;
  j["query_kernel_s"] = r.stats.query_kernel_s;
  j["shade_s"] = r.stats.shade_s;
  j["render_s"] = r.total_s;
  j["queries"] = r.stats.queries;
  j["caustic_queries"] = r.stats.caustic_queries;
  j["index_calls"] = r.stats.index_calls;
  j["result_bytes"] = r.stats.result_bytes;
  j["fused_estimate"] = r.stats.result_bytes > 0 && r.stats.result_bytes == 16 * (r.stats.queries + r.stats.caustic_queries);
  if (d) {
    j["rmse"] = d->rmse;
    j["relative_rmse"] = d->relative_rmse;
    j["mean_rel_error"] = d->mean_rel_error;
    j["max_abs_error"] = d->max_abs;
  }
  return j;
}

Image read_reference(const Args& args, const RenderOptions& ropt) {
  Image reference;
  if (args.has("reference")) {
    reference = read_exr(args.str("reference"));
    if (reference.width != ropt.width || reference.height != ropt.height)
      throw UsageError("--reference " + args.str("reference") + " is " + std::to_string(reference.width) + "x" +
                       std::to_string(reference.height) + ", the render " + std::to_string(ropt.width) + "x" +
                       std::to_string(ropt.height));
  }
  return reference;
}

// The scene and render settings every stats file of `bhcl render` carries.
Json render_header(const Runtime& rt, const Args& args, const std::string& scene, const RenderOptions& ropt,
                   const PhotonMaps& maps, std::size_t photons_requested) {
  Json j = stats_header("render", rt);
  add_image_fields(j, args, scene, ropt.width, ropt.height, ropt.spp);
  j["gather"] = ropt.gather;
  j["shadow_rays"] = ropt.shadow_rays;
  j["k"] = ropt.search.k;
  j["estimator"] = estimator_name(ropt.estimator);
  j["boundary"] = ropt.boundary_correction ? "surface" : "none";
  j["caustic_k"] = ropt.caustic_k;
  j["caustic_radius"] = ropt.caustic_radius;
  j["batch"] = ropt.batch_queries;
  j["seed"] = ropt.seed;
  const long long photon_seed = args.integer("photon-seed", -1);
  j["photon_seed"] = photon_seed >= 0 ? photon_seed : static_cast<long long>(ropt.seed);
  j["threads"] = ropt.threads;
  j["photons_requested"] = photons_requested;
  j["photons"] = maps.global->size();
  j["photons_emitted"] = maps.trace.emitted;
  j["caustic_photons"] = maps.caustic ? maps.caustic->size() : std::size_t(0);
  return j;
}

}  // namespace bhcl::cli::render_cmd
