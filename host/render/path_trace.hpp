// A reference renderer with no photon map: unidirectional path tracing with next-event estimation
// (one shadow ray to the emitters at every diffuse vertex), Russian roulette, mirrors and glass by
// the same specular bounce as the photon renderer. It converges to the scene's true radiance, so
// it is the independent answer the photon map's density estimators are measured against (on
// scenes where light reaches diffuse surfaces by diffuse paths: caustics converge slowly).
//
// Emission is counted where a path arrives on an emitter's front side from the camera or a
// specular bounce; after a diffuse bounce the shadow ray has already counted it.
#pragma once

#include <cstdint>

#include "embree_scene.hpp"
#include "film.hpp"
#include "lights.hpp"
#include "progress.hpp"

namespace bhcl::render {

struct PathTraceOptions {
  int width = 256, height = 256;
  int spp = 64;             // paths per pixel (jittered)
  int max_depth = 64;       // vertices; Russian roulette ends paths long before
  int min_depth = 3;        // vertices before Russian roulette
  std::uint64_t seed = 1;
  int threads = 0;          // 0: hardware threads; the image does not depend on it
  // Only the pixels x0 <= x < x1, y0 <= y < y1 are traced (the others stay 0); x1, y1 <= 0: to
  // the image's edge. For refining a reference where its paths are rare (light reaching a surface
  // only through glass, seen in a mirror) at many more samples than the whole image can afford.
  int window_x0 = 0, window_y0 = 0, window_x1 = 0, window_y1 = 0;
};

struct PathTraceStats {
  std::size_t paths = 0, vertices = 0, shadow_rays = 0;
  double seconds = 0;
};

// Throws bhcl::Error on a bad option or an Embree error.
Image path_trace(const EmbreeScene& scene, const LightSampler& lights, const PathTraceOptions& options,
                 PathTraceStats& stats, Progress* progress = nullptr);

}  // namespace bhcl::render
