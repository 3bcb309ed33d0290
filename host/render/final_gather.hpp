// The renderer: camera rays (Embree packets of 16), direct light by shadow rays to the area
// lights, caustics from the caustic map looked up directly, and indirect diffuse light by final
// gather. The gather hit points of a pass (a band of image rows) are collected into one array and
// answered by ONE batched kNN call on the global photon map.
//
// Per visible diffuse point x (normal n towards the viewer, albedo kd, path throughput b):
//   L = b * [ direct(x) + caustic(x) + (1/M) sum_j L_map(y_j) * kd ]
// where the M gather rays are cosine-distributed (so BRDF x cos / pdf = kd), y_j is the first
// diffuse point the j-th ray reaches (through mirrors and glass), and L_map is the photon map's
// radiance estimate (photon_map.hpp). Gather rays that leave the scene, or end on an emitter or a
// black surface, issue no query: emitters are direct light, already counted by the shadow rays;
// paths emitter -> specular -> x are caustics, counted by the caustic map. Pixels that see
// nothing, or only an emitter, get no gather at all.
//
// Tracing and shading are apart: trace() follows the camera, shadow and gather rays of every pass
// once (a TracedFrame: nothing in it depends on the photon maps' index), and shade() answers its
// queries with whatever index the maps hold now and shades the frame once per density estimator.
// So a comparison of methods, A values and estimators traces the rays once; render() does both
// pass by pass and keeps only one pass in memory.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "embree_scene.hpp"
#include "film.hpp"
#include "lights.hpp"
#include "photon_map.hpp"
#include "progress.hpp"
#include "surface_area.hpp"

namespace bhcl::render {

struct RenderOptions {
  int width = 512, height = 512;
  int spp = 1;               // camera samples per pixel (jittered)
  int gather = 32;           // M: final-gather rays per visible point
  int shadow_rays = 4;       // light samples per visible point
  SearchParams search;       // global map: k, A (block hashing), max_radius
  DensityEstimator estimator;  // render() and shade(points): the disc and filter of the estimates
  int caustic_k = 0;         // caustic map: k (0: search.k)
  float caustic_radius = 0;  // caustic map: maximum radius in scene units (0: 2% of the diagonal)
  // Specular vertices a camera or gather chain may have before it ends (its light then lost). As
  // deep as the path tracer's paths (PathTraceOptions::max_depth): a ray that enters the glass
  // block through a side face at a grazing angle is trapped by total internal reflection and
  // circles the block 10 to 20 times before it reaches the floor inside; 8 cut those chains off
  // and the block's right face came out 3x too dark (issue 24).
  int max_specular_depth = 64;
  std::uint64_t seed = 1;
  int threads = 0;           // 0: hardware threads; the image does not depend on it
  std::size_t batch_queries = 262144;  // target gather queries per index call (sets the pass size)
  // A progressive pass (progressive.hpp): every estimate's disc shrunk to this times the
  // estimator's squared radius (global and caustic map). 1: the plain render.
  float radius_scale2 = 1.0f;
  // Shading with one estimator: the density estimate inside the query (PhotonMap::estimate): only
  // 16 bytes per query come back instead of the k-nearest lists (8 k + 4). Equal to the lists' path
  // up to float rounding, not bit for bit: off by default, so that shade() with several estimators
  // (which needs the lists) and render() agree exactly; bhcl render turns it on.
  bool fused_estimate = false;
  // The boundary correction (surface_area.hpp): every estimate counts only the photons on its
  // gather point's surface and divides by the filter's integral over the part of its disc on that
  // surface, not over the whole disc. Off here (a struct default that hand-made photon maps of the
  // tests need: their records carry no surface class); bhcl render's --boundary chooses.
  bool boundary_correction = false;
  // Its surface rasters, shared by the passes of a progressive render; built by the renderer when
  // null and the correction is on.
  std::shared_ptr<const SurfaceAreaMap> surface_areas;
};

struct RenderStats {
  std::size_t pixels = 0, camera_rays = 0, visible_points = 0, shadow_rays = 0;
  std::size_t gather_rays = 0, gather_escaped = 0, gather_no_query = 0;
  std::size_t queries = 0, caustic_queries = 0, index_calls = 0, passes = 0;
  double trace_s = 0;         // Embree: camera, shadow and gather rays, building the batches
  double query_s = 0;         // the batched index calls, wall clock
  double query_kernel_s = 0;  // of which kernel execution (device event times)
  double compile_s = 0;       // kernel compiles during the calls (first launches)
  double shade_s = 0;         // radiance estimates and film
  std::size_t result_bytes = 0;  // device -> host bytes of the query results (lists or estimates)
  void add_query(const QueryStats& q);
};

// One gather query of a traced pass: the diffuse surface it ended on (triangle, and in the top bit
// whether the ray arrived on its back side) and the throughput to the pixel.
// prim_side also says (bit 30) whether the point is inside glass (its position medium-keyed).
struct GatherQuery {
  static constexpr std::uint32_t kBack = 0x80000000u, kInGlass = 0x40000000u, kPrim = 0x3FFFFFFFu;
  std::uint32_t prim_side = 0;
  Vec3 weight;
};

// The rays of one pass (image rows [y0, y1)), traced: every sample slot's emitted radiance seen
// through mirrors and glass; every visible diffuse point's slot, direct light, surface and gather
// queries (rows q_begin[i] .. q_begin[i + 1] of the gather arrays).
struct TracedPass {
  int y0 = 0, y1 = 0;
  std::vector<Vec3> emitted;                // per sample slot
  std::vector<std::uint32_t> vis_slot;      // per visible point
  std::vector<Vec3> direct;                 // per visible point, weighted
  std::vector<float> vis_xyz;               // 3 per visible point: the caustic queries
  std::vector<Vec3> vis_n, vis_kd, vis_weight;
  std::vector<std::uint32_t> vis_prim;      // per visible point, as GatherQuery::prim_side (kPrim: none)
  std::vector<std::size_t> q_begin;         // visible points + 1
  std::vector<float> gather_xyz;            // 3 per gather query
  std::vector<GatherQuery> gather;
  std::size_t bytes() const;
};

// Every pass of an image, with the settings that made it (shade() refuses a frame traced with
// other image, sampling or seed settings).
struct TracedFrame {
  int width = 0, height = 0, spp = 0, gather = 0, shadow_rays = 0, max_specular_depth = 0;
  std::uint64_t seed = 0;
  const void* scene = nullptr;
  std::vector<TracedPass> passes;
  std::size_t bytes() const;
};

struct SurfacePoint {
  Vec3 x, n;                  // position; unit normal on the side the light is gathered from
  Vec3 kd;                    // albedo
  Vec3 weight{1, 1, 1};       // path throughput up to x
  bool in_glass = false;      // x lies inside glass (its queries are keyed by medium_key)
  std::uint32_t prim = GatherQuery::kPrim;  // its triangle (kPrim: not known: no boundary correction)
  bool back = false;          // n is the triangle's back side
  std::uint64_t rng_index = 0;
};

// One bounce off the specular surface `hit` of the ray (org, dir): a mirror reflects; glass reflects
// or refracts with the Fresnel probabilities, so that the weight stays ks, times (n_from / n_to)^2
// on refraction (radiance, see glass_scatter). Updates org, dir and beta; false when beta became
// black. Camera, gather and path-traced rays all bounce through it. glass_depth (when given) counts
// glass entered minus left: +1 on a refraction into glass, -1 out of it (never below 0).
bool specular_bounce(const EmbreeScene& es, Rng& rng, Vec3& org, Vec3& dir, const EmbreeScene::Hit& hit,
                     Vec3& beta, int* glass_depth = nullptr);

class FinalGatherRenderer {
 public:
  // caustic may be null or empty: then no caustic lookup is made.
  FinalGatherRenderer(const EmbreeScene& scene, const LightSampler& lights, const PhotonMap& global,
                      const PhotonMap* caustic, const RenderOptions& options);

