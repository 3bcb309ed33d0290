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
namespace {

// --exact, --approx, --compare-A and --diff-scale.
struct CompareOptions {
  std::string exact, approx;
  std::vector<float> As;
  float max_rel = 0;  // the fixed scale of the difference images
};

CompareOptions compare_options(const Args& args) {
  CompareOptions c;
  c.exact = args.str("exact", "kdtree");
  c.approx = args.str("approx", "blockhash");
  c.As = parse_list(args.str("compare-A", "4,8,16"));
  c.max_rel = static_cast<float>(args.number("diff-scale", 0.1));
  if (!(c.max_rel > 0)) throw UsageError("--diff-scale must be > 0");
  return c;
}

// The exact render's own Monte Carlo error (--noise-floor), per estimator: two exact renders that
// differ only in the photon seed or only in the render seed, each against the exact run.
using NamedDiffs = std::vector<std::pair<std::string, ImageDiff>>;
struct NoiseFloor {
  std::vector<NamedDiffs> diffs;  // per estimator; empty lists without --noise-floor
  std::vector<Image> photon_seed_images, render_seed_images;
};

// Per estimator e: diffs[e][i], run i against the exact run (both with estimator e); the
// automatic scale of the difference images; the sheet's path.
struct Sheets {
  std::vector<std::vector<ImageDiff>> diffs;
  std::vector<float> auto_rels;
  std::vector<std::string> paths;
};

// Each estimator's exact render against --reference: per pixel, and on blocks of pixels; with the
// noise floor's other-render-seed render on the same blocks.
struct ReferenceErrors {
  std::vector<ImageDiff> diffs;
  std::vector<BlockError> block, seed_block;
};

// Everything the comparison makes, for its tables and its stats file.
struct Comparison {
  CompareOptions opt;
  std::vector<RenderRun> runs;  // runs[0]: the exact method; then the approximate one by A
  RenderStats trace_stats;      // the rays, traced once
  std::size_t frame_bytes = 0;
  NoiseFloor noise;
  int block = 8;  // --reference-block
  Image reference;
  float exposure = 0;
  Sheets sheets;
  ReferenceErrors ref;
};

// Camera, shadow and gather rays traced once, for every run to shade.
TracedFrame trace_once(const RenderSetup& s, RenderStats& trace_stats) {
  TracedFrame frame;
  {
    FinalGatherRenderer tracer(s.es, s.lights, *s.maps.global, s.maps.caustic.get(), s.ropt);
    Progress bar("trace rays", !s.quiet);
    frame = tracer.trace(trace_stats, &bar);
    bar.finish();
  }
  std::fprintf(stderr,
               "bhcl render --compare: camera, shadow and gather rays traced once in %.2f s (%zu gather queries "
               "kept, %.1f MiB), shaded by every run\n",
               trace_stats.trace_s, trace_stats.gather_rays - trace_stats.gather_escaped - trace_stats.gather_no_query,
               frame.bytes() / 1048576.0);
  return frame;
}

// At most this many gather queries, evenly spread over the frame, measure the lists' accuracy:
// enough for the mean dilation to two or three digits, a small share of a render's queries.
constexpr std::size_t kListSample = 20000;

// Every stride-th gather query of the frame, at most `most` of them (3 floats each).
std::vector<float> gather_sample(const TracedFrame& frame, std::size_t most) {
  std::size_t total = 0;
  for (const TracedPass& p : frame.passes) total += p.gather_xyz.size() / 3;
  const std::size_t stride = std::max<std::size_t>(1, (total + most - 1) / most);
  std::vector<float> out;
  out.reserve(3 * std::min(total, most));
  std::size_t i = 0;
  for (const TracedPass& p : frame.passes)
    for (std::size_t q = 0; q < p.gather_xyz.size() / 3; ++q, ++i)
      if (i % stride == 0) out.insert(out.end(), p.gather_xyz.begin() + 3 * q, p.gather_xyz.begin() + 3 * q + 3);
  return out;
}

bool same_images(const RenderRun& a, const RenderRun& b, std::size_t estimators) {
  bool same = true;
  for (std::size_t e = 0; e < estimators; ++e) same = same && a.images[e].rgb == b.images[e].rgb;
  return same;
}

// Shades the frame with the exact run (runs[0], started), then with the approximate method at each
// A. A larger A examines more candidates; once the images are bit-identical to the previous A's,
// the neighbour lists that matter have stopped changing and larger A would only cost time.
void shade_sweep(const RenderSetup& s, const CompareOptions& c, const TracedFrame& frame,
                 std::vector<RenderRun>& runs) {
  shade_run(runs.back(), frame, s.ests, s.maps, s.es, s.lights, s.ropt, s.quiet);
  // The exact method's lists on a sample of the gather queries, while its index is the map's.
  const std::vector<float> sample = gather_sample(frame, kListSample);
  KnnResult truth;
  if (!sample.empty()) s.maps.global->query(sample.data(), sample.size() / 3, s.ropt.search, truth);
  for (float A : c.As) {
    char label[64];
    std::snprintf(label, sizeof label, "%s A=%g", c.approx.c_str(), A);
    runs.push_back(start_run(label, c.approx, A, s.maps, s.rt, s.mopt, s.ropt));
    if (!sample.empty()) {
      SearchParams p = s.ropt.search;
      p.A = A;
      KnnResult r;
      s.maps.global->query(sample.data(), sample.size() / 3, p, r);
      runs.back().lists_accuracy = evaluate_accuracy(r, truth);
      runs.back().has_lists_accuracy = true;
    }
    shade_run(runs.back(), frame, s.ests, s.maps, s.es, s.lights, s.ropt, s.quiet);
    if (runs.size() > 2 && same_images(runs.back(), runs[runs.size() - 2], s.ests.size())) {
      std::fprintf(stderr, "bhcl render --compare: %s gives an image bit-identical to %s: larger A skipped\n",
                   runs.back().label.c_str(), runs[runs.size() - 2].label.c_str());
      break;
    }
  }
}

// --noise-floor: a new photon map shading the same rays, and the same map with new camera, shadow
// and gather rays (the frame is dropped first: that run traces its own). Block hashing's error
// matters only against these.
NoiseFloor noise_floor(const RenderSetup& s, const Comparison& c, TracedFrame& frame) {
  const std::string& exact = c.opt.exact;
  PhotonTraceOptions popt2 = s.popt;
  popt2.seed = s.popt.seed + 1000003;
  PhotonMaps maps2 = build_photon_maps(s.es, s.lights, popt2);
  RenderRun p2 = start_run(exact + " photon seed+", exact, s.ropt.search.A, maps2, s.rt, s.mopt, s.ropt);
  shade_run(p2, frame, s.ests, maps2, s.es, s.lights, s.ropt, s.quiet);
  frame = TracedFrame{};  // its memory: the render-seed run traces its own
  RenderOptions ropt2 = s.ropt;
  ropt2.seed = s.ropt.seed + 1000003;
  RenderRun r2 = start_run(exact + " render seed+", exact, s.ropt.search.A, s.maps, s.rt, s.mopt, ropt2);
  {
    FinalGatherRenderer renderer(s.es, s.lights, *s.maps.global, s.maps.caustic.get(), ropt2);
    RenderStats ts;
    Progress bar("render " + r2.label, !s.quiet);
    TracedFrame f2 = renderer.trace(ts, &bar);
    r2.images = renderer.shade(f2, s.ests, r2.stats, nullptr);
    bar.finish();
  }
  NoiseFloor nf;
  nf.diffs.resize(s.ests.size());
  for (std::size_t e = 0; e < s.ests.size(); ++e) {
    const Image& exact_image = c.runs[0].images[e];
    nf.diffs[e].emplace_back("exact, photon seed " + std::to_string(popt2.seed), image_diff(p2.images[e], exact_image));
    nf.diffs[e].emplace_back("exact, render seed " + std::to_string(ropt2.seed), image_diff(r2.images[e], exact_image));
  }
  nf.photon_seed_images = std::move(p2.images);
  nf.render_seed_images = std::move(r2.images);
  return nf;
}

// Estimator e: each run's EXR and PNG (--out is the first estimator's exact render), its false-
// colour difference to the exact render, and the sheet: the renders on top, then the differences
// on the fixed and on the automatic scale.
void write_estimator_sheet(const RenderSetup& s, const Comparison& c, std::size_t e, const TextPainter& text,
                           Sheets& out) {
  const std::vector<RenderRun>& runs = c.runs;
  const std::size_t E = s.ests.size();
  const float max_rel = c.opt.max_rel;
  const Image& ref = runs[0].images[e];
  // With several estimators every output name carries the estimator ("_kth-cone").
  const std::string etag = E == 1 ? "" : "_" + estimator_tag(s.ests[e]);
  std::vector<Panel> top, fixed_row, auto_row;
  std::vector<const Image*> approx_images;
  for (std::size_t i = 1; i < runs.size(); ++i) approx_images.push_back(&runs[i].images[e]);
  // The automatic scale: the 99th percentile of every approximate image's per-pixel error, so
  // that errors far below the fixed scale still show (0 when all are exact: then the fixed one).
  float auto_rel = relative_error_percentile(approx_images, ref, 0.99f);
  const bool auto_ok = auto_rel > 0;
  if (!auto_ok) auto_rel = max_rel;
  out.auto_rels[e] = auto_rel;
  char buf[128];
  for (std::size_t i = 0; i < runs.size(); ++i) {
    const Image& img = runs[i].images[e];
    const std::string tag = i == 0 ? "exact" : "A" + format_g(runs[i].A);
    const std::string exr = i == 0 ? (e == 0 ? s.out : beside_output(s.out, s.base, etag + ".exr")) : beside_output(s.out, s.base, etag + "_" + tag + ".exr");
    write_exr(exr, img);
    Rgb8 tm = tonemap(img, c.exposure);
    write_png(beside_output(exr, strip_extension(exr), ".png"), tm);
    out.diffs[e].push_back(image_diff(img, ref));
    const ImageDiff& d = out.diffs[e].back();
    Panel p{tm, {}};
    p.lines.push_back((i == 0 ? runs[i].label + " (exact)" : runs[i].label) + (E == 1 ? "" : ", " + estimator_name(s.ests[e])));
    std::snprintf(buf, sizeof buf, "query %.3f s", runs[i].stats.query_s);
    p.lines.push_back(buf);
    std::snprintf(buf, sizeof buf, "RMSE %.3g (%.3g%%)", d.rmse, 100.0 * d.relative_rmse);
    p.lines.push_back(i == 0 ? "the reference" : buf);
    if (runs[i].has_lists_accuracy) {
      const Accuracy& a = runs[i].lists_accuracy;
      std::snprintf(buf, sizeof buf, "FN %.3g%% dil %.3g/%.4f", 100.0 * a.false_negative_rate, a.max_dilation,
                    a.mean_dilation);
      p.lines.push_back(buf);
    }
    top.push_back(std::move(p));
    if (i > 0) {
      Rgb8 fc = false_colour_difference(img, ref, max_rel);
      write_png(beside_output(s.out, s.base, etag + "_diff_" + tag + ".png"), fc);
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
  out.paths[e] = beside_output(s.out, s.base, etag + "_compare.png");
  write_png(out.paths[e], labelled_sheet({top, fixed_row, auto_row}, 8, text));
}

Sheets write_sheets(const RenderSetup& s, const Comparison& c) {
  TextPainter text(std::clamp(s.ropt.width / 22, 9, 16));
  if (!text.ok()) std::fprintf(stderr, "bhcl render: the comparison sheet is unlabelled: %s\n", text.why().c_str());
  const std::size_t E = s.ests.size();
  Sheets out;
  out.diffs.resize(E);
  out.auto_rels.resize(E);
  out.paths.resize(E);
  for (std::size_t e = 0; e < E; ++e) write_estimator_sheet(s, c, e, text, out);
  return out;
}

// The time split, then per estimator each run's errors against the exact render and the noise floor.
void print_errors(const RenderSetup& s, const Comparison& c) {
  const std::vector<RenderRun>& runs = c.runs;
  print_split("bhcl render: time split", runs[0], s.photon_s);
  std::fprintf(stderr, "\nbhcl render --compare: scene '%s', %dx%d, %zu photons, k=%d, M=%d, device %s\n",
               s.scene.name.c_str(), s.ropt.width, s.ropt.height, s.maps.global->size(), s.ropt.search.k,
               s.ropt.gather, s.device.c_str());
  for (std::size_t e = 0; e < s.ests.size(); ++e) {
    const std::vector<ImageDiff>& diffs = c.sheets.diffs[e];
    std::fprintf(stderr, "  estimator %s: errors against the exact render with the same estimator\n",
                 estimator_name(s.ests[e]).c_str());
    std::fprintf(stderr, "  %-18s %12s %12s %14s %12s %12s %10s\n", "method", "RMSE", "rel. RMSE", "mean rel err",
                 "query s", "kernel s", "build s");
    for (std::size_t i = 0; i < runs.size(); ++i)
      std::fprintf(stderr, "  %-18s %12.5g %12.5g %14.5g %12.3f %12.3f %10.3f\n", runs[i].label.c_str(),
                   diffs[i].rmse, diffs[i].relative_rmse, diffs[i].mean_rel_error, runs[i].stats.query_s,
                   runs[i].stats.query_kernel_s, runs[i].build_s);
    if (e == 0 && runs.size() > 1 && runs[1].has_lists_accuracy) {
      std::fprintf(stderr, "  the global map's k-nearest lists on %zu of the gather queries against %s's (the talk's measures):\n",
                   runs[1].lists_accuracy.queries, runs[0].label.c_str());
      std::fprintf(stderr, "  %-18s %12s %12s %12s %12s %12s\n", "method", "false neg.", "dil. max", "dil. mean",
                   "recall", "incomplete");
      for (std::size_t i = 1; i < runs.size(); ++i) {
        const Accuracy& a = runs[i].lists_accuracy;
        std::fprintf(stderr, "  %-18s %12.5f %12.4f %12.5f %12.5f %12zu\n", runs[i].label.c_str(),
                     a.false_negative_rate, a.max_dilation, a.mean_dilation, a.recall, a.incomplete_queries);
      }
    }
    for (const auto& [name, d] : c.noise.diffs[e])
      std::fprintf(stderr, "  %-18s %12.5g %12.5g %14.5g   (noise floor: %s)\n", "exact, other seed", d.rmse,
                   d.relative_rmse, d.mean_rel_error, name.c_str());
  }
}

// Against --reference (when given): per pixel, and on blocks, which average away most of the
// render's per-pixel noise and keep the estimator's bias (blur at corners and edges, darkening
// near walls); with the noise floor's other-seed render against the same reference, so that the
// estimator's bias can be told from the noise.
ReferenceErrors reference_errors(const RenderSetup& s, const Comparison& c) {
  ReferenceErrors r;
  if (c.reference.rgb.empty()) return r;
  const int block = c.block;
  std::fprintf(stderr,
               "\n  against the reference %s: per pixel, and on blocks of %dx%d pixels (blocks where the reference "
               "sees an emitter left out):\n",
               s.args.str("reference").c_str(), block, block);
  std::fprintf(stderr, "  %-22s %12s %16s %16s %22s\n", "estimator", "rel. RMSE", "block rel. RMSE", "mean bias",
               "other render seed: block");
  const std::vector<Image>& seed_images = c.noise.render_seed_images;
  for (std::size_t e = 0; e < s.ests.size(); ++e) {
    r.diffs.push_back(image_diff(c.runs[0].images[e], c.reference));
    r.block.push_back(block_error(c.runs[0].images[e], c.reference, block));
    if (!seed_images.empty()) r.seed_block.push_back(block_error(seed_images[e], c.reference, block));
    std::fprintf(stderr, "  %-22s %12.5g %16.5g %+15.3f%% %22s\n", estimator_name(s.ests[e]).c_str(),
                 r.diffs[e].relative_rmse, r.block[e].relative_rmse, 100.0 * r.block[e].mean_bias,
                 r.seed_block.empty() ? "-" : format_g(r.seed_block[e].relative_rmse).c_str());
  }
  std::fprintf(stderr, "  (%zu blocks compared, %zu left out)\n", r.block[0].blocks, r.block[0].blocks_left_out);
  return r;
}

void print_sheet_note(const RenderSetup& s, const Comparison& c) {
  const std::size_t E = s.ests.size();
  std::string rendered_As;  // those rendered: larger ones are skipped once the image stops changing
  for (std::size_t i = 1; i < c.runs.size(); ++i) rendered_As += (i > 1 ? "," : "") + format_g(c.runs[i].A);
  std::fprintf(stderr,
               "  sheet%s %s: top row the renders (%s first, then A = %s), second row the colour scale and the "
               "false-colour |relative luminance error| of each against the exact render (0 to %.3g%%, fixed), "
               "third row the same on the automatic scale (the 99th percentile); black: exactly 0\n",
               E == 1 ? "" : "s (one per estimator)",
               E == 1 ? c.sheets.paths[0].c_str() : (s.base + "_<estimator>_compare.png").c_str(),
               c.opt.exact.c_str(), rendered_As.c_str(), 100.0 * c.opt.max_rel);
}

Json noise_json(const NamedDiffs& noise) {
  Json j = Json::array();
  for (const auto& [name, d] : noise)
    j.push_back({{"what", name}, {"rmse", d.rmse}, {"relative_rmse", d.relative_rmse},
                 {"mean_rel_error", d.mean_rel_error}});
  return j;
}

Json runs_json(const std::vector<RenderRun>& runs, const std::vector<ImageDiff>& diffs) {
  Json j = Json::array();
  for (std::size_t i = 0; i < runs.size(); ++i) {
    j.push_back(run_json(runs[i], &diffs[i]));
    if (!runs[i].has_lists_accuracy) continue;
    const Accuracy& a = runs[i].lists_accuracy;
    j.back()["lists_accuracy"] = {{"queries", a.queries},
                                  {"false_negative_rate", a.false_negative_rate},
                                  {"max_dilation", a.max_dilation},
                                  {"mean_dilation", a.mean_dilation},
                                  {"recall", a.recall},
                                  {"incomplete_queries", a.incomplete_queries}};
  }
  return j;
}

// Estimator e's figures in the stats file.
Json estimator_json(const RenderSetup& s, const Comparison& c, std::size_t e) {
  const DensityEstimator& est = s.ests[e];
  Json je;
  je["estimator"] = estimator_name(est);
  je["radius"] = radius_estimator_name(est.radius);
  je["filter"] = density_filter_name(est.filter);
  je["sheet"] = c.sheets.paths[e];
  je["diff_scale_auto"] = c.sheets.auto_rels[e];
  je["runs"] = runs_json(c.runs, c.sheets.diffs[e]);
  je["noise_floor"] = noise_json(c.noise.diffs[e]);
  const ReferenceErrors& r = c.ref;
  if (!r.diffs.empty()) {
    je["vs_reference"] = {{"rmse", r.diffs[e].rmse},
                          {"relative_rmse", r.diffs[e].relative_rmse},
                          {"block", c.block},
                          {"block_relative_rmse", r.block[e].relative_rmse},
                          {"mean_bias", r.block[e].mean_bias},
                          {"blocks", r.block[e].blocks},
                          {"blocks_left_out", r.block[e].blocks_left_out},
                          {"mean_luminance", mean_luminance(c.runs[0].images[e])}};
    if (!r.seed_block.empty()) {
      je["vs_reference"]["render_seed_block_relative_rmse"] = r.seed_block[e].relative_rmse;
      je["vs_reference"]["render_seed_mean_bias"] = r.seed_block[e].mean_bias;
    }
  }
  return je;
}

// --stats: the first estimator's figures at the top level (as before estimators were a list);
// every estimator's in "estimators".
void write_compare_stats(const RenderSetup& s, const Comparison& c) {
  const Args& args = s.args;
  Json j = render_header(*s.rt, args, s.scene.name, s.ropt, s.maps, s.popt.photons);
  j["exact"] = c.opt.exact;
  j["approx"] = c.opt.approx;
  j["exposure"] = c.exposure;
  j["diff_scale"] = c.opt.max_rel;
  j["diff_scale_auto"] = c.sheets.auto_rels[0];
  j["photon_s"] = s.photon_s;
  j["trace_once_s"] = c.trace_stats.trace_s;
  j["traced_frame_bytes"] = c.frame_bytes;
  j["total_s"] = since(s.t_start);
  j["runs"] = runs_json(c.runs, c.sheets.diffs[0]);
  j["noise_floor"] = noise_json(c.noise.diffs[0]);
  j["estimators"] = Json::array();
  for (std::size_t e = 0; e < s.ests.size(); ++e) j["estimators"].push_back(estimator_json(s, c, e));
  if (!c.reference.rgb.empty()) {
    j["reference"] = args.str("reference");
    j["reference_mean_luminance"] = mean_luminance(c.reference);
  }
  write_json(args.str("stats"), j);
}

}  // namespace

// --compare: the same photon map and the same rays, traced once, shaded by each method, A and
// estimator.
int run_compare(const RenderSetup& s) {
  Comparison c;
  c.opt = compare_options(s.args);
  c.runs.push_back(start_run(c.opt.exact, c.opt.exact, s.ropt.search.A, s.maps, s.rt, s.mopt, s.ropt));
  TracedFrame frame = trace_once(s, c.trace_stats);
  c.frame_bytes = frame.bytes();
  shade_sweep(s, c.opt, frame, c.runs);
  for (RenderRun& r : c.runs) add_trace_counts(r.stats, c.trace_stats);
  c.runs[0].stats.trace_s = c.trace_stats.trace_s;
  if (s.args.flag("noise-floor")) c.noise = noise_floor(s, c, frame);
  else c.noise.diffs.resize(s.ests.size());
  frame = TracedFrame{};
  c.block = static_cast<int>(s.args.integer("reference-block", 8));
  c.reference = read_reference(s.args, s.ropt);
  c.exposure = s.exposure_opt > 0 ? static_cast<float>(s.exposure_opt) : auto_exposure(c.runs[0].images[0]);
  c.sheets = write_sheets(s, c);
  print_errors(s, c);
  c.ref = reference_errors(s, c);
  print_sheet_note(s, c);
  if (s.args.has("stats")) write_compare_stats(s, c);
  return 0;
}

}  // namespace bhcl::cli::render_cmd
