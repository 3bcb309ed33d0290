#include "final_gather.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <tuple>

#include "blockhash_cl/error.hpp"
#include "parallel.hpp"

namespace bhcl::render {
namespace {

constexpr std::uint64_t kCameraStream = 0x43414D;  // "CAM"
constexpr std::uint64_t kGatherStream = 0x474154;  // "GAT"

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

constexpr std::uint32_t kBackSide = 0x80000000u;  // GatherQuery::prim_side: arrived on the back

template <typename T>
std::size_t vec_bytes(const std::vector<T>& v) {
  return v.capacity() * sizeof(T);
}

// Follows a ray through mirrors and glass to the first non-specular surface. Returns false when
// the ray leaves the scene or the depth runs out; else `hit` is that surface, `beta` the
// specular throughput, org/dir the last ray.
bool follow_specular(const EmbreeScene& es, Rng& rng, Vec3& org, Vec3& dir, EmbreeScene::Hit& hit,
                     Vec3& beta, int max_depth, int& glass_depth) {
  for (int depth = 0;; ++depth) {
    if (!es.scene().material_of(hit.prim).is_specular()) return true;
    if (depth >= max_depth) return false;
    if (!specular_bounce(es, rng, org, dir, hit, beta, &glass_depth)) return false;
    if (!es.intersect(org, dir, 0.0f, INFINITY, hit)) return false;
  }
}

}  // namespace

bool specular_bounce(const EmbreeScene& es, Rng& rng, Vec3& org, Vec3& dir,
                     const EmbreeScene::Hit& hit, Vec3& beta, int* glass_depth) {
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
    if (glass_depth && dot(dir, n) < 0) *glass_depth = std::max(0, *glass_depth + (front ? 1 : -1));
  }
  return !is_black(beta);
}

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
  if (!(opt_.radius_scale2 > 0) || !(opt_.radius_scale2 <= 1))
    throw Error("render: the progressive radius scale must be in (0, 1], got " + std::to_string(opt_.radius_scale2));
}

std::size_t TracedPass::bytes() const {
  return vec_bytes(emitted) + vec_bytes(vis_slot) + vec_bytes(direct) + vec_bytes(vis_xyz) + vec_bytes(vis_n) +
         vec_bytes(vis_kd) + vec_bytes(vis_weight) + vec_bytes(q_begin) + vec_bytes(gather_xyz) + vec_bytes(gather);
}

std::size_t TracedFrame::bytes() const {
  std::size_t b = 0;
  for (const auto& p : passes) b += p.bytes();
  return b;
}

std::vector<Vec3> FinalGatherRenderer::shade(const std::vector<SurfacePoint>& points,
                                             RenderStats& stats) const {
  TracedPass pass;
  pass.emitted.assign(points.size(), Vec3{0, 0, 0});
  std::vector<std::uint32_t> slots(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) slots[i] = static_cast<std::uint32_t>(i);
  trace_points(points, slots, pass, stats);
  std::vector<std::vector<Vec3>> out;
  QueryScratch scratch;
  shade_pass(pass, points.size(), {opt_.estimator}, out, stats, scratch);
  return std::move(out[0]);
}