  // Trace and shade pass by pass with options.estimator.
  Image render(RenderStats& stats, Progress* progress = nullptr) const;

  // The rays of every pass (stats: trace_s and the ray counts).
  TracedFrame trace(RenderStats& stats, Progress* progress = nullptr) const;
  // One image per estimator, in order, from a frame this renderer's settings traced (else throws):
  // the queries answered by the maps' current indices (stats: query and shade times). Equal to
  // render() for each estimator, bit for bit.
  std::vector<Image> shade(const TracedFrame& frame, const std::vector<DensityEstimator>& estimators,
                           RenderStats& stats, Progress* progress = nullptr) const;

  // Outgoing radiance of surface points by the same direct + caustic + final-gather path as the
  // render, in one batch (tests: energy conservation on a furnace scene).
  std::vector<Vec3> shade(const std::vector<SurfacePoint>& points, RenderStats& stats) const;

 private:
  int rows_per_pass() const;
  TracedPass trace_pass(int y0, int y1, RenderStats& stats) const;
  // Stage A for visible points: direct light and gather rays, appended to `pass` (slot i of the
  // points is slots[i]).
  void trace_points(const std::vector<SurfacePoint>& points, const std::vector<std::uint32_t>& slots,
                    TracedPass& pass, RenderStats& stats) const;
  // The queries of a pass and its radiance per slot, once per estimator: out[e][slot]. The kNN
  // results land in `scratch`, kept by the caller from pass to pass: their arrays (8 k bytes per
  // query) are then allocated once per image, not once per pass.
  struct QueryScratch {
    KnnResult global, caustic;
    DensityResult global_est, caustic_est;  // RenderOptions::fused_estimate
    std::vector<float> normals, caustic_normals;
  };
  // The boundary correction's factor of one estimate (1 when it is off).
  float boundary_factor(std::uint32_t prim_side, const float* key, float r2, const DensityEstimator& est) const;
  void shade_pass(const TracedPass& pass, std::size_t slots, const std::vector<DensityEstimator>& estimators,
                  std::vector<std::vector<Vec3>>& out, RenderStats& stats, QueryScratch& scratch) const;
  void film(const TracedPass& pass, const std::vector<Vec3>& radiance, Image& img, RenderStats& stats) const;

  const EmbreeScene& es_;
  const LightSampler& lights_;
  const PhotonMap& global_;
  const PhotonMap* caustic_;
  RenderOptions opt_;
};

}  // namespace bhcl::render
