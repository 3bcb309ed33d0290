// bhcl render --compare: the same photon map and the same rays, traced once, shaded by an exact
// method and by block hashing at several A (and estimators); the images side by side with
// false-colour differences, error figures and the noise floor.
#include <algorithm>
#include <cmath>
#include <cstdio>

#include "exr_io.hpp"
#include "png_io.hpp"
#include "progress.hpp"
#include "render_runs.hpp"

namespace bhcl::cli::render_cmd {

int run_compare(const RenderSetup& s) {
  const Args& args = s.args;
  const auto t_start = s.t_start;
  const bool quiet = s.quiet;
  const std::string& out = s.out;
  const std::string& base = s.base;
  RenderOptions& ropt = s.ropt;
  const std::vector<DensityEstimator>& ests = s.ests;
  const MethodOptions& mopt = s.mopt;
  const Scene& scene = s.scene;
  EmbreeScene& es = s.es;
  LightSampler& lights = s.lights;
  PhotonTraceOptions& popt = s.popt;
  PhotonMaps& maps = s.maps;
  const double photon_s = s.photon_s;
  const std::shared_ptr<Runtime>& rt = s.rt;
  const std::string& device = s.device;
  const double exposure_opt = s.exposure_opt;
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
  const int block = static_cast<int>(args.integer("reference-block", 8));
  const Image reference = read_reference(args, ropt);

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

}  // namespace bhcl::cli::render_cmd
