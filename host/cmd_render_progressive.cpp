// bhcl render --passes N / --time SECONDS: progressive photon mapping (host/render/progressive.hpp).
// Each pass traces its own photons, rebuilds the photon map's index, renders with its own rays and
// a shrunk disc, and the image is the running mean; one line per pass on the terminal, the running
// image written to --out every --exr-every passes (write_exr: a temporary renamed over the file, so
// a reader or a kill never sees half an image).
#include <cmath>
#include <cstdio>

#include "blockhash_cl/blockhash.hpp"
#include "exr_io.hpp"
#include "png_io.hpp"
#include "progressive.hpp"
#include "render_runs.hpp"

namespace bhcl::cli::render_cmd {

int run_progressive(const RenderSetup& s) {
  const Args& args = s.args;
  const std::string method = args.str("method", "kdtree");
  ProgressiveOptions po;
  // --time alone: passes until the time is up (the option's upper bound caps them).
  po.passes = static_cast<int>(args.has("passes") ? args.integer("passes", 1) : (args.has("time") ? 1000000 : 1));
  po.time_s = args.number("time", 0.0);
  po.alpha = args.number("alpha", kPpmAlpha);
  po.method = method;
  // The paper presets: B sized for the A and k asked (the talk's rule).
  po.index_options = method == "blockhash" ? paper_options_for_search(s.mopt, s.ropt.search) : s.mopt;
  po.runtime = s.rt;
  po.photons = s.popt;
  const long long exr_every = args.integer("exr-every", 0);
  RenderOptions ropt = s.ropt;
  ropt.search.A = s.ropt.search.A;
  std::fprintf(stderr, "bhcl render: progressive photon mapping, %s%d passes%s, alpha %.4g, method %s\n",
               args.has("passes") || !args.has("time") ? "" : "up to ", po.passes,
               po.time_s > 0 ? (" or " + format_g(po.time_s) + " s").c_str() : "", po.alpha, method.c_str());
  int written = 0;
  // --reference: each pass's running image against it on blocks (block_error: emitter blocks left
  // out), the convergence curve.
  const int rblock = static_cast<int>(args.integer("reference-block", 8));
  const Image reference = read_reference(args, ropt);
  std::vector<BlockError> errors;
  auto on_pass = [&](const PassReport& r, const Image& img) {
    if (args.has("reference")) {
      errors.push_back(block_error(img, reference, rblock));
      const BlockError& e = errors.back();
      std::fprintf(stderr,
                   "bhcl render: pass %d vs reference, %d-px blocks (%zu, %zu with the emitter left out): RMSE "
                   "%.2f %%, worst %.2f %% at (%d, %d), bias %+.2f %%; %.2f s\n",
                   r.pass, rblock, e.blocks, e.blocks_left_out, 100 * e.relative_rmse, 100 * e.worst_relative,
                   e.worst_x, e.worst_y, 100 * e.mean_bias, r.elapsed_s);
    }
    // One line per pass, --quiet or not (it only silences the progress bars), as every other
    // "bhcl render:" line.
    std::fprintf(stderr,
                   "bhcl render: pass %d%s: %zu photons (%zu caustic) %.2f s, index %s %.2f s, render %.2f s, "
                   "disc scale r_i/r_1 = %.4f; %.2f s so far\n",
                   r.pass, po.time_s > 0 && !args.has("passes") ? "" : ("/" + std::to_string(po.passes)).c_str(),
                   r.photons, r.caustic_photons, r.photon_s, r.rebuilt ? "rebuilt" : "built", r.build_s, r.render_s,
                   std::sqrt(r.radius_scale2), r.elapsed_s);
    if (exr_every > 0 && r.pass % exr_every == 0) {
      write_exr(s.out, img);
      ++written;
      std::fprintf(stderr, "bhcl render: wrote %s (mean of %d passes)\n", s.out.c_str(), r.pass);
    }
  };
  ProgressiveResult res = render_progressive(s.es, s.lights, ropt, po, &s.maps, on_pass);
  write_exr(s.out, res.image);
  const float exposure = s.exposure_opt > 0 ? static_cast<float>(s.exposure_opt) : auto_exposure(res.image);
  const std::string png = args.str("png", beside_output(s.out, s.base, ".png"));
  write_png(png, tonemap(res.image, exposure));
  const double total = since(s.t_start);
  const RenderStats& st = res.stats;
  std::fprintf(stderr,
               "bhcl render: %d passes in %.2f s: photons %.2f s | index builds %.2f s | camera+shadow+gather rays "
               "%.2f s | gather queries %.2f s (kernel %.2f s, %zu queries) | shading %.2f s\n",
               res.passes, res.total_s, res.photon_s, res.build_s, st.trace_s, st.query_s, st.query_kernel_s,
               st.queries + st.caustic_queries, st.shade_s);
  std::fprintf(stderr, "bhcl render: wrote %s and %s (exposure %.4g); total %.2f s on %s\n", s.out.c_str(),
               png.c_str(), exposure, total, s.device.c_str());
  if (args.has("stats")) {
    // s.maps was moved into pass 1: the header's photon figures come from the reports.
    Json j = stats_header("render", *s.rt);
    add_image_fields(j, args, s.scene.name, ropt.width, ropt.height, ropt.spp);
    j["gather"] = ropt.gather;
    j["k"] = ropt.search.k;
    j["estimator"] = estimator_name(ropt.estimator);
    j["boundary"] = ropt.boundary_correction ? "surface" : "none";
    j["seed"] = ropt.seed;
    j["method"] = method;
    j["photons_requested"] = s.popt.photons;
    j["alpha"] = po.alpha;
    j["passes"] = res.passes;
    j["time_limit_s"] = po.time_s;
    j["exr_written"] = written;
    j["photon_s"] = res.photon_s;
    j["index_build_s"] = res.build_s;
    j["trace_s"] = st.trace_s;
    j["query_s"] = st.query_s;
    j["query_kernel_s"] = st.query_kernel_s;
    j["shade_s"] = st.shade_s;
    j["queries"] = st.queries;
    j["result_bytes"] = st.result_bytes;
    j["fused_estimate"] = ropt.fused_estimate;
    j["caustic_queries"] = st.caustic_queries;
    j["exposure"] = exposure;
    j["total_s"] = total;
    Json passes = Json::array();
    for (std::size_t i = 0; i < res.reports.size(); ++i) {
      const PassReport& r = res.reports[i];
      Json p = {{"pass", r.pass}, {"radius_scale2", r.radius_scale2}, {"photons", r.photons},
                {"caustic_photons", r.caustic_photons}, {"photon_s", r.photon_s}, {"build_s", r.build_s},
                {"render_s", r.render_s}, {"elapsed_s", r.elapsed_s}, {"rebuilt", r.rebuilt}};
      if (i < errors.size()) {
        p["block_rmse"] = errors[i].relative_rmse;
        p["block_worst"] = errors[i].worst_relative;
        p["block_worst_xy"] = {errors[i].worst_x, errors[i].worst_y};
        p["block_bias"] = errors[i].mean_bias;
        p["blocks"] = errors[i].blocks;
        p["blocks_left_out"] = errors[i].blocks_left_out;
      }
      passes.push_back(p);
    }
    if (args.has("reference")) {
      j["reference"] = args.str("reference");
      j["reference_block"] = rblock;
    }
    j["pass_reports"] = passes;
    write_json(args.str("stats"), j);
  }
  return 0;
}

}  // namespace bhcl::cli::render_cmd
