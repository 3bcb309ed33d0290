// bhcl render: the photon-mapping renderer end to end. Embree traces photons and rays; the
// final-gather hit points of each pass are answered by one batched kNN call of the chosen
// method; the image is written as half-float OpenEXR with a tone-mapped PNG preview.
// --compare renders the same photon map with an exact method and with block hashing at several
// A, and writes the images side by side with false-colour differences and error figures.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <sstream>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
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

namespace bhcl::cli {
namespace {

using namespace bhcl::render;
using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

std::vector<float> parse_list(const std::string& s) {
  std::vector<float> v;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    try {
      std::size_t p = 0;
      float a = std::stof(item, &p);
      if (p != item.size() || !(a > 0)) throw 0;
      v.push_back(a);
    } catch (...) {
      throw UsageError("--compare-A expects positive numbers separated by commas, got '" + s + "'");
    }
  }
  if (v.empty()) throw UsageError("--compare-A is empty");
  return v;
}

bool has_method(const std::string& m) {
  for (const auto& n : method_names())
    if (n == m) return true;
  return false;
}

struct RenderRun {
  std::string label, method;
  float A = 0;
  std::vector<Image> images;  // one per density estimator
  RenderStats stats;
  double build_s = 0, warm_s = 0, total_s = 0;
  Json build, search;  // the parameters the global map's index used, for the stats
};

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
  maps.global->build_index(method, rt, mopt);
  if (maps.caustic) maps.caustic->build_index(method, rt, mopt);
  run.build_s = maps.global->build_seconds() + (maps.caustic ? maps.caustic->build_seconds() : 0.0);
  if (maps.global->index()) {
    run.warm_s += maps.global->index()->warm_up(ropt.search);
    run.build = build_json(*maps.global->index(), mopt);
    run.search = search_json(*maps.global->index(), ropt.search);
  }
  if (maps.caustic && maps.caustic->index()) {
    SearchParams cp = ropt.search;
    cp.k = ropt.caustic_k > 0 ? ropt.caustic_k : ropt.search.k;
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
               "gather queries %.2f s (kernel %.2f s, %zu queries in %zu calls, %.0f q/s) | shading %.2f s\n",
               title, r.label.c_str(), photon_s, r.build_s, r.warm_s + s.compile_s, s.trace_s, s.query_s,
               s.query_kernel_s, s.queries + s.caustic_queries, s.index_calls,
               s.query_s > 0 ? (s.queries + s.caustic_queries) / s.query_s : 0.0, s.shade_s);
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
  if (d) {
    j["rmse"] = d->rmse;
    j["relative_rmse"] = d->relative_rmse;
    j["mean_rel_error"] = d->mean_rel_error;
    j["max_abs_error"] = d->max_abs;
  }
  return j;
}

