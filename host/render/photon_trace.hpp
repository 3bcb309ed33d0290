// Photon tracing with Embree: photons leave the emitters (cosine-distributed), bounce diffusely
// with Russian roulette, reflect/refract at mirrors and glass, and are stored at diffuse hits.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "embree_scene.hpp"
#include "lights.hpp"
#include "photon.hpp"

namespace bhcl::render {

struct PhotonTraceOptions {
  // Photons wanted in the global map. Photons are emitted in fixed chunks (in index order) until
  // the stored count reaches this; the map holds at least this many (up to one chunk more).
  std::size_t photons = 100000;
  int max_depth = 64;          // safety bound; Russian roulette ends paths long before
  std::uint64_t seed = 1;
  int threads = 0;             // 0: hardware threads; results do not depend on it
  std::size_t max_emitted = 0;  // 0: 64 x photons + 1M (then stop: the light cannot reach anything)
};

struct PhotonTraceResult {
  std::vector<PhotonRecord> global;   // every diffuse hit (L {S|D}* D)
  std::vector<PhotonRecord> caustic;  // diffuse hits after specular bounces only (L S+ D)
  std::size_t emitted = 0;
  // Power of one record = record power x power_scale (the emitted power per photon: luminance of
  // the total emitted power / emitted photons).
  float power_scale = 0;
  Vec3 total_power{0, 0, 0};   // emitted by the lights
  Vec3 stored_power{0, 0, 0};  // sum of the global records' powers (float, before half rounding)
  double seconds = 0;
};

// progress(fraction) is called from the calling thread.
PhotonTraceResult trace_photons(const EmbreeScene& scene, const LightSampler& lights,
                                const PhotonTraceOptions& options,
                                const std::function<void(double)>& progress = {});

}  // namespace bhcl::render

#include <memory>

#include "photon_map.hpp"

namespace bhcl::render {

// The photon maps of a scene: the global map, and a caustic map only when the scene has
// specular surfaces (null otherwise). Indexes are not built yet (PhotonMap::build_index).
struct PhotonMaps {
  std::unique_ptr<PhotonMap> global, caustic;
  PhotonTraceResult trace;  // counts and powers; its record vectors are moved into the maps
};
PhotonMaps build_photon_maps(const EmbreeScene& scene, const LightSampler& lights,
                             const PhotonTraceOptions& options,
                             const std::function<void(double)>& progress = {});

}  // namespace bhcl::render
