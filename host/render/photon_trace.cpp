#include "photon_trace.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <thread>

#include "blockhash_cl/error.hpp"
#include "parallel.hpp"
#include "surface_area.hpp"

namespace bhcl::render {
namespace {

constexpr std::uint64_t kPhotonStream = 0x50484F54;  // "PHOT"

struct ChunkOut {
  std::vector<PhotonRecord> global, caustic;
  Vec3 stored{0, 0, 0};
};

// Russian roulette at a specular bounce, on the specular colour's largest channel: false when the
// photon ends there, else its power reweighted (the surviving power never grows).
bool specular_survives(const Vec3& ks, Rng& rng, Vec3& power) {
  float p = std::fmin(1.0f, max_component(ks));
  if (!(p > 0) || rng.uniform() >= p) return false;
  power = power * ks / p;
  return true;
}

void trace_one(const EmbreeScene& es, const LightSampler& lights, const PhotonTraceOptions& opt,
               float inv_lum_power, float separation, std::uint64_t index, ChunkOut& out) {
  const Scene& scene = es.scene();
  const float eps = es.ray_epsilon();
  Rng rng(opt.seed, kPhotonStream, index);
  float u0 = rng.uniform(), u1 = rng.uniform(), u2 = rng.uniform();
  LightSampler::Sample ls = lights.sample(u0, u1, u2);
  Vec3 dir = Frame(ls.normal).to_world(cosine_hemisphere(rng.uniform(), rng.uniform()));
  // Power of the photon if it were the only one: pi Le / pdf_area (cosine emission), made
  // relative to the total emitted luminance so that the stored halves are near 1.
  Vec3 power = ls.emission * (kPi / ls.pdf_area) * inv_lum_power;
  Vec3 org = ls.position + ls.normal * eps;
  bool only_specular = true, had_specular = false;
  // Glass entries minus exits along the path, from the emitter's own medium: > 0 inside glass
  // (photon.hpp, medium_key).
  int glass = es.inside_glass(org) ? 1 : 0;
  for (int depth = 0; depth < opt.max_depth; ++depth) {
    EmbreeScene::Hit hit;
    if (!es.intersect(org, dir, 0.0f, INFINITY, hit)) return;
    const Material& m = scene.material_of(hit.prim);
    Vec3 x = org + dir * hit.t;
    Vec3 ng = scene.geometric_normal(hit.prim);
    bool front = dot(ng, dir) < 0;
    Vec3 n = front ? ng : -ng;  // faces the incoming photon
    if (m.is_diffuse()) {
      PhotonRecord r;
      const Vec3 key = medium_key(x, glass > 0, separation);
      r.position[0] = key.x;
      r.position[1] = key.y;
      r.position[2] = key.z;
      r.set_power(power);
      r.set_direction(-dir);
      r.flags = static_cast<std::uint16_t>(std::min(depth, 255));
      bool caustic = only_specular && had_specular;
      if (caustic) r.flags |= PhotonRecord::kCaustic;
      if (glass > 0) r.flags |= PhotonRecord::kInGlass;
      r.set_surface_class(surface_class(n));  // the boundary-corrected estimate's surface test
      out.global.push_back(r);
      out.stored += power;
      if (caustic) out.caustic.push_back(r);
      // Russian roulette on the albedo's largest channel: the surviving power never grows.
      float p = std::fmin(1.0f, max_component(m.kd));
      if (rng.uniform() >= p) return;
      power = power * m.kd / p;
      dir = Frame(n).to_world(cosine_hemisphere(rng.uniform(), rng.uniform()));
      org = x + n * eps;
      only_specular = false;
    } else if (m.type == MaterialType::Mirror) {
      if (!specular_survives(m.ks, rng, power)) return;
      dir = reflect(dir, n);
      org = x + n * eps;
      had_specular = true;
    } else if (m.type == MaterialType::Glass) {
      if (!specular_survives(m.ks, rng, power)) return;
      // A photon carries flux, which crossing the interface conserves (apart from the Fresnel
      // split, sampled here): the (n_from / n_to)^2 that glass_scatter returns is the change of
      // radiance, i.e. of flux per solid angle, as Snell's law narrows or widens the solid angle;
      // it does not apply to a photon's power.
      (void)glass_scatter(dir, org, x, n, front, m.ior, rng.uniform(), eps);
      if (dot(dir, n) < 0) glass = std::max(0, glass + (front ? 1 : -1));  // refracted: crossed the surface
      had_specular = true;
    } else {
      return;  // black diffuse (e.g. a light without reflectance): absorbed
    }
  }
}

}  // namespace

PhotonTraceResult trace_photons(const EmbreeScene& es, const LightSampler& lights,
                                const PhotonTraceOptions& opt,
                                const std::function<void(double)>& progress) {
  if (opt.photons == 0) throw Error("photon tracing: --photons must be > 0");
  auto t0 = std::chrono::steady_clock::now();
  PhotonTraceResult res;
  res.total_power = lights.total_power();
  const float lum_power = luminance(res.total_power) > 0 ? luminance(res.total_power)
                                                          : max_component(res.total_power);
  const float inv_lum = 1.0f / lum_power;
  const float separation = medium_separation(es.scene().diagonal());
  // The chunk size depends only on the target, so the photon set does not depend on threads.
  const std::size_t chunk = std::clamp<std::size_t>(opt.photons / 16, 64, 4096);
  const std::size_t max_emitted = opt.max_emitted ? opt.max_emitted : 64 * opt.photons + 1000000;
  const int threads = resolve_threads(opt.threads);
  const std::size_t round_chunks = static_cast<std::size_t>(threads) * 8;

  std::size_t next_chunk = 0;
  bool done = false;
  while (!done) {
    std::vector<ChunkOut> outs(round_chunks);
    // One chunk of photons per task; a throw reaches the caller (parallel.hpp).
    parallel_chunks(round_chunks, 1, threads, [&](std::size_t c, std::size_t, std::size_t) {
      std::uint64_t first = static_cast<std::uint64_t>(next_chunk + c) * chunk;
      for (std::uint64_t i = first; i < first + chunk; ++i) trace_one(es, lights, opt, inv_lum, separation, i, outs[c]);
    });
    es.check("photon tracing");
    for (auto& o : outs) {
      res.global.insert(res.global.end(), o.global.begin(), o.global.end());
      res.caustic.insert(res.caustic.end(), o.caustic.begin(), o.caustic.end());
      res.stored_power += o.stored;
      res.emitted += chunk;
      ++next_chunk;
      if (res.global.size() >= opt.photons) {
        done = true;
        break;
      }
      if (res.emitted >= max_emitted)
        throw Error("photon tracing: " + std::to_string(res.emitted) + " photons emitted but only " +
                    std::to_string(res.global.size()) + " stored (of " + std::to_string(opt.photons) +
                    " wanted): the lights reach almost no diffuse surface in scene '" +
                    es.scene().name + "'");
    }
    if (progress) progress(std::min(1.0, static_cast<double>(res.global.size()) / opt.photons));
  }
  res.power_scale = lum_power / static_cast<float>(res.emitted);
  res.stored_power *= res.power_scale;
  res.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

}  // namespace bhcl::render

namespace bhcl::render {

PhotonMaps build_photon_maps(const EmbreeScene& scene, const LightSampler& lights,
                             const PhotonTraceOptions& options,
                             const std::function<void(double)>& progress) {
  PhotonMaps maps;
  maps.trace = trace_photons(scene, lights, options, progress);
  maps.global = std::make_unique<PhotonMap>("global", std::move(maps.trace.global), maps.trace.power_scale);
  maps.trace.global.clear();
  if (scene.scene().has_specular())
    maps.caustic = std::make_unique<PhotonMap>("caustic", std::move(maps.trace.caustic), maps.trace.power_scale);
  maps.trace.caustic.clear();
  return maps;
}

}  // namespace bhcl::render
