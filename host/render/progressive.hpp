// Progressive photon mapping in the probabilistic form of Knaus and Zwicker ("Progressive Photon
// Mapping: A Probabilistic Approach", ACM TOG 2011).
//
// A render of one photon map is as close to the truth as its photon count allows: the density
// estimate's disc blurs the illumination (bias), and more gather rays do not shrink it. Knaus and
// Zwicker make each pass an independent photon-mapping render (its own photons, its own camera,
// shadow and gather rays) whose disc shrinks from pass to pass as
//     r_{i+1}^2 = r_i^2 (i + alpha) / (i + 1),   alpha in (0, 1),
// and the image is the plain mean of the pass images. The bias of pass i is O(r_i^2) -> 0, the
// variance of pass i grows only as 1 / r_i^2 ~ i^(1 - alpha), so the mean's variance falls as
// i^(-alpha) and its bias as i^(alpha - 1): both vanish. alpha = 2/3 (the default here) is the
// value that balances the two asymptotically (their section 4.3, also Hachisuka's original
// choice).
//
// Our r_1 is not one global radius but the estimator's own disc at each gather point (the
// k-nearest distance, or the mean / variance estimator of density.hpp) on the pass's photons: a
// fixed global r_1 would be far too wide in bright regions and too narrow in dark ones. Pass i
// then keeps the photons of the k-nearest list within sqrt(s_i) r_1, s_i = prod_{j<i} (j + alpha)
// / (j + 1) (RenderOptions::radius_scale2), and divides their filtered power by the shrunk disc's
// area. For a locally uniform density the k - 1 photons inside an exact k-nearest disc are uniform
// in it, so the expected count inside the shrunk disc is (k - 1) s_i and the estimate stays
// unbiased up to the density's variation over the (shrinking) disc, as the scheme requires.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/runtime.hpp"
#include "embree_scene.hpp"
#include "final_gather.hpp"
#include "lights.hpp"
#include "photon_trace.hpp"

namespace bhcl::render {

inline constexpr double kPpmAlpha = 2.0 / 3.0;

// s_i = prod_{j=1}^{i-1} (j + alpha) / (j + 1): pass i's squared-radius scale (pass 1: 1).
// Throws bhcl::Error for pass < 1 or alpha outside (0, 1).
double ppm_radius_scale2(int pass, double alpha);

// The seed of pass i (1-based): pass 1 keeps `base` (a one-pass render is the plain render, bit for
// bit); later passes get a well-mixed distinct seed, so their photons and rays are independent.
std::uint64_t ppm_pass_seed(std::uint64_t base, int pass);

struct ProgressiveOptions {
  int passes = 1;            // at most this many passes (>= 1)
  double time_s = 0;         // > 0: no pass starts once the render has run this long (pass 1 always runs)
  double alpha = kPpmAlpha;  // in (0, 1)
  std::string method;        // the kNN method of the photon maps (make_index)
  MethodOptions index_options;
  std::shared_ptr<Runtime> runtime;
  PhotonTraceOptions photons;  // photons per pass; seed: pass 1's photon seed
};

// What one pass did (on the terminal, in the stats).
struct PassReport {
  int pass = 0;
  double radius_scale2 = 1;  // s_i
  std::size_t photons = 0, caustic_photons = 0;
  double photon_s = 0, build_s = 0, render_s = 0;
  double elapsed_s = 0;  // since the progressive render started, this pass included
  bool rebuilt = false;  // the index was rebuilt in place (BlockHashIndex::rebuild), not built afresh
};

struct ProgressiveResult {
  Image image;          // the mean of the pass images
  int passes = 0;
  RenderStats stats;    // summed over the passes
  double photon_s = 0, build_s = 0, total_s = 0;
  std::vector<PassReport> reports;
};

// Renders passes until opt.passes or opt.time_s, each with its own photons (ppm_pass_seed of
// opt.photons.seed) and rays (of ropt.seed), its index built anew (rebuilt in place where the
// method allows) and its disc shrunk by ppm_radius_scale2. `first` may hold pass 1's photon maps
// already traced with opt.photons (indices not needed); else pass 1 traces them. on_pass is called
// after every pass with the pass's report and the running mean image (progress, periodic EXR).
ProgressiveResult render_progressive(const EmbreeScene& es, const LightSampler& lights, RenderOptions ropt,
                                     const ProgressiveOptions& opt, PhotonMaps* first = nullptr,
                                     const std::function<void(const PassReport&, const Image&)>& on_pass = {});

}  // namespace bhcl::render