// The scene and render settings every stats file of `bhcl render` carries.
Json render_header(const Runtime& rt, const Args& args, const std::string& scene, const RenderOptions& ropt,
                   const PhotonMaps& maps, std::size_t photons_requested) {
  Json j = stats_header("render", rt);
  j["scene"] = scene;
  j["scene_arg"] = args.str("scene", "cornell");
  j["width"] = ropt.width;
  j["height"] = ropt.height;
  j["spp"] = ropt.spp;
  j["gather"] = ropt.gather;
  j["shadow_rays"] = ropt.shadow_rays;
  j["k"] = ropt.search.k;
  j["estimator"] = estimator_name(ropt.estimator);
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

void declare_render(Args& a) {
  a.add_required("out", "the image (half-float OpenEXR); a PNG preview goes beside it", "IMAGE.exr");
  a.add_text("scene", "cornell, a scene name from the scenes folder, or an OBJ file", "cornell", "SCENE");
  a.add_text("method", "the kNN method of the final gather", has_method("kdtree") ? "kdtree" : "bruteforce",
             "NAME");
  a.add_integer("photons", "photons emitted", 1, Args::kNoLimit, "200000");
  a.add_integer("gather", "final-gather rays per pixel sample", 0, 4096, "32");
  a.add_integer("spp", "samples per pixel", 1, 4096, "1");
  a.add_text("size", "image size WxH", "512x512", "WxH");
  a.add_text("png", "the tone-mapped PNG preview", "OUT with .png", "FILE");
  a.add_text("stats", "write timings and parameters here as JSON", "", "FILE");
  declare_device_option(a);
  a.add_integer("shadow-rays", "shadow rays per shading point", 1, 4096, "4");
  a.add_integer("caustic-k", "photons per caustic estimate (0: --k)", 0, kMaxK, "0");
  a.add_number("caustic-radius", "caustic gather radius (0: automatic)", "0");
  a.add_integer("batch", "gather queries per kNN call", 1, Args::kNoLimit, "262144");
  a.add_number("exposure", "tone-mapping exposure (0: automatic)", "0");
  a.add_integer("photon-seed", "seed of the photons (-1: --seed); --seed then seeds the camera, shadow and gather rays",
                -1, Args::kNoLimit, "-1");
  a.add_text("estimator", "photon density: the disc's radius from the k-th distance (kth), the mean distance "
                          "(mean) or the variance of the distances (var); with --compare a comma list",
             "kth", "NAME");
  a.add_text("filter", "photon weights in the disc: box, cone or epanechnikov; with --compare a comma list", "cone",
             "NAME");
  a.add_flag("quiet", "no progress bars");
  a.group("Comparison");
  a.add_flag("compare", "render with an exact method and with block hashing at several A, side by side");
  a.add_text("exact", "--compare: the exact method", has_method("kdtree") ? "kdtree" : "bruteforce", "NAME");
  a.add_text("approx", "--compare: the approximate method", "blockhash", "NAME");
  a.add_text("compare-A", "--compare: the values of A, comma separated", "4,8,16", "LIST");
  a.add_number("diff-scale", "--compare: relative error shown as full scale in the difference images", "0.1");
  a.add_flag("noise-floor", "--compare: also render the exact method with another photon seed and with another "
                            "render seed, and print their differences (the render's own Monte Carlo noise)");
  a.add_text("reference", "--compare: an independent render of the same scene and camera (EXR, e.g. bhcl "
                          "pathtrace): each estimator's exact render is compared with it", "", "IMAGE.exr");
  a.add_integer("reference-block", "--compare: block size (pixels) of the block-averaged error against --reference",
                1, 4096, "8");
  declare_index_options(a, 50, true);
}

int run_render(const Args& args) {
  {
    const bool cmp = args.flag("compare");
    for (const char* o : {"exact", "approx", "compare-A", "diff-scale", "noise-floor", "reference", "reference-block"})
      if (!cmp && args.has(o)) throw UsageError("--" + std::string(o) + " applies only with --compare");
    if (cmp && args.has("method")) throw UsageError("--method does not apply with --compare (see --exact, --approx)");
    const std::string dflt = has_method("kdtree") ? "kdtree" : "bruteforce";
    // --threads and --seed also drive Embree and the photon tracer.
    if (cmp)
      check_method_options(args, {args.str("exact", dflt), args.str("approx", "blockhash")}, {"threads", "seed"});
    else
      check_method_options(args, {args.str("method", dflt)}, {"threads", "seed"});
  }
  const auto t_start = Clock::now();
  const bool quiet = args.flag("quiet");
  const bool compare = args.flag("compare");
  const std::string out = args.str("out");
  const std::string base = strip_extension(out);

  RenderOptions ropt;
  parse_image_size(args.str("size", "512x512"), ropt.width, ropt.height);
  ropt.search = search_params(args, 50);
  ropt.spp = static_cast<int>(args.integer("spp", 1));
  ropt.gather = static_cast<int>(args.integer("gather", 32));
  ropt.shadow_rays = static_cast<int>(args.integer("shadow-rays", 4));
  ropt.caustic_k = static_cast<int>(args.integer("caustic-k", 0));
  ropt.caustic_radius = static_cast<float>(args.number("caustic-radius", 0));
  // The integer options above are range-checked as declared (declare_render).
  long long batch = args.integer("batch", 262144);
  if (!(ropt.caustic_radius >= 0)) throw UsageError("--caustic-radius must be >= 0");
  ropt.batch_queries = static_cast<std::size_t>(batch);
  const std::vector<DensityEstimator> ests = parse_estimators(args, compare);
  ropt.estimator = ests[0];
  MethodOptions mopt = method_options(args);
  {
    // Before any work: no output may overwrite the scene, a saved index or another output (the
    // PNG preview lands beside --out unless --png names it).
    std::vector<FileArg> outputs = {{"--out", out},
                                    {args.has("png") ? "--png" : "the PNG beside --out", args.str("png", base + ".png")},
                                    {"--stats", args.str("stats", "")},
                                    {"--save-index", mopt.save_index()}};
    if (compare) outputs.push_back({"the comparison sheet beside --out", base + "_compare.png"});
    check_distinct_files({{"--scene", args.str("scene", "")},
                          {"--load-index", mopt.load_index()},
                          {"--reference", args.str("reference", "")}},
                         outputs);
  }
  ropt.seed = static_cast<std::uint64_t>(mopt.integer("seed", 1));
  ropt.threads = static_cast<int>(mopt.integer("threads", 0));
  long long photons = args.integer("photons", 200000);
  const double exposure_opt = args.number("exposure", 0.0);
  if (exposure_opt < 0 || !std::isfinite(exposure_opt)) throw UsageError("--exposure must be >= 0 (0: automatic)");

  // The scene, in Embree.
  Scene scene = load_scene(args.str("scene", "cornell"));
  EmbreeScene es(scene, ropt.threads);
  LightSampler lights(scene);
  Vec3 P = lights.total_power();
  std::fprintf(stderr,
               "bhcl render: scene '%s': %zu triangles, %zu emitter triangles, emitted power (%.4g, %.4g, %.4g) "
               "[radiance x mm^2], %dx%d, %d spp, %d gather rays, k=%d\n",
               scene.name.c_str(), scene.triangles.size(), lights.count(), P.x, P.y, P.z, ropt.width,
               ropt.height, ropt.spp, ropt.gather, ropt.search.k);

  // Photons.
  PhotonTraceOptions popt;
  popt.photons = static_cast<std::size_t>(photons);
  const long long photon_seed = args.integer("photon-seed", -1);
  popt.seed = photon_seed >= 0 ? static_cast<std::uint64_t>(photon_seed) : ropt.seed;
  popt.threads = ropt.threads;
  PhotonMaps maps;
  {
    Progress bar("photons", !quiet);
    maps = build_photon_maps(es, lights, popt, [&](double f) { bar.update(f); });
  }
  const double photon_s = maps.trace.seconds;
  Vec3 sp = maps.trace.stored_power;
  std::fprintf(stderr,
               "bhcl render: %zu photons emitted, %zu stored in the global map (24-byte records, %.1f MiB) in %.2f s; "
               "stored power (%.4g, %.4g, %.4g)\n",
               maps.trace.emitted, maps.global->size(), maps.global->size() * sizeof(PhotonRecord) / 1048576.0,
               photon_s, sp.x, sp.y, sp.z);
  if (maps.caustic)
    std::fprintf(stderr, "bhcl render: caustic map: %zu photons (paths light -> specular+ -> diffuse)\n",
                 maps.caustic->size());
  else
    std::fprintf(stderr, "bhcl render: no specular surfaces in scene '%s': no caustic map built\n",
                 scene.name.c_str());

  auto rt = std::make_shared<Runtime>(args.str("device", ""));
  const std::string device = rt->info().summary();

  if (!compare) {
    const std::string method = args.str("method", has_method("kdtree") ? "kdtree" : "bruteforce");
    RenderRun r = render_with(method, method, ropt.search.A, maps, rt, mopt, es, lights, ropt, quiet);
    write_exr(out, r.images[0]);
    const float exposure = exposure_opt > 0 ? static_cast<float>(exposure_opt) : auto_exposure(r.images[0]);
    const std::string png = args.str("png", base + ".png");
    write_png(png, tonemap(r.images[0], exposure));
    const double total = since(t_start);
    print_split("bhcl render: time split", r, photon_s);
    print_skipped(r, maps);
    std::fprintf(stderr, "bhcl render: wrote %s and %s (exposure %.4g); total %.2f s on %s\n", out.c_str(),
                 png.c_str(), exposure, total, device.c_str());
    if (args.has("stats")) {
      Json j = render_header(*rt, args, scene.name, ropt, maps, popt.photons);
      j.update(run_json(r, nullptr));  // method, A, build, search, the time split, query counts
      j["exposure"] = exposure;
      j["gather_rays"] = r.stats.gather_rays;
      j["gather_escaped"] = r.stats.gather_escaped;
      j["gather_no_query"] = r.stats.gather_no_query;
      j["camera_samples"] = r.stats.camera_rays;
      j["caustic_map"] = maps.caustic != nullptr;
      j["visible_points"] = r.stats.visible_points;
      j["photon_s"] = photon_s;
      j["total_s"] = total;
      write_json(args.str("stats"), j);
    }
    return 0;
  }

  // --compare: the same photon map and the same rays, traced once, shaded by each method, A and
  // estimator.
  const std::string exact = args.str("exact", has_method("kdtree") ? "kdtree" : "bruteforce");
  const std::string approx = args.str("approx", "blockhash");
  const std::vector<float> As = parse_list(args.str("compare-A", "4,8,16"));
  const std::size_t E = ests.size();
  const float max_rel = static_cast<float>(args.number("diff-scale", 0.1));
  if (!(max_rel > 0)) throw UsageError("--diff-scale must be > 0");
  std::vector<RenderRun> runs;
  runs.push_back(start_run(exact, exact, ropt.search.A, maps, rt, mopt, ropt));
  RenderStats trace_stats;
  TracedFrame frame;
  {
    FinalGatherRenderer tracer(es, lights, *maps.global, maps.caustic.get(), ropt);
    Progress bar("trace rays", !quiet);
    frame = tracer.trace(trace_stats, &bar);
    bar.finish();
  }
  std::fprintf(stderr,
               "bhcl render --compare: camera, shadow and gather rays traced once in %.2f s (%zu gather queries "
               "kept, %.1f MiB), shaded by every run\n",
               trace_stats.trace_s, trace_stats.gather_rays - trace_stats.gather_escaped - trace_stats.gather_no_query,
               frame.bytes() / 1048576.0);
  const std::size_t frame_bytes = frame.bytes();
  shade_run(runs.back(), frame, ests, maps, es, lights, ropt, quiet);
  for (float A : As) {
    char label[64];
    std::snprintf(label, sizeof label, "%s A=%g", approx.c_str(), A);
    runs.push_back(start_run(label, approx, A, maps, rt, mopt, ropt));
    shade_run(runs.back(), frame, ests, maps, es, lights, ropt, quiet);
    // A larger A examines more candidates; once the images are bit-identical to the previous A's,
    // the neighbour lists that matter have stopped changing and larger A would only cost time.
    if (runs.size() > 2) {
      bool same = true;
      for (std::size_t e = 0; e < E; ++e) same = same && runs.back().images[e].rgb == runs[runs.size() - 2].images[e].rgb;
      if (same) {
        std::fprintf(stderr, "bhcl render --compare: %s gives an image bit-identical to %s: larger A skipped\n",
                     runs.back().label.c_str(), runs[runs.size() - 2].label.c_str());
        break;
      }
    }
  }
  for (RenderRun& r : runs) add_trace_counts(r.stats, trace_stats);
  runs[0].stats.trace_s = trace_stats.trace_s;
  // The noise floor: the exact render's own Monte Carlo error, as the difference between two
  // exact renders that differ only in the photon seed (a new photon map, the same rays) or only
  // in the render seed (new camera, shadow and gather rays). Block hashing's error matters only
  // against these.
  std::vector<std::vector<std::pair<std::string, ImageDiff>>> noise(E);  // per estimator
  std::vector<Image> photon_seed_images, render_seed_images;
  if (args.flag("noise-floor")) {
    PhotonTraceOptions popt2 = popt;
    popt2.seed = popt.seed + 1000003;
    PhotonMaps maps2 = build_photon_maps(es, lights, popt2);
    RenderRun p2 = start_run(exact + " photon seed+", exact, ropt.search.A, maps2, rt, mopt, ropt);
    shade_run(p2, frame, ests, maps2, es, lights, ropt, quiet);
    frame = TracedFrame{};  // its memory: the render-seed run traces its own
    RenderOptions ropt2 = ropt;
    ropt2.seed = ropt.seed + 1000003;
    RenderRun r2 = start_run(exact + " render seed+", exact, ropt.search.A, maps, rt, mopt, ropt2);
    {
      FinalGatherRenderer renderer(es, lights, *maps.global, maps.caustic.get(), ropt2);
      RenderStats ts;
      Progress bar("render " + r2.label, !quiet);
      TracedFrame f2 = renderer.trace(ts, &bar);
      r2.images = renderer.shade(f2, ests, r2.stats, nullptr);
      bar.finish();
    }
    for (std::size_t e = 0; e < E; ++e) {
      noise[e].emplace_back("exact, photon seed " + std::to_string(popt2.seed), image_diff(p2.images[e], runs[0].images[e]));
      noise[e].emplace_back("exact, render seed " + std::to_string(ropt2.seed), image_diff(r2.images[e], runs[0].images[e]));
    }
    photon_seed_images = std::move(p2.images);
    render_seed_images = std::move(r2.images);
  }
  frame = TracedFrame{};

  // The independent reference, when given: each estimator's exact render against it, per pixel
  // and on blocks of pixels (which average away most of the render's per-pixel noise and keep
  // the estimator's bias: blur at corners and edges, darkening near walls).
  Image reference;
  const int block = static_cast<int>(args.integer("reference-block", 8));
  if (args.has("reference")) {
    reference = read_exr(args.str("reference"));
    if (reference.width != ropt.width || reference.height != ropt.height)
      throw UsageError("--reference " + args.str("reference") + " is " + std::to_string(reference.width) + "x" +
                       std::to_string(reference.height) + ", the render " + std::to_string(ropt.width) + "x" +
                       std::to_string(ropt.height));
  }

  const float exposure = exposure_opt > 0 ? static_cast<float>(exposure_opt) : auto_exposure(runs[0].images[0]);
  TextPainter text(std::clamp(ropt.width / 22, 9, 16));
  if (!text.ok()) std::fprintf(stderr, "bhcl render: the comparison sheet is unlabelled: %s\n", text.why().c_str());
  // diffs[e][i]: run i against the exact run, both with estimator e.
  std::vector<std::vector<ImageDiff>> diffs(E);
  std::vector<float> auto_rels(E);
  std::vector<std::string> sheets(E);
  for (std::size_t e = 0; e < E; ++e) {
    const Image& ref = runs[0].images[e];
    // With several estimators every output name carries the estimator ("_kth-cone").
    const std::string etag = E == 1 ? "" : "_" + estimator_tag(ests[e]);
    std::vector<Panel> top, fixed_row, auto_row;
    std::vector<const Image*> approx_images;
    for (std::size_t i = 1; i < runs.size(); ++i) approx_images.push_back(&runs[i].images[e]);
    // The automatic scale: the 99th percentile of every approximate image's per-pixel error, so
    // that errors far below the fixed scale still show (0 when all are exact: then the fixed one).
    float auto_rel = relative_error_percentile(approx_images, ref, 0.99f);
    const bool auto_ok = auto_rel > 0;
    if (!auto_ok) auto_rel = max_rel;
    auto_rels[e] = auto_rel;
    char buf[128];
    for (std::size_t i = 0; i < runs.size(); ++i) {
      const Image& img = runs[i].images[e];
      const std::string tag = i == 0 ? "exact" : "A" + format_g(runs[i].A);
      // --out is the first estimator's exact render.
      const std::string exr = i == 0 ? (e == 0 ? out : base + etag + ".exr") : base + etag + "_" + tag + ".exr";
      write_exr(exr, img);
      Rgb8 tm = tonemap(img, exposure);
      write_png(strip_extension(exr) + ".png", tm);
      diffs[e].push_back(image_diff(img, ref));
      const ImageDiff& d = diffs[e].back();
      Panel p{tm, {}};
      p.lines.push_back((i == 0 ? runs[i].label + " (exact)" : runs[i].label) + (E == 1 ? "" : ", " + estimator_name(ests[e])));
      std::snprintf(buf, sizeof buf, "query %.3f s", runs[i].stats.query_s);
      p.lines.push_back(buf);
      std::snprintf(buf, sizeof buf, "RMSE %.3g (%.3g%%)", d.rmse, 100.0 * d.relative_rmse);
      p.lines.push_back(i == 0 ? "the reference" : buf);
      top.push_back(std::move(p));
      if (i > 0) {
        Rgb8 fc = false_colour_difference(img, ref, max_rel);
        write_png(base + etag + "_diff_" + tag + ".png", fc);
        std::snprintf(buf, sizeof buf, "fixed scale 0-%.3g%%", 100.0 * max_rel);
        fixed_row.push_back({fc, {"|rel. error| " + tag, buf}});
        std::snprintf(buf, sizeof buf, "auto scale 0-%.3g%% (p99)", 100.0 * auto_rel);
        auto_row.push_back({false_colour_difference(img, ref, auto_rel), {"|rel. error| " + tag, buf}});
      }
    }
    // First column of the difference rows: the colour scale with its numbers.
    fixed_row.insert(fixed_row.begin(), Panel{labelled_colour_scale(ref.width, ref.height, max_rel, text),
                                              {"colour scale", "fixed (--diff-scale)"}});
    auto_row.insert(auto_row.begin(), Panel{labelled_colour_scale(ref.width, ref.height, auto_rel, text),
                                            {"colour scale", auto_ok ? "auto: 99th pct." : "auto: all exact"}});
    sheets[e] = base + etag + "_compare.png";
    write_png(sheets[e], labelled_sheet({top, fixed_row, auto_row}, 8, text));
  }

  std::string rendered_As;  // those rendered: larger ones are skipped once the image stops changing
  for (std::size_t i = 1; i < runs.size(); ++i) rendered_As += (i > 1 ? "," : "") + format_g(runs[i].A);
  print_split("bhcl render: time split", runs[0], photon_s);
  std::fprintf(stderr, "\nbhcl render --compare: scene '%s', %dx%d, %zu photons, k=%d, M=%d, device %s\n",
               scene.name.c_str(), ropt.width, ropt.height, maps.global->size(), ropt.search.k, ropt.gather,
               device.c_str());
  for (std::size_t e = 0; e < E; ++e) {
    std::fprintf(stderr, "  estimator %s: errors against the exact render with the same estimator\n",
                 estimator_name(ests[e]).c_str());
    std::fprintf(stderr, "  %-18s %12s %12s %14s %12s %12s %10s\n", "method", "RMSE", "rel. RMSE", "mean rel err",
                 "query s", "kernel s", "build s");
    for (std::size_t i = 0; i < runs.size(); ++i)
      std::fprintf(stderr, "  %-18s %12.5g %12.5g %14.5g %12.3f %12.3f %10.3f\n", runs[i].label.c_str(),
                   diffs[e][i].rmse, diffs[e][i].relative_rmse, diffs[e][i].mean_rel_error, runs[i].stats.query_s,
                   runs[i].stats.query_kernel_s, runs[i].build_s);
    for (const auto& [name, d] : noise[e])
      std::fprintf(stderr, "  %-18s %12.5g %12.5g %14.5g   (noise floor: %s)\n", "exact, other seed", d.rmse,
                   d.relative_rmse, d.mean_rel_error, name.c_str());
  }
  // Against the reference: per pixel, and on blocks; with the noise floor's other-seed renders
  // against the same reference, so that the estimator's bias can be told from the noise.
  std::vector<ImageDiff> ref_diffs;
  std::vector<BlockError> ref_block, seed_block;
  if (!reference.rgb.empty()) {
    std::fprintf(stderr,
                 "\n  against the reference %s: per pixel, and on blocks of %dx%d pixels (blocks where the reference "
                 "sees an emitter left out):\n",
                 args.str("reference").c_str(), block, block);
    std::fprintf(stderr, "  %-22s %12s %16s %16s %22s\n", "estimator", "rel. RMSE", "block rel. RMSE",
                 "mean bias", "other render seed: block");
    for (std::size_t e = 0; e < E; ++e) {
      ref_diffs.push_back(image_diff(runs[0].images[e], reference));
      ref_block.push_back(block_error(runs[0].images[e], reference, block));
      if (!render_seed_images.empty()) seed_block.push_back(block_error(render_seed_images[e], reference, block));
      std::fprintf(stderr, "  %-22s %12.5g %16.5g %+15.3f%% %22s\n", estimator_name(ests[e]).c_str(),
                   ref_diffs[e].relative_rmse, ref_block[e].relative_rmse, 100.0 * ref_block[e].mean_bias,
                   seed_block.empty() ? "-" : format_g(seed_block[e].relative_rmse).c_str());
    }
    std::fprintf(stderr, "  (%zu blocks compared, %zu left out)\n", ref_block[0].blocks, ref_block[0].blocks_left_out);
  }
  std::fprintf(stderr,
               "  sheet%s %s: top row the renders (%s first, then A = %s), second row the colour scale and the "
               "false-colour |relative luminance error| of each against the exact render (0 to %.3g%%, fixed), "
               "third row the same on the automatic scale (the 99th percentile); black: exactly 0\n",
               E == 1 ? "" : "s (one per estimator)", E == 1 ? sheets[0].c_str() : (base + "_<estimator>_compare.png").c_str(),
               exact.c_str(), rendered_As.c_str(), 100.0 * max_rel);
  if (args.has("stats")) {
    Json j = render_header(*rt, args, scene.name, ropt, maps, popt.photons);
    j["exact"] = exact;
    j["approx"] = approx;
    j["exposure"] = exposure;
    j["diff_scale"] = max_rel;
    j["diff_scale_auto"] = auto_rels[0];
    j["photon_s"] = photon_s;
    j["trace_once_s"] = trace_stats.trace_s;
    j["traced_frame_bytes"] = frame_bytes;
    j["total_s"] = since(t_start);
    // The first estimator's figures at the top level (as before estimators were a list); every
    // estimator's in "estimators".
    j["runs"] = Json::array();
    j["noise_floor"] = Json::array();
    for (const auto& [name, d] : noise[0])
      j["noise_floor"].push_back({{"what", name}, {"rmse", d.rmse}, {"relative_rmse", d.relative_rmse},
                                  {"mean_rel_error", d.mean_rel_error}});
    for (std::size_t i = 0; i < runs.size(); ++i) j["runs"].push_back(run_json(runs[i], &diffs[0][i]));
    j["estimators"] = Json::array();
    for (std::size_t e = 0; e < E; ++e) {
      Json je;
      je["estimator"] = estimator_name(ests[e]);
      je["radius"] = radius_estimator_name(ests[e].radius);
      je["filter"] = density_filter_name(ests[e].filter);
      je["sheet"] = sheets[e];
      je["diff_scale_auto"] = auto_rels[e];
      je["runs"] = Json::array();
      for (std::size_t i = 0; i < runs.size(); ++i) je["runs"].push_back(run_json(runs[i], &diffs[e][i]));
      je["noise_floor"] = Json::array();
      for (const auto& [name, d] : noise[e])
        je["noise_floor"].push_back({{"what", name}, {"rmse", d.rmse}, {"relative_rmse", d.relative_rmse},
                                     {"mean_rel_error", d.mean_rel_error}});
      if (!ref_diffs.empty()) {
        je["vs_reference"] = {{"rmse", ref_diffs[e].rmse},
                              {"relative_rmse", ref_diffs[e].relative_rmse},
                              {"block", block},
                              {"block_relative_rmse", ref_block[e].relative_rmse},
                              {"mean_bias", ref_block[e].mean_bias},
                              {"blocks", ref_block[e].blocks},
                              {"blocks_left_out", ref_block[e].blocks_left_out},
                              {"mean_luminance", mean_luminance(runs[0].images[e])}};
        if (!seed_block.empty()) {
          je["vs_reference"]["render_seed_block_relative_rmse"] = seed_block[e].relative_rmse;
          je["vs_reference"]["render_seed_mean_bias"] = seed_block[e].mean_bias;
        }
      }
      j["estimators"].push_back(je);
    }
    if (!reference.rgb.empty()) {
      j["reference"] = args.str("reference");
      j["reference_mean_luminance"] = mean_luminance(reference);
    }
    write_json(args.str("stats"), j);
  }
  return 0;
}

RegisterCommand reg("render", "the photon-mapping renderer, final gather answered by a kNN method",
                    declare_render, run_render);

}  // namespace
}  // namespace bhcl::cli
