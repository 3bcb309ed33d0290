// bhcl pathtrace: the independent reference for the renderer. The same scene and camera as
// `bhcl render`, rendered by path tracing without any photon map or kNN (host/render/path_trace.hpp),
// so that `bhcl render --compare --reference` can measure each density estimator's own error.
#include <chrono>
#include <cmath>
#include <cstdio>

#include "cli.hpp"
#include "commands.hpp"
#include "compare.hpp"
#include "embree_scene.hpp"
#include "exr_io.hpp"
#include "path_trace.hpp"
#include "png_io.hpp"
#include "progress.hpp"
#include "scene.hpp"

namespace bhcl::cli {
namespace {

using namespace bhcl::render;

void declare_pathtrace(Args& a) {
  a.add_required("out", "the image (half-float OpenEXR); a PNG preview goes beside it", "IMAGE.exr");
  a.add_text("scene", "cornell, a scene name from the scenes folder, or an OBJ file", "cornell", "SCENE");
  a.add_text("size", "image size WxH", "512x512", "WxH");
  a.add_integer("spp", "paths per pixel", 1, 1 << 24, "64");
  a.add_integer("max-depth", "path vertices at most (Russian roulette ends most paths before)", 1, 4096, "64");
  a.add_integer("seed", "random seed", 0, Args::kNoLimit, "1");
  a.add_integer("threads", "host threads (0: all); the image does not depend on it", 0, 4096, "0");
  a.add_text("png", "the tone-mapped PNG preview", "OUT with .png", "FILE");
  a.add_number("exposure", "tone-mapping exposure (0: automatic)", "0");
  a.add_text("stats", "write timings and parameters here as JSON", "", "FILE");
  a.add_flag("quiet", "no progress bar");
  a.add_text("window", "trace only the pixels x0 <= x < x1, y0 <= y < y1", "", "X0,Y0,X1,Y1");
  a.add_text("base", "with --window: the pixels outside the window are this image's (an EXR of the same size)", "",
             "IMAGE.exr");
}

// --size, --spp, --max-depth, --seed and --threads.
PathTraceOptions pathtrace_options(const Args& args) {
  PathTraceOptions opt;
  parse_image_size(args.str("size", "512x512"), opt.width, opt.height);
  opt.spp = static_cast<int>(args.integer("spp", 64));
  opt.max_depth = static_cast<int>(args.integer("max-depth", 64));
  opt.seed = static_cast<std::uint64_t>(args.integer("seed", 1));
  opt.threads = static_cast<int>(args.integer("threads", 0));
  return opt;
}

// --window X0,Y0,X1,Y1, inside the image (none when empty).
void parse_window(const std::string& window, PathTraceOptions& opt) {
  if (window.empty()) return;
  char tail = 0;
  if (std::sscanf(window.c_str(), "%d,%d,%d,%d%c", &opt.window_x0, &opt.window_y0, &opt.window_x1, &opt.window_y1,
                  &tail) != 4 ||
      opt.window_x0 < 0 || opt.window_y0 < 0 || opt.window_x1 > opt.width || opt.window_y1 > opt.height ||
      opt.window_x0 >= opt.window_x1 || opt.window_y0 >= opt.window_y1)
    throw UsageError("--window must be X0,Y0,X1,Y1 inside the image with X0 < X1 and Y0 < Y1, got '" + window + "'");
}

// --base: the pixels outside the window are the base image's.
void paste_outside_window(const std::string& base, const PathTraceOptions& opt, Image& img) {
  const Image b = read_exr(base);
  if (b.width != img.width || b.height != img.height)
    throw UsageError("--base " + base + " is " + std::to_string(b.width) + "x" + std::to_string(b.height) +
                     ", the image " + std::to_string(img.width) + "x" + std::to_string(img.height));
  for (int y = 0; y < img.height; ++y)
    for (int x = 0; x < img.width; ++x)
      if (x < opt.window_x0 || x >= opt.window_x1 || y < opt.window_y0 || y >= opt.window_y1) {
        const std::size_t i = static_cast<std::size_t>(y) * img.width + x;
        img.set(i, b.at(i));
      }
}

// What the trace did: its paths, their vertices, the shadow rays and the time.
Json trace_json(const PathTraceStats& stats) {
  return {{"paths", stats.paths},
          {"vertices", stats.vertices},
          {"shadow_rays", stats.shadow_rays},
          {"trace_s", stats.seconds}};
}

Json pathtrace_stats(const Args& args, const std::string& scene, const PathTraceOptions& opt,
                     const PathTraceStats& stats, double mean, float exposure, double total_s) {
  Json j;
  j["command"] = "pathtrace";
  add_image_fields(j, args, scene, opt.width, opt.height, opt.spp);
  j["max_depth"] = opt.max_depth;
  if (!args.str("window", "").empty()) j["window"] = {opt.window_x0, opt.window_y0, opt.window_x1, opt.window_y1};
  if (const std::string base = args.str("base", ""); !base.empty()) j["base"] = base;
  j["seed"] = opt.seed;
  j.update(trace_json(stats));
  j["mean_luminance"] = mean;
  j["exposure"] = exposure;
  j["total_s"] = total_s;
  return j;
}

int run_pathtrace(const Args& args) {
  const auto t0 = std::chrono::steady_clock::now();
  PathTraceOptions opt = pathtrace_options(args);
  const double exposure_opt = args.number("exposure", 0.0);
  if (exposure_opt < 0 || !std::isfinite(exposure_opt)) throw UsageError("--exposure must be >= 0 (0: automatic)");
  const std::string out = args.str("out");
  const std::string window = args.str("window", ""), base = args.str("base", "");
  parse_window(window, opt);
  if (!base.empty() && window.empty()) throw UsageError("--base applies only with --window");
  const std::string png = args.str("png", beside_output(out, strip_extension(out), ".png"));
  check_distinct_files({{"--scene", args.str("scene", "")}, {"--base", base}},
                       {{"--out", out}, {args.has("png") ? "--png" : "the PNG beside --out", png},
                        {"--stats", args.str("stats", "")}});

  Scene scene = load_scene(args.str("scene", "cornell"));
  if (!scene.has_light()) throw UsageError("scene '" + scene.name + "' has no emitter: the image would be black");
  EmbreeScene es(scene, opt.threads);
  LightSampler lights(scene);
  PathTraceStats stats;
  Image img;
  {
    Progress bar("path trace", !args.flag("quiet"));
    img = path_trace(es, lights, opt, stats, &bar);
    bar.finish();
  }
  if (!base.empty()) paste_outside_window(base, opt, img);
  write_exr(out, img);
  const float exposure = exposure_opt > 0 ? static_cast<float>(exposure_opt) : auto_exposure(img);
  write_png(png, tonemap(img, exposure));
  const double mean = mean_luminance(img);
  std::fprintf(stderr,
               "bhcl pathtrace: scene '%s', %dx%d, %d spp: %zu paths, %.2f vertices per path, %zu shadow rays in "
               "%.2f s; mean luminance %.6g; wrote %s and %s\n",
               scene.name.c_str(), opt.width, opt.height, opt.spp, stats.paths,
               stats.paths ? static_cast<double>(stats.vertices) / stats.paths : 0.0, stats.shadow_rays,
               stats.seconds, mean, out.c_str(), png.c_str());
  if (args.has("stats")) {
    const double total_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    write_json(args.str("stats"), pathtrace_stats(args, scene.name, opt, stats, mean, exposure, total_s));
  }
  return 0;
}

RegisterCommand reg_pathtrace("pathtrace", "a path-traced reference image of a render scene (no photon map)",
                              declare_pathtrace, run_pathtrace);

}  // namespace
}  // namespace bhcl::cli
