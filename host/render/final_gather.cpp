#include "final_gather.hpp"

#include <chrono>
#include <cmath>

#include "blockhash_cl/error.hpp"
#include "parallel.hpp"

namespace bhcl::render {
namespace {

constexpr std::uint64_t kCameraStream = 0x43414D;  // "CAM"
constexpr std::uint64_t kGatherStream = 0x474154;  // "GAT"

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// One gather query: where, the surface there, and what its radiance is worth to the pixel.
struct GatherQuery {
  Vec3 n, kd, weight;
};

// One bounce off the specular surface `hit` (mirror, or glass with the Fresnel probabilities so
// that the weight stays ks, times (n_from / n_to)^2 on refraction: see glass_scatter). Updates
// org, dir and beta; false when beta became black.
bool specular_bounce(const EmbreeScene& es, Rng& rng, Vec3& org, Vec3& dir,
                     const EmbreeScene::Hit& hit, Vec3& beta) {
  const Scene& scene = es.scene();
  const float eps = es.ray_epsilon();
  const Material& m = scene.material_of(hit.prim);
  Vec3 x = org + dir * hit.t;
  Vec3 ng = scene.geometric_normal(hit.prim);
  bool front = dot(ng, dir) < 0;
  Vec3 n = front ? ng : -ng;
  beta *= m.ks;
  if (m.type == MaterialType::Mirror) {
    dir = reflect(dir, n);
    org = x + n * eps;
  } else {
    // Camera and gather paths carry radiance: scaled by (n_from / n_to)^2 when refracted.
    beta *= glass_scatter(dir, org, x, n, front, m.ior, rng.uniform(), eps);
  }
  return !is_black(beta);
}

// Follows a ray through mirrors and glass to the first non-specular surface. Returns false when
// the ray leaves the scene or the depth runs out; else `hit` is that surface, `beta` the
// specular throughput, org/dir the last ray.
bool follow_specular(const EmbreeScene& es, Rng& rng, Vec3& org, Vec3& dir, EmbreeScene::Hit& hit,
                     Vec3& beta, int max_depth) {
  for (int depth = 0;; ++depth) {
    if (!es.scene().material_of(hit.prim).is_specular()) return true;
    if (depth >= max_depth) return false;
    if (!specular_bounce(es, rng, org, dir, hit, beta)) return false;
    if (!es.intersect(org, dir, 0.0f, INFINITY, hit)) return false;
  }
}

}  // namespace

void RenderStats::add_query(const QueryStats& q) {
  query_kernel_s += q.query_s;
  compile_s += q.compile_s;
  ++index_calls;
}

FinalGatherRenderer::FinalGatherRenderer(const EmbreeScene& scene, const LightSampler& lights,
                                         const PhotonMap& global, const PhotonMap* caustic,
                                         const RenderOptions& options)
    : es_(scene), lights_(lights), global_(global), caustic_(caustic), opt_(options) {
  if (opt_.width <= 0 || opt_.height <= 0) throw Error("render: image size must be positive");
  if (opt_.spp < 1) throw Error("render: --spp must be >= 1");
  if (opt_.gather < 0) throw Error("render: --gather must be >= 0");
  if (opt_.shadow_rays < 1) throw Error("render: --shadow-rays must be >= 1");
  if (!global_.index() && !global_.empty()) throw Error("render: the global photon map has no index");
  if (caustic_ && caustic_->empty()) caustic_ = nullptr;
  if (caustic_ && !caustic_->index()) throw Error("render: the caustic photon map has no index");
  if (opt_.caustic_k <= 0) opt_.caustic_k = opt_.search.k;
  if (!(opt_.caustic_radius > 0)) opt_.caustic_radius = 0.02f * es_.scene().diagonal();
  if (opt_.batch_queries == 0) opt_.batch_queries = 262144;
}

std::vector<Vec3> FinalGatherRenderer::shade(const std::vector<SurfacePoint>& points,
                                             RenderStats& stats) const {
  return shade_batch(points, stats);
}

std::vector<Vec3> FinalGatherRenderer::shade_batch(const std::vector<SurfacePoint>& pts,
                                                   RenderStats& stats) const {
  const Scene& scene = es_.scene();
  const float eps = es_.ray_epsilon();
  const int M = opt_.gather, S = opt_.shadow_rays;
  const std::size_t n = pts.size();
  std::vector<Vec3> out(n, Vec3{0, 0, 0});
  if (n == 0) return out;

  // Stage A: direct light and gather rays, per fixed chunk of points (outputs concatenated in
  // chunk order, so the query order and the image do not depend on threads).
  auto t0 = Clock::now();
  constexpr std::size_t kChunk = 64;
  const std::size_t chunks = (n + kChunk - 1) / kChunk;
  struct ChunkOut {
    std::vector<float> xyz;
    std::vector<GatherQuery> q;
    std::size_t shadow = 0, gather = 0, escaped = 0, no_query = 0;
  };
  std::vector<ChunkOut> co(chunks);
  std::vector<std::uint32_t> q_count(n, 0);  // gather queries of each point
  parallel_chunks(n, kChunk, opt_.threads, [&](std::size_t c, std::size_t b, std::size_t e) {
    ChunkOut& o = co[c];
    std::vector<RTCRay> shadow(static_cast<std::size_t>(S));
    std::vector<Vec3> contrib(static_cast<std::size_t>(S));
    std::vector<RTCRayHit> rays(static_cast<std::size_t>(M));
    for (std::size_t i = b; i < e; ++i) {
      const SurfacePoint& p = pts[i];
      Rng rng(opt_.seed, kGatherStream, p.rng_index);
      const Vec3 org = p.x + p.n * eps;
      // Direct light: S shadow rays to points on the emitters, one stream.
      for (int s = 0; s < S; ++s) {
        float u0 = rng.uniform(), u1 = rng.uniform(), u2 = rng.uniform();
        LightSampler::Sample ls = lights_.sample(u0, u1, u2);
        Vec3 wi = ls.position - p.x;
        float d2 = dot(wi, wi), d = std::sqrt(d2);
        wi = wi / d;
        float cos_x = dot(p.n, wi), cos_l = -dot(ls.normal, wi);
        contrib[s] = {0, 0, 0};
        if (cos_x > 0 && cos_l > 0 && d > 2 * eps) {
          contrib[s] = ls.emission * (cos_x * cos_l / (d2 * ls.pdf_area));
          set_shadow_ray(shadow[s], org, wi, 0.0f, d - 2 * eps);
        } else {
          set_shadow_ray(shadow[s], org, Vec3{0, 0, 1}, 0.0f, -1.0f);  // tfar < tnear: inactive
        }
      }
      es_.occluded_stream(shadow.data(), shadow.size());
      o.shadow += static_cast<std::size_t>(S);
      Vec3 direct{0, 0, 0};
      for (int s = 0; s < S; ++s)
        if (shadow[s].tfar >= 0) direct += contrib[s];  // Embree sets tfar = -inf when occluded
      out[i] = p.weight * p.kd * direct * (1.0f / (kPi * S));

      // Final gather: M cosine-distributed rays, one incoherent stream.
      if (M == 0) continue;
      Frame frame(p.n);
      for (int j = 0; j < M; ++j) {
        Vec3 d = frame.to_world(cosine_hemisphere(rng.uniform(), rng.uniform()));
        set_ray(rays[j], org, d, 0.0f, INFINITY);
      }
      es_.intersect_stream(rays.data(), rays.size(), false);
      o.gather += static_cast<std::size_t>(M);
      const Vec3 w0 = p.weight * p.kd * (1.0f / M);
      for (int j = 0; j < M; ++j) {
        const RTCRayHit& r = rays[j];
        if (r.hit.geomID == RTC_INVALID_GEOMETRY_ID) {
          ++o.escaped;
          continue;
        }
        EmbreeScene::Hit hit{r.ray.tfar, r.hit.primID};
        Vec3 ro = org, rd{r.ray.dir_x, r.ray.dir_y, r.ray.dir_z}, beta{1, 1, 1};
        if (!follow_specular(es_, rng, ro, rd, hit, beta, opt_.max_specular_depth)) {
          ++o.escaped;
          continue;
        }
        const Material& m = scene.material_of(hit.prim);
        if (!m.is_diffuse()) {  // an emitter or a black surface: nothing for the map to add
          ++o.no_query;
          continue;
        }
        Vec3 y = ro + rd * hit.t;
        Vec3 ng = scene.geometric_normal(hit.prim);
        o.xyz.insert(o.xyz.end(), {y.x, y.y, y.z});
        o.q.push_back({dot(ng, rd) < 0 ? ng : -ng, m.kd, w0 * beta});
        ++q_count[i];
      }
    }
  });
  es_.check("final gather");
  std::vector<float> xyz;
  std::vector<GatherQuery> queries;
  {
    std::size_t total = 0;
    for (const auto& o : co) total += o.q.size();
    xyz.reserve(3 * total);
    queries.reserve(total);
    for (auto& o : co) {
      xyz.insert(xyz.end(), o.xyz.begin(), o.xyz.end());
      queries.insert(queries.end(), o.q.begin(), o.q.end());
      stats.shadow_rays += o.shadow;
      stats.gather_rays += o.gather;
      stats.gather_escaped += o.escaped;
      stats.gather_no_query += o.no_query;
      o = ChunkOut{};
    }
  }
  std::vector<std::size_t> q_begin(n + 1, 0);
  for (std::size_t i = 0; i < n; ++i) q_begin[i + 1] = q_begin[i] + q_count[i];
  stats.trace_s += since(t0);

  // The batched kNN calls: all gather points of the batch in one call; the caustic map is looked
  // up directly at the visible points, also in one call.
  t0 = Clock::now();
  KnnResult gres, cres;
  if (!queries.empty() && !global_.empty()) {
    stats.add_query(global_.query(xyz.data(), queries.size(), opt_.search, gres));
    stats.queries += queries.size();
  }
  SearchParams cparams = opt_.search;
  cparams.k = opt_.caustic_k;
  cparams.max_radius = opt_.caustic_radius;
  if (caustic_) {
    std::vector<float> cxyz(3 * n);
    for (std::size_t i = 0; i < n; ++i) {
      cxyz[3 * i] = pts[i].x.x;
      cxyz[3 * i + 1] = pts[i].x.y;
      cxyz[3 * i + 2] = pts[i].x.z;
    }
    stats.add_query(caustic_->query(cxyz.data(), n, cparams, cres));
    stats.caustic_queries += n;
  }
  stats.query_s += since(t0);

  // Stage B: radiance estimates, summed per point in a fixed order.
  t0 = Clock::now();
  const bool have_global = !queries.empty() && !global_.empty();
  parallel_chunks(n, 256, opt_.threads, [&](std::size_t, std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      Vec3 indirect{0, 0, 0};
      if (have_global)
        for (std::size_t q = q_begin[i]; q < q_begin[i + 1]; ++q)
          indirect += queries[q].weight *
                      global_.radiance(gres, q, queries[q].n, queries[q].kd, opt_.search.max_radius);
      Vec3 caustic{0, 0, 0};
      if (caustic_) caustic = pts[i].weight * caustic_->radiance(cres, i, pts[i].n, pts[i].kd, cparams.max_radius);
      out[i] += indirect + caustic;
    }
  });
  stats.shade_s += since(t0);
  return out;
}

