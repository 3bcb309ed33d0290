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
#pragma once

#include <cstdint>
#include <vector>

#include "embree_scene.hpp"
#include "film.hpp"
#include "lights.hpp"
#include "photon_map.hpp"
#include "progress.hpp"

namespace bhcl::render {

struct RenderOptions {
  int width = 512, height = 512;
  int spp = 1;               // camera samples per pixel (jittered)
  int gather = 32;           // M: final-gather rays per visible point
  int shadow_rays = 4;       // light samples per visible point
  SearchParams search;       // global map: k, A (block hashing), max_radius
  int caustic_k = 0;         // caustic map: k (0: search.k)
  float caustic_radius = 0;  // caustic map: maximum radius in scene units (0: 2% of the diagonal)
  int max_specular_depth = 8;
  std::uint64_t seed = 1;
  int threads = 0;           // 0: hardware threads; the image does not depend on it
  std::size_t batch_queries = 262144;  // target gather queries per index call (sets the pass size)
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
  void add_query(const QueryStats& q);
};

struct SurfacePoint {
  Vec3 x, n;                  // position; unit normal on the side the light is gathered from
  Vec3 kd;                    // albedo
  Vec3 weight{1, 1, 1};       // path throughput up to x
  std::uint64_t rng_index = 0;
};

class FinalGatherRenderer {
 public:
  // caustic may be null or empty: then no caustic lookup is made.
  FinalGatherRenderer(const EmbreeScene& scene, const LightSampler& lights, const PhotonMap& global,
                      const PhotonMap* caustic, const RenderOptions& options);

  Image render(RenderStats& stats, Progress* progress = nullptr) const;

  // Outgoing radiance of surface points by the same direct + caustic + final-gather path as the
  // render, in one batch (tests: energy conservation on a furnace scene).
  std::vector<Vec3> shade(const std::vector<SurfacePoint>& points, RenderStats& stats) const;

 private:
  std::vector<Vec3> shade_batch(const std::vector<SurfacePoint>& points, RenderStats& stats) const;

  const EmbreeScene& es_;
  const LightSampler& lights_;
  const PhotonMap& global_;
  const PhotonMap* caustic_;
  RenderOptions opt_;
};

}  // namespace bhcl::render