namespace {

// Each visible point's caustic query key, normal, albedo and weight.
void fill_visible_points(const std::vector<SurfacePoint>& pts, float separation, TracedPass& pass) {
  const std::size_t n = pts.size();
  pass.vis_xyz.resize(3 * n);
  pass.vis_n.resize(n);
  pass.vis_kd.resize(n);
  pass.vis_weight.resize(n);
  for (std::size_t i = 0; i < n; ++i) {
    const Vec3 key = medium_key(pts[i].x, pts[i].in_glass, separation);  // the caustic query
    pass.vis_xyz[3 * i] = key.x;
    pass.vis_xyz[3 * i + 1] = key.y;
    pass.vis_xyz[3 * i + 2] = key.z;
    pass.vis_n[i] = pts[i].n;
    pass.vis_kd[i] = pts[i].kd;
    pass.vis_weight[i] = pts[i].weight;
  }
}

// The gather queries and ray counts of one fixed chunk of visible points.
struct GatherChunk {
  std::vector<float> xyz;
  std::vector<GatherQuery> q;
  std::size_t shadow = 0, gather = 0, escaped = 0, no_query = 0;
};

// Direct light at p: shadow.size() shadow rays to points on the emitters, one stream; the sum of
// the unoccluded emitters' contributions (`contrib`: the caller's scratch, one per ray).
Vec3 direct_light(const EmbreeScene& es, const LightSampler& lights, const SurfacePoint& p, Vec3 org, Rng& rng,
                  std::vector<RTCRay>& shadow, std::vector<Vec3>& contrib) {
  const float eps = es.ray_epsilon();
  for (std::size_t s = 0; s < shadow.size(); ++s) {
    float u0 = rng.uniform(), u1 = rng.uniform(), u2 = rng.uniform();
    LightSampler::Sample ls = lights.sample(u0, u1, u2);
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
  es.occluded_stream(shadow.data(), shadow.size());
  Vec3 direct{0, 0, 0};
  for (std::size_t s = 0; s < shadow.size(); ++s)
    if (shadow[s].tfar >= 0) direct += contrib[s];  // Embree sets tfar = -inf when occluded
  return direct;
}

// Final gather at p: rays.size() cosine-distributed rays, one incoherent stream; each that ends on
// a diffuse surface (through mirrors and glass) becomes a query in `o`. Returns their count.
std::uint32_t gather_queries(const EmbreeScene& es, const SurfacePoint& p, Vec3 org, Rng& rng, int max_specular_depth,
                             float separation, std::vector<RTCRayHit>& rays, GatherChunk& o) {
  const Scene& scene = es.scene();
  const std::size_t M = rays.size();
  Frame frame(p.n);
  for (std::size_t j = 0; j < M; ++j) {
    Vec3 d = frame.to_world(cosine_hemisphere(rng.uniform(), rng.uniform()));
    set_ray(rays[j], org, d, 0.0f, INFINITY);
  }
  es.intersect_stream(rays.data(), rays.size(), false);
  o.gather += M;
  const Vec3 w0 = p.weight * p.kd * (1.0f / static_cast<int>(M));
  std::uint32_t queries = 0;
  for (std::size_t j = 0; j < M; ++j) {
    const RTCRayHit& r = rays[j];
    if (r.hit.geomID == RTC_INVALID_GEOMETRY_ID) {
      ++o.escaped;
      continue;
    }
    EmbreeScene::Hit hit{r.ray.tfar, r.hit.primID};
    Vec3 ro = org, rd{r.ray.dir_x, r.ray.dir_y, r.ray.dir_z}, beta{1, 1, 1};
    int glass = p.in_glass ? 1 : 0;
    if (!follow_specular(es, rng, ro, rd, hit, beta, max_specular_depth, glass)) {
      ++o.escaped;
      continue;
    }
    const Material& m = scene.material_of(hit.prim);
    if (!m.is_diffuse()) {  // an emitter or a black surface: nothing for the map to add
      ++o.no_query;
      continue;
    }
    const Vec3 y = medium_key(ro + rd * hit.t, glass > 0, separation);
    const bool back = dot(scene.geometric_normal(hit.prim), rd) >= 0;
    o.xyz.insert(o.xyz.end(), {y.x, y.y, y.z});
    o.q.push_back({hit.prim | (back ? kBackSide : 0u), w0 * beta});
    ++queries;
  }
  return queries;
}

// The chunks' queries concatenated in chunk order (each chunk freed once copied), their ray
// counts into `stats`, and each point's first query (q_begin) from its count.
void concatenate_chunks(std::vector<GatherChunk>& co, const std::vector<std::uint32_t>& q_count, TracedPass& pass,
                        RenderStats& stats) {
  std::size_t total = 0;
  for (const auto& o : co) total += o.q.size();
  pass.gather_xyz.reserve(3 * total);
  pass.gather.reserve(total);
  for (auto& o : co) {
    pass.gather_xyz.insert(pass.gather_xyz.end(), o.xyz.begin(), o.xyz.end());
    pass.gather.insert(pass.gather.end(), o.q.begin(), o.q.end());
    stats.shadow_rays += o.shadow;
    stats.gather_rays += o.gather;
    stats.gather_escaped += o.escaped;
    stats.gather_no_query += o.no_query;
    o = GatherChunk{};
  }
  for (std::size_t i = 0; i < q_count.size(); ++i) pass.q_begin[i + 1] = pass.q_begin[i] + q_count[i];
}

}  // namespace

void FinalGatherRenderer::trace_points(const std::vector<SurfacePoint>& pts, const std::vector<std::uint32_t>& slots,
                                       TracedPass& pass, RenderStats& stats) const {
  const float eps = es_.ray_epsilon();
  const int M = opt_.gather, S = opt_.shadow_rays;
  const std::size_t n = pts.size();
  pass.vis_slot = slots;
  pass.direct.assign(n, Vec3{0, 0, 0});
  pass.q_begin.assign(n + 1, 0);
  const float separation = medium_separation(es_.scene().diagonal());
  fill_visible_points(pts, separation, pass);
  if (n == 0) return;

  // Direct light and gather rays, per fixed chunk of points (outputs concatenated in chunk order,
  // so the query order and the image do not depend on threads).
  auto t0 = Clock::now();
  constexpr std::size_t kChunk = 64;
  const std::size_t chunks = (n + kChunk - 1) / kChunk;
  std::vector<GatherChunk> co(chunks);
  std::vector<std::uint32_t> q_count(n, 0);  // gather queries of each point
  parallel_chunks(n, kChunk, opt_.threads, [&](std::size_t c, std::size_t b, std::size_t e) {
    GatherChunk& o = co[c];
    std::vector<RTCRay> shadow(static_cast<std::size_t>(S));
    std::vector<Vec3> contrib(static_cast<std::size_t>(S));
    std::vector<RTCRayHit> rays(static_cast<std::size_t>(M));
    for (std::size_t i = b; i < e; ++i) {
      const SurfacePoint& p = pts[i];
      Rng rng(opt_.seed, kGatherStream, p.rng_index);
      const Vec3 org = p.x + p.n * eps;
      const Vec3 direct = direct_light(es_, lights_, p, org, rng, shadow, contrib);
      o.shadow += static_cast<std::size_t>(S);
      pass.direct[i] = p.weight * p.kd * direct * (1.0f / (kPi * S));
      if (M == 0) continue;
      q_count[i] = gather_queries(es_, p, org, rng, opt_.max_specular_depth, separation, rays, o);
    }
  });
  es_.check("final gather");
  concatenate_chunks(co, q_count, pass, stats);
  stats.trace_s += since(t0);
}

void FinalGatherRenderer::shade_pass(const TracedPass& pass, std::size_t slots,
                                     const std::vector<DensityEstimator>& estimators,
                                     std::vector<std::vector<Vec3>>& out, RenderStats& stats,
                                     QueryScratch& scratch) const {
  const Scene& scene = es_.scene();
  const std::size_t n = pass.vis_slot.size(), nq = pass.gather.size(), E = estimators.size();
  out.assign(E, pass.emitted);
  if (slots != pass.emitted.size()) throw Error("render: a traced pass does not match its image rows");
  if (n == 0 || E == 0) return;

  // The batched kNN calls: all gather points of the pass in one call; the caustic map is looked
  // up directly at the visible points, also in one call.
  auto t0 = Clock::now();
  KnnResult& gres = scratch.global;
  KnnResult& cres = scratch.caustic;
  const bool have_global = nq > 0 && !global_.empty();
  SearchParams cparams = opt_.search;
  cparams.k = opt_.caustic_k;
  cparams.max_radius = opt_.caustic_radius;
  // One estimator needs no lists: the estimate is made inside the query (the gather point's
  // surface normal goes with it) and only the estimates come back.
  const bool fused = opt_.fused_estimate && E == 1;
  if (fused) {
    if (have_global) {
      std::vector<float>& nrm = scratch.normals;
      nrm.resize(3 * nq);
      for (std::size_t q = 0; q < nq; ++q) {
        const GatherQuery& g = pass.gather[q];
        const Vec3 ng = scene.geometric_normal(g.prim_side & ~kBackSide);
        const Vec3 n = (g.prim_side & kBackSide) ? -ng : ng;
        nrm[3 * q] = n.x;
        nrm[3 * q + 1] = n.y;
        nrm[3 * q + 2] = n.z;
      }
      stats.add_query(global_.estimate(pass.gather_xyz.data(), nrm.data(), nq, opt_.search, estimators[0],
                                       opt_.radius_scale2, scratch.global_est));
      stats.result_bytes += scratch.global_est.bytes_read_back;
      stats.queries += nq;
    }
    if (caustic_) {
      static_assert(sizeof(Vec3) == 3 * sizeof(float), "normals are read as n x 3 floats");
      stats.add_query(caustic_->estimate(pass.vis_xyz.data(), reinterpret_cast<const float*>(pass.vis_n.data()), n,
                                         cparams, estimators[0], opt_.radius_scale2, scratch.caustic_est));
      stats.result_bytes += scratch.caustic_est.bytes_read_back;
      stats.caustic_queries += n;
    }
  } else {
    if (have_global) {
      stats.add_query(global_.query(pass.gather_xyz.data(), nq, opt_.search, gres));
      stats.result_bytes += nq * (8 * static_cast<std::size_t>(opt_.search.k) + 4);
      stats.queries += nq;
    }
    if (caustic_) {
      stats.add_query(caustic_->query(pass.vis_xyz.data(), n, cparams, cres));
      stats.result_bytes += n * (8 * static_cast<std::size_t>(cparams.k) + 4);
      stats.caustic_queries += n;
    }
  }
  stats.query_s += since(t0);

  // Radiance estimates, summed per point in a fixed order, once per estimator.
  t0 = Clock::now();
  const float gscale = global_.power_scale() / kPi;
  const float cscale = caustic_ ? caustic_->power_scale() / kPi : 0.0f;
  auto est3 = [](const DensityResult& d, std::size_t q) {
    return Vec3{d.estimate[3 * q], d.estimate[3 * q + 1], d.estimate[3 * q + 2]};
  };
  parallel_chunks(n, 256, opt_.threads, [&](std::size_t, std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      for (std::size_t k = 0; k < E; ++k) {
        const DensityEstimator& est = estimators[k];
        Vec3 indirect{0, 0, 0};
        if (have_global)
          for (std::size_t q = pass.q_begin[i]; q < pass.q_begin[i + 1]; ++q) {
            const GatherQuery& g = pass.gather[q];
            const std::uint32_t prim = g.prim_side & ~kBackSide;
            if (fused) {
              indirect += g.weight * (scene.material_of(prim).kd * est3(scratch.global_est, q) * gscale);
              continue;
            }
            const Vec3 ng = scene.geometric_normal(prim);
            indirect += g.weight * global_.radiance(gres, q, (g.prim_side & kBackSide) ? -ng : ng,
                                                    scene.material_of(prim).kd, opt_.search.max_radius, est,
                                                    opt_.radius_scale2);
          }
        Vec3 caustic{0, 0, 0};
        if (caustic_)
          caustic = pass.vis_weight[i] *
                    (fused ? pass.vis_kd[i] * est3(scratch.caustic_est, i) * cscale
                           : caustic_->radiance(cres, i, pass.vis_n[i], pass.vis_kd[i], cparams.max_radius, est,
                                                opt_.radius_scale2));
        out[k][pass.vis_slot[i]] += pass.direct[i] + (indirect + caustic);
      }
    }
  });
  stats.shade_s += since(t0);
}

