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
#include "render_runs.hpp"

namespace bhcl::cli {
namespace {

using namespace render_cmd;

void declare_render(Args& a) {
  a.add_required("out", "the image (half-float OpenEXR); a PNG preview goes beside it", "IMAGE.exr");
  a.add_text("scene", "cornell, a scene name from the scenes folder, or an OBJ file", "cornell", "SCENE");
  a.add_text("method", "the kNN method of the final gather", "kdtree",
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
  a.add_text("boundary", "density estimates near walls, corners and the glass's footprint: surface (only the photons "
                         "on the gather point's surface, over the part of the disc on it; planar scenes) or none "
                         "(the whole disc, biased low within a disc of an edge; for curved meshes)", "surface", "NAME");
  a.add_flag("quiet", "no progress bars");
  a.add_flag("lists", "shade from the k-nearest lists read back to the host (8 k + 4 bytes a query) instead of the "
                      "density estimate made inside the query (16 bytes a query); for measurement");
  a.group("Progressive photon mapping");
  a.add_integer("passes", "passes, each with its own photons and rays, the disc shrinking pass to pass (Knaus and "
                          "Zwicker's probabilistic PPM); the image is their mean", 1, 1000000, "1");
  a.add_number("time", "no pass starts after this many seconds (> 0; pass 1 always runs; --passes still caps them)", "0");
  a.add_number("alpha", "PPM's alpha in (0, 1): pass i's squared radius is (i - 1 + alpha) / i times pass i - 1's",
               "0.666667");
  a.add_integer("exr-every", "write the running image to --out every K passes (atomically: a temporary renamed)",
                1, 1000000, "0");
  a.group("Comparison");
  a.add_flag("compare", "render with an exact method and with block hashing at several A, side by side");
  a.add_text("exact", "--compare: the exact method", "kdtree", "NAME");
  a.add_text("approx", "--compare: the approximate method", "blockhash", "NAME");
  a.add_text("compare-A", "--compare: the values of A, comma separated", "4,8,16", "LIST");
  a.add_number("diff-scale", "--compare: relative error shown as full scale in the difference images", "0.1");
  a.add_flag("noise-floor", "--compare: also render the exact method with another photon seed and with another "
                            "render seed, and print their differences (the render's own Monte Carlo noise)");
  a.add_text("reference", "--compare, and progressive renders (each pass's image): an independent render of the same scene and camera (EXR, e.g. bhcl "
                          "pathtrace): each estimator's exact render is compared with it", "", "IMAGE.exr");
  a.add_integer("reference-block", "--compare: block size (pixels) of the block-averaged error against --reference",
                1, 4096, "8");
  declare_index_options(a, 50, true);
}

// The options that apply only to one kind of render (--compare, a progressive one), refused in
// the others; before any work.
void check_render_usage(const Args& args) {
  const bool cmp = args.flag("compare");
  const bool prog0 = args.integer("passes", 1) > 1 || args.has("time");
  for (const char* o : {"exact", "approx", "compare-A", "diff-scale", "noise-floor", "reference", "reference-block"})
    if (!cmp && args.has(o) && !(prog0 && (std::string(o) == "reference" || std::string(o) == "reference-block")))
      throw UsageError("--" + std::string(o) + " applies only with --compare" +
                       (std::string(o).rfind("reference", 0) == 0 ? " or a progressive render" : ""));
  if (cmp && args.has("method")) throw UsageError("--method does not apply with --compare (see --exact, --approx)");
  for (const char* o : {"passes", "time", "alpha", "exr-every", "lists"})
    if (cmp && args.has(o)) throw UsageError("--" + std::string(o) + " does not apply with --compare");
  const bool prog = args.integer("passes", 1) > 1 || args.has("time");
  for (const char* o : {"alpha", "exr-every"})
    if (!prog && args.has(o))
      throw UsageError("--" + std::string(o) + " applies only to a progressive render (--passes N > 1 or --time)");
  if (args.has("time")) {
    const double t = args.number("time", 0);
    if (!(t > 0) || !std::isfinite(t)) throw UsageError("--time must be a positive number of seconds");
  }
  if (args.has("alpha")) {
    const double al = args.number("alpha", 0);
    if (!(al > 0 && al < 1)) throw UsageError("--alpha must be in (0, 1) (exclusive), got " + args.str("alpha", ""));
  }
  const std::string dflt = "kdtree";
  // --threads and --seed also drive Embree and the photon tracer.
  if (cmp)
    check_method_options(args, {args.str("exact", dflt), args.str("approx", "blockhash")}, {"threads", "seed"});
  else
    check_method_options(args, {args.str("method", dflt)}, {"threads", "seed"});
}

// The image, the gather and its kNN search (seed and threads come later, from the method options).
RenderOptions render_options(const Args& args) {
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
  // surface by default: measured better on both Cornell boxes (docs/RENDER.md, "The boundary
  // correction"); none for scenes of curved meshes, where every facet would be its own plane.
  const std::string boundary = args.str("boundary", "surface");
  if (boundary != "none" && boundary != "surface")
    throw UsageError("--boundary must be none or surface, got '" + boundary + "'");
  ropt.boundary_correction = boundary == "surface";
  return ropt;
}

// Before any work: no output may overwrite the scene, a saved index or another output (the PNG
// preview lands beside --out unless --png names it).
void check_render_files(const Args& args, const std::string& out, const std::string& base, const MethodOptions& mopt,
                        bool compare) {
  std::vector<FileArg> outputs = {{"--out", out},
                                  {args.has("png") ? "--png" : "the PNG beside --out", args.str("png", beside_output(out, base, ".png"))},
                                  {"--stats", args.str("stats", "")},
                                  {"--save-index", mopt.save_index()}};
  if (compare) outputs.push_back({"the comparison sheet beside --out", beside_output(out, base, "_compare.png")});
  check_distinct_files({{"--scene", args.str("scene", "")},
                        {"--load-index", mopt.load_index()},
                        {"--reference", args.str("reference", "")}},
                       outputs);
}

void print_scene(const Scene& scene, const LightSampler& lights, const RenderOptions& ropt) {
  Vec3 P = lights.total_power();
  std::fprintf(stderr,
               "bhcl render: scene '%s': %zu triangles, %zu emitter triangles, emitted power (%.4g, %.4g, %.4g) "
               "[radiance x mm^2], %dx%d, %d spp, %d gather rays, k=%d\n",
               scene.name.c_str(), scene.triangles.size(), lights.count(), P.x, P.y, P.z, ropt.width,
               ropt.height, ropt.spp, ropt.gather, ropt.search.k);
}

// The global and caustic photon maps, traced with a progress bar and reported.
PhotonMaps trace_photons(const Scene& scene, const EmbreeScene& es, const LightSampler& lights,
                         const PhotonTraceOptions& popt, bool quiet) {
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
  return maps;
}

// The plain render: one method, pass by pass; the EXR, its PNG preview and the stats.
int run_plain(const RenderSetup& s) {
  const Args& args = s.args;
  const std::string method = args.str("method", "kdtree");
  RenderRun r = render_with(method, method, s.ropt.search.A, s.maps, s.rt, s.mopt, s.es, s.lights, s.ropt, s.quiet);
  write_exr(s.out, r.images[0]);
  const float exposure = s.exposure_opt > 0 ? static_cast<float>(s.exposure_opt) : auto_exposure(r.images[0]);
  const std::string png = args.str("png", beside_output(s.out, s.base, ".png"));
  write_png(png, tonemap(r.images[0], exposure));
  const double total = since(s.t_start);
  print_split("bhcl render: time split", r, s.photon_s);
  print_skipped(r, s.maps);
  std::fprintf(stderr, "bhcl render: wrote %s and %s (exposure %.4g); total %.2f s on %s\n", s.out.c_str(),
               png.c_str(), exposure, total, s.device.c_str());
  if (args.has("stats")) {
    Json j = render_header(*s.rt, args, s.scene.name, s.ropt, s.maps, s.popt.photons);
    j.update(run_json(r, nullptr));  // method, A, build, search, the time split, query counts
    j["exposure"] = exposure;
    j["gather_rays"] = r.stats.gather_rays;
    j["gather_escaped"] = r.stats.gather_escaped;
    j["gather_no_query"] = r.stats.gather_no_query;
    j["camera_samples"] = r.stats.camera_rays;
    j["caustic_map"] = s.maps.caustic != nullptr;
    j["visible_points"] = r.stats.visible_points;
    j["photon_s"] = s.photon_s;
    j["total_s"] = total;
    write_json(args.str("stats"), j);
  }
  return 0;
}

int run_render(const Args& args) {
  check_render_usage(args);
  const auto t_start = Clock::now();
  const bool quiet = args.flag("quiet");
  const bool compare = args.flag("compare");
  const std::string out = args.str("out");
  const std::string base = strip_extension(out);

  RenderOptions ropt = render_options(args);
  const std::vector<DensityEstimator> ests = parse_estimators(args, compare);
  ropt.estimator = ests[0];
  // --compare shades several estimators from one set of lists; one estimator needs none.
  ropt.fused_estimate = !compare && !args.flag("lists");
  MethodOptions mopt = method_options(args);
  check_render_files(args, out, base, mopt, compare);
  ropt.seed = static_cast<std::uint64_t>(mopt.integer("seed", 1));
  ropt.threads = static_cast<int>(mopt.integer("threads", 0));
  long long photons = args.integer("photons", 200000);
  const double exposure_opt = args.number("exposure", 0.0);
  if (exposure_opt < 0 || !std::isfinite(exposure_opt)) throw UsageError("--exposure must be >= 0 (0: automatic)");

  // The scene, in Embree.
  Scene scene = load_scene(args.str("scene", "cornell"));
  EmbreeScene es(scene, ropt.threads);
  LightSampler lights(scene);
  print_scene(scene, lights, ropt);

  // Photons.
  PhotonTraceOptions popt;
  popt.photons = static_cast<std::size_t>(photons);
  const long long photon_seed = args.integer("photon-seed", -1);
  popt.seed = photon_seed >= 0 ? static_cast<std::uint64_t>(photon_seed) : ropt.seed;
  popt.threads = ropt.threads;
  PhotonMaps maps = trace_photons(scene, es, lights, popt, quiet);
  const double photon_s = maps.trace.seconds;

  auto rt = std::make_shared<Runtime>(args.str("device", ""));
  const std::string device = rt->info().summary();
  const RenderSetup setup{args, t_start, quiet, out, base, ropt, ests, mopt, scene, es, lights, popt,
                          maps, photon_s, rt, device, exposure_opt};
  if (args.integer("passes", 1) > 1 || args.has("time")) return run_progressive(setup);
  return compare ? run_compare(setup) : run_plain(setup);
}

RegisterCommand reg_render("render", "the photon-mapping renderer, final gather answered by a kNN method",
                           declare_render, run_render);

}  // namespace
}  // namespace bhcl::cli