Image FinalGatherRenderer::render(RenderStats& stats, Progress* progress) const {
  const Scene& scene = es_.scene();
  const int W = opt_.width, H = opt_.height, spp = opt_.spp;
  const PinholeCamera cam(scene.camera, W, H);
  Image img(W, H);
  stats.pixels += img.pixels();
  const std::size_t per_row = static_cast<std::size_t>(W) * spp * std::max(1, opt_.gather);
  const int rows_per_pass = static_cast<int>(std::clamp<std::size_t>(opt_.batch_queries / per_row, 1, H));

  for (int y0 = 0; y0 < H; y0 += rows_per_pass) {
    const int y1 = std::min(H, y0 + rows_per_pass);
    const std::size_t slot0 = static_cast<std::size_t>(y0) * W * spp;
    const std::size_t nslots = static_cast<std::size_t>(y1 - y0) * W * spp;
    std::vector<Vec3> radiance(nslots, Vec3{0, 0, 0});

    // Camera rays in packets of 16 consecutive samples; specular chains followed one by one.
    auto t0 = Clock::now();
    constexpr std::size_t kChunk = 64;
    const std::size_t chunks = (nslots + kChunk - 1) / kChunk;
    std::vector<std::vector<SurfacePoint>> vis_chunks(chunks);
    std::vector<std::vector<std::uint32_t>> vis_slot_chunks(chunks);
    parallel_chunks(nslots, kChunk, opt_.threads, [&](std::size_t c, std::size_t b, std::size_t e) {
      for (std::size_t p0 = b; p0 < e; p0 += 16) {
        alignas(64) RTCRayHit16 packet;
        alignas(64) int valid[16];
        std::vector<Rng> rngs;
        rngs.reserve(16);
        const Vec3 o = cam.origin();
        for (int l = 0; l < 16; ++l) {
          std::size_t s = p0 + l;
          valid[l] = s < e ? -1 : 0;
          std::size_t gs = slot0 + std::min(s, e - 1);  // global sample index: pixel * spp + sample
          rngs.emplace_back(opt_.seed, kCameraStream, gs);
          std::size_t pixel = gs / spp;
          float px = static_cast<float>(pixel % W) + rngs[l].uniform();
          float py = static_cast<float>(pixel / W) + rngs[l].uniform();
          Vec3 d = cam.direction(px, py);
          packet.ray.org_x[l] = o.x;
          packet.ray.org_y[l] = o.y;
          packet.ray.org_z[l] = o.z;
          packet.ray.dir_x[l] = d.x;
          packet.ray.dir_y[l] = d.y;
          packet.ray.dir_z[l] = d.z;
          packet.ray.tnear[l] = 0.0f;
          packet.ray.tfar[l] = INFINITY;
          packet.ray.time[l] = 0.0f;
          packet.ray.mask[l] = 0xFFFFFFFFu;
          packet.ray.id[l] = static_cast<unsigned>(l);
          packet.ray.flags[l] = 0;
          packet.hit.geomID[l] = RTC_INVALID_GEOMETRY_ID;
          packet.hit.instID[0][l] = RTC_INVALID_GEOMETRY_ID;
        }
        es_.intersect16(valid, packet);
        for (int l = 0; l < 16 && p0 + l < e; ++l) {
          if (packet.hit.geomID[l] == RTC_INVALID_GEOMETRY_ID) continue;  // sees nothing
          const std::size_t s = p0 + l;
          Vec3 org = o, dir{packet.ray.dir_x[l], packet.ray.dir_y[l], packet.ray.dir_z[l]};
          EmbreeScene::Hit hit{packet.ray.tfar[l], packet.hit.primID[l]};
          Vec3 beta{1, 1, 1};
          Rng& rng = rngs[l];
          // Emitters seen directly or through mirrors/glass; the chain stops at a diffuse surface.
          for (int depth = 0;; ++depth) {
            const Material& m = scene.material_of(hit.prim);
            Vec3 ng = scene.geometric_normal(hit.prim);
            bool front = dot(ng, dir) < 0;
            if (m.is_light() && front) radiance[s] += beta * m.emission;
            if (!m.is_specular()) {
              if (m.is_diffuse()) {
                SurfacePoint sp;
                sp.x = org + dir * hit.t;
                sp.n = front ? ng : -ng;
                sp.kd = m.kd;
                sp.weight = beta;
                sp.rng_index = slot0 + s;
                vis_chunks[c].push_back(sp);
                vis_slot_chunks[c].push_back(static_cast<std::uint32_t>(s));
              }
              break;
            }
            if (depth >= opt_.max_specular_depth) break;
            if (!specular_bounce(es_, rng, org, dir, hit, beta)) break;
            if (!es_.intersect(org, dir, 0.0f, INFINITY, hit)) break;
          }
        }
      }
    });
    es_.check("camera rays");
    std::vector<SurfacePoint> vis;
    std::vector<std::uint32_t> vis_slot;
    for (std::size_t c = 0; c < chunks; ++c) {
      vis.insert(vis.end(), vis_chunks[c].begin(), vis_chunks[c].end());
      vis_slot.insert(vis_slot.end(), vis_slot_chunks[c].begin(), vis_slot_chunks[c].end());
    }
    stats.camera_rays += nslots;
    stats.visible_points += vis.size();
    stats.trace_s += since(t0);

    std::vector<Vec3> shaded = shade_batch(vis, stats);

    t0 = Clock::now();
    for (std::size_t i = 0; i < vis.size(); ++i) radiance[vis_slot[i]] += shaded[i];
    for (int y = y0; y < y1; ++y)
      for (int x = 0; x < W; ++x) {
        Vec3 sum{0, 0, 0};
        std::size_t base = (static_cast<std::size_t>(y - y0) * W + x) * spp;
        for (int s = 0; s < spp; ++s) sum += radiance[base + s];
        img.set(static_cast<std::size_t>(y) * W + x, sum * (1.0f / spp));
      }
    stats.shade_s += since(t0);
    ++stats.passes;
    if (progress) progress->update(static_cast<double>(y1) / H);
  }
  return img;
}

}  // namespace bhcl::render
