// The runs of `bhcl render` (render_runs.cpp): an index per run on the photon maps, its shading,
// the time split and the stats; used by the plain render (cmd_render.cpp) and by --compare
// (cmd_render_compare.cpp).
#pragma once

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/metrics.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "compare.hpp"
#include "density.hpp"
#include "embree_scene.hpp"
#include "final_gather.hpp"
#include "photon_trace.hpp"

namespace bhcl::cli::render_cmd {

using namespace bhcl::render;
using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0);

// --compare-A: positive numbers separated by commas.
std::vector<float> parse_list(const std::string& s);

struct RenderRun {
  std::string label, method;
  float A = 0;
  std::vector<Image> images;  // one per density estimator
  RenderStats stats;
  double build_s = 0, warm_s = 0, total_s = 0;
  Json build, search;  // the parameters the global map's index used, for the stats
  // --compare: the talk's measures (false negatives, max and mean dilation) of the global map's
  // k-nearest lists on a sample of the frame's gather queries, against the exact run's lists.
  bool has_lists_accuracy = false;
  Accuracy lists_accuracy;
};

std::string format_g(double v);
// "kth-cone": the estimator in file names.
std::string estimator_tag(const DensityEstimator& e);
// --estimator and --filter: one each, or (with --compare) comma lists whose every pair is shaded.
std::vector<DensityEstimator> parse_estimators(const Args& args, bool lists);
// Builds the index of `method` on the (shared) photon maps and compiles its kernels, so that the
// query time excludes first-launch compiles.
RenderRun start_run(const std::string& label, const std::string& method, float A, PhotonMaps& maps,
                    const std::shared_ptr<Runtime>& rt, const MethodOptions& mopt, RenderOptions ropt);
// Shades a traced frame with the maps' current indices (start_run), once per estimator.
void shade_run(RenderRun& run, const TracedFrame& frame, const std::vector<DensityEstimator>& ests,
               const PhotonMaps& maps, const EmbreeScene& es, const LightSampler& lights, RenderOptions ropt,
               bool quiet);
// Traces and shades pass by pass (one pass in memory): the plain render.
RenderRun render_with(const std::string& label, const std::string& method, float A, PhotonMaps& maps,
                      const std::shared_ptr<Runtime>& rt, const MethodOptions& mopt,
                      const EmbreeScene& es, const LightSampler& lights, RenderOptions ropt,
                      bool quiet);
// The ray counts of a frame traced once, for the skip report of every run that shaded it.
void add_trace_counts(RenderStats& s, const RenderStats& t);
// What the render did not do, because the scene did not need it (item by item).
void print_skipped(const RenderRun& r, const PhotonMaps& maps);
void print_split(const char* title, const RenderRun& r, double photon_s);
Json run_json(const RenderRun& r, const ImageDiff* d);
// The scene and render settings every stats file of `bhcl render` carries.
// --reference (with --reference-block): the reference image, checked to be the render's size;
// empty without --reference.
Image read_reference(const Args& args, const RenderOptions& ropt);
Json render_header(const Runtime& rt, const Args& args, const std::string& scene, const RenderOptions& ropt,
                   const PhotonMaps& maps, std::size_t photons_requested);

// What run_render has set up before it renders: options, scene, photon maps, device.
struct RenderSetup {
  const Args& args;
  Clock::time_point t_start;
  bool quiet;
  std::string out, base;
  RenderOptions& ropt;
  const std::vector<DensityEstimator>& ests;
  const MethodOptions& mopt;
  const Scene& scene;
  EmbreeScene& es;
  LightSampler& lights;
  PhotonTraceOptions& popt;
  PhotonMaps& maps;
  double photon_s;
  std::shared_ptr<Runtime> rt;
  std::string device;
  double exposure_opt;
};
// bhcl render --compare (cmd_render_compare.cpp).
int run_compare(const RenderSetup& s);
// bhcl render --passes N / --time S (cmd_render_progressive.cpp): s.maps are pass 1's photons.
int run_progressive(const RenderSetup& s);

}  // namespace bhcl::cli::render_cmd