int FinalGatherRenderer::rows_per_pass() const {
  const std::size_t per_row = static_cast<std::size_t>(opt_.width) * opt_.spp * std::max(1, opt_.gather);
  return static_cast<int>(std::clamp<std::size_t>(opt_.batch_queries / per_row, 1, opt_.height));
}

TracedPass FinalGatherRenderer::trace_pass(int y0, int y1, RenderStats& stats) const {
  const Scene& scene = es_.scene();
  const int W = opt_.width, spp = opt_.spp;
  const PinholeCamera cam(scene.camera, W, opt_.height);
  TracedPass pass;
  pass.y0 = y0;
  pass.y1 = y1;
  const std::size_t slot0 = static_cast<std::size_t>(y0) * W * spp;
  const std::size_t nslots = static_cast<std::size_t>(y1 - y0) * W * spp;
  pass.emitted.assign(nslots, Vec3{0, 0, 0});

  // Camera rays in packets of 16 consecutive samples; specular chains followed one by one.
  auto t0 = Clock::now();
  constexpr std::size_t kChunk = 64;
  const std::size_t chunks = (nslots + kChunk - 1) / kChunk;
  const int camera_glass = es_.inside_glass(cam.origin()) ? 1 : 0;
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
        int glass = camera_glass;
        Rng& rng = rngs[l];
        // Emitters seen directly or through mirrors/glass; the chain stops at a diffuse surface.
        for (int depth = 0;; ++depth) {
          const Material& m = scene.material_of(hit.prim);
          Vec3 ng = scene.geometric_normal(hit.prim);
          bool front = dot(ng, dir) < 0;
          if (m.is_light() && front) pass.emitted[s] += beta * m.emission;
          if (!m.is_specular()) {
            if (m.is_diffuse()) {
              SurfacePoint sp;
              sp.x = org + dir * hit.t;
              sp.n = front ? ng : -ng;
              sp.kd = m.kd;
              sp.weight = beta;
              sp.in_glass = glass > 0;
              sp.rng_index = slot0 + s;
              vis_chunks[c].push_back(sp);
              vis_slot_chunks[c].push_back(static_cast<std::uint32_t>(s));
            }
            break;
          }
          if (depth >= opt_.max_specular_depth) break;
          if (!specular_bounce(es_, rng, org, dir, hit, beta, &glass)) break;
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
  trace_points(vis, vis_slot, pass, stats);
  ++stats.passes;
  return pass;
}

void FinalGatherRenderer::film(const TracedPass& pass, const std::vector<Vec3>& radiance, Image& img,
                               RenderStats& stats) const {
  auto t0 = Clock::now();
  const int W = opt_.width, spp = opt_.spp;
  for (int y = pass.y0; y < pass.y1; ++y)
    for (int x = 0; x < W; ++x) {
      Vec3 sum{0, 0, 0};
      std::size_t base = (static_cast<std::size_t>(y - pass.y0) * W + x) * spp;
      for (int s = 0; s < spp; ++s) sum += radiance[base + s];
      img.set(static_cast<std::size_t>(y) * W + x, sum * (1.0f / spp));
    }
  stats.shade_s += since(t0);
}

Image FinalGatherRenderer::render(RenderStats& stats, Progress* progress) const {
  const int H = opt_.height, rows = rows_per_pass();
  Image img(opt_.width, H);
  stats.pixels += img.pixels();
  std::vector<std::vector<Vec3>> radiance;
  QueryScratch scratch;
  for (int y0 = 0; y0 < H; y0 += rows) {
    const TracedPass pass = trace_pass(y0, std::min(H, y0 + rows), stats);
    shade_pass(pass, pass.emitted.size(), {opt_.estimator}, radiance, stats, scratch);
    film(pass, radiance[0], img, stats);
    if (progress) progress->update(static_cast<double>(pass.y1) / H);
  }
  return img;
}

// The settings a traced frame's passes depend on (RenderOptions' and TracedFrame's fields of those
// names), as one tuple: trace() records them and shade() compares them, so the two cannot drift.
template <class Settings>
static auto frame_settings(Settings& s) {
  return std::tie(s.width, s.height, s.spp, s.gather, s.shadow_rays, s.max_specular_depth, s.seed);
}

TracedFrame FinalGatherRenderer::trace(RenderStats& stats, Progress* progress) const {
  TracedFrame f;
  frame_settings(f) = frame_settings(opt_);
  f.scene = &es_;
  const int H = opt_.height, rows = rows_per_pass();
  for (int y0 = 0; y0 < H; y0 += rows) {
    f.passes.push_back(trace_pass(y0, std::min(H, y0 + rows), stats));
    if (progress) progress->update(static_cast<double>(f.passes.back().y1) / H);
  }
  return f;
}

std::vector<Image> FinalGatherRenderer::shade(const TracedFrame& f, const std::vector<DensityEstimator>& estimators,
                                              RenderStats& stats, Progress* progress) const {
  if (f.scene != &es_ || frame_settings(f) != frame_settings(opt_))
    throw Error("render: the traced frame was made with another scene or other image, sampling or seed settings");
  std::vector<Image> images(estimators.size(), Image(opt_.width, opt_.height));
  stats.pixels += images.empty() ? 0 : images[0].pixels();
  std::vector<std::vector<Vec3>> radiance;
  QueryScratch scratch;
  for (const TracedPass& pass : f.passes) {
    shade_pass(pass, pass.emitted.size(), estimators, radiance, stats, scratch);
    for (std::size_t e = 0; e < estimators.size(); ++e) film(pass, radiance[e], images[e], stats);
    if (progress) progress->update(static_cast<double>(pass.y1) / opt_.height);
  }
  return images;
}

}  // namespace bhcl::render
