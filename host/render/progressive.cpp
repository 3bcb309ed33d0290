#include "progressive.hpp"

#include <chrono>
#include <cmath>
#include <string>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/error.hpp"

namespace bhcl::render {
namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

void check_alpha(double alpha) {
  if (!(alpha > 0 && alpha < 1))
    throw Error("progressive photon mapping: alpha must be in (0, 1), got " + std::to_string(alpha));
}

}  // namespace

double ppm_radius_scale2(int pass, double alpha) {
  check_alpha(alpha);
  if (pass < 1) throw Error("progressive photon mapping: passes count from 1, got pass " + std::to_string(pass));
  double s = 1.0;
  for (int j = 1; j < pass; ++j) s *= (j + alpha) / (j + 1.0);
  return s;
}

std::uint64_t ppm_pass_seed(std::uint64_t base, int pass) {
  if (pass <= 1) return base;
  // Mixed twice, so that base + 1's passes do not run into base's (a plain base + pass would).
  return splitmix64(splitmix64(base) ^ static_cast<std::uint64_t>(pass));
}

ProgressiveResult render_progressive(const EmbreeScene& es, const LightSampler& lights, RenderOptions ropt,
                                     const ProgressiveOptions& opt, PhotonMaps* first,
                                     const std::function<void(const PassReport&, const Image&)>& on_pass) {
  check_alpha(opt.alpha);
  if (opt.passes < 1) throw Error("progressive photon mapping: passes must be >= 1, got " + std::to_string(opt.passes));
  if (!(opt.time_s >= 0) || !std::isfinite(opt.time_s))
    throw Error("progressive photon mapping: the time limit must be finite and >= 0 (0: none)");
  if (!opt.runtime) throw Error("progressive photon mapping: no OpenCL runtime given");
  const auto t_start = Clock::now();
  const std::uint64_t ray_seed = ropt.seed;
  ProgressiveResult res;
  res.image = Image(ropt.width, ropt.height);
  std::vector<double> sum(res.image.rgb.size(), 0.0);  // double: hundreds of passes add up exactly enough
  // The boundary correction's rasters depend on the scene only: built once, shared by every pass.
  if (ropt.boundary_correction && !ropt.surface_areas)
    ropt.surface_areas = std::make_shared<const SurfaceAreaMap>(es, ropt.threads);
  PhotonMaps prev;
  for (int pass = 1; pass <= opt.passes; ++pass) {
    if (pass > 1 && opt.time_s > 0 && since(t_start) >= opt.time_s) break;
    PassReport rep;
    rep.pass = pass;
    rep.radius_scale2 = ppm_radius_scale2(pass, opt.alpha);

    // This pass's photons.
    auto t0 = Clock::now();
    PhotonMaps maps;
    if (pass == 1 && first) {
      maps = std::move(*first);
      rep.photon_s = maps.trace.seconds;
    } else {
      PhotonTraceOptions po = opt.photons;
      po.seed = ppm_pass_seed(opt.photons.seed, pass);
      maps = build_photon_maps(es, lights, po);
      rep.photon_s = since(t0);
    }
    rep.photons = maps.global ? maps.global->size() : 0;
    rep.caustic_photons = maps.caustic ? maps.caustic->size() : 0;

    // Its index: the previous pass's rebuilt in place where the method can, else a fresh build.
    t0 = Clock::now();
    if (prev.global && prev.global->index()) {
      rep.rebuilt = prev.global->index()->rebuilds_in_place();
      maps.global->rebuild_index_from(*prev.global, opt.method, opt.runtime, opt.index_options);
    } else {
      maps.global->build_index(opt.method, opt.runtime, opt.index_options);
    }
    if (maps.caustic) {
      if (prev.caustic && prev.caustic->index())
        maps.caustic->rebuild_index_from(*prev.caustic, opt.method, opt.runtime, opt.index_options);
      else
        maps.caustic->build_index(opt.method, opt.runtime, opt.index_options);
    }
    rep.build_s = since(t0);

    // The pass's render: its own rays, the shrunk disc.
    t0 = Clock::now();
    RenderOptions po = ropt;
    po.seed = ppm_pass_seed(ray_seed, pass);
    po.radius_scale2 = static_cast<float>(rep.radius_scale2);
    FinalGatherRenderer renderer(es, lights, *maps.global, maps.caustic.get(), po);
    const Image img = renderer.render(res.stats);
    rep.render_s = since(t0);

    for (std::size_t i = 0; i < sum.size(); ++i) sum[i] += img.rgb[i];
    res.passes = pass;
    const double inv = 1.0 / pass;
    for (std::size_t i = 0; i < sum.size(); ++i) res.image.rgb[i] = static_cast<float>(sum[i] * inv);
    res.photon_s += rep.photon_s;
    res.build_s += rep.build_s;
    rep.elapsed_s = since(t_start);
    res.reports.push_back(rep);
    if (on_pass) on_pass(rep, res.image);
    prev = std::move(maps);  // its index is the next pass's to rebuild
  }
  res.total_s = since(t_start);
  return res;
}

}  // namespace bhcl::render
