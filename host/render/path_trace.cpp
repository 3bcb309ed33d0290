#include "path_trace.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>

#include "blockhash_cl/error.hpp"
#include "final_gather.hpp"
#include "parallel.hpp"

namespace bhcl::render {
namespace {
constexpr std::uint64_t kPathStream = 0x505448;  // "PTH"
}

Image path_trace(const EmbreeScene& es, const LightSampler& lights, const PathTraceOptions& opt,
                 PathTraceStats& stats, Progress* progress) {
  if (opt.width <= 0 || opt.height <= 0) throw Error("path trace: image size must be positive");
  if (opt.spp < 1) throw Error("path trace: --spp must be >= 1");
  if (opt.max_depth < 1 || opt.min_depth < 1) throw Error("path trace: depths must be >= 1");
  const auto t0 = std::chrono::steady_clock::now();
  const Scene& scene = es.scene();
  const float eps = es.ray_epsilon();
  const int W = opt.width, H = opt.height, spp = opt.spp;
  const int wx0 = opt.window_x0, wy0 = opt.window_y0, wx1 = opt.window_x1 > 0 ? opt.window_x1 : W,
            wy1 = opt.window_y1 > 0 ? opt.window_y1 : H;
  if (wx0 < 0 || wy0 < 0 || wx1 > W || wy1 > H || wx0 >= wx1 || wy0 >= wy1)
    throw Error("path trace: the window must be a non-empty part of the image");
  const PinholeCamera cam(scene.camera, W, H);
  Image img(W, H);
  std::atomic<std::size_t> vertices{0}, shadow_rays{0};

  // Bands of rows so that progress is drawn from this thread; pixels within a band in parallel.
  const int band = static_cast<int>(
      std::clamp<std::size_t>(65536 / (static_cast<std::size_t>(W) * spp), 1, static_cast<std::size_t>(H)));
  for (int y0 = wy0; y0 < wy1; y0 += band) {
    const int y1 = std::min(wy1, y0 + band);
    const std::size_t npx = static_cast<std::size_t>(y1 - y0) * W;
    parallel_chunks(npx, 16, opt.threads, [&](std::size_t, std::size_t b, std::size_t e) {
      std::size_t nv = 0, ns = 0;
      for (std::size_t i = b; i < e; ++i) {
        const std::size_t pixel = static_cast<std::size_t>(y0) * W + i;
        if (static_cast<int>(pixel % W) < wx0 || static_cast<int>(pixel % W) >= wx1) continue;
        Vec3 sum{0, 0, 0};
        for (int s = 0; s < spp; ++s) {
          Rng rng(opt.seed, kPathStream, pixel * spp + s);
          Vec3 org = cam.origin();
          Vec3 dir = cam.direction(static_cast<float>(pixel % W) + rng.uniform(),
                                   static_cast<float>(pixel / W) + rng.uniform());
          Vec3 beta{1, 1, 1}, L{0, 0, 0};
          bool count_emission = true;  // from the camera or a specular bounce
          EmbreeScene::Hit hit;
          for (int depth = 0; depth < opt.max_depth; ++depth) {
            if (!es.intersect(org, dir, 0.0f, INFINITY, hit)) break;
            ++nv;
            const Material& m = scene.material_of(hit.prim);
            const Vec3 ng = scene.geometric_normal(hit.prim);
            const bool front = dot(ng, dir) < 0;
            if (m.is_light() && front && count_emission) L += beta * m.emission;
            if (m.is_specular()) {
              if (!specular_bounce(es, rng, org, dir, hit, beta)) break;
              count_emission = true;
              continue;
            }
            if (!m.is_diffuse()) break;
            const Vec3 x = org + dir * hit.t, n = front ? ng : -ng;
            const Vec3 xo = x + n * eps;
            // Next-event estimation: one point on the emitters.
            {
              const float u0 = rng.uniform(), u1 = rng.uniform(), u2 = rng.uniform();
              const LightSampler::Sample ls = lights.sample(u0, u1, u2);
              Vec3 wi = ls.position - x;
              const float d2 = dot(wi, wi), d = std::sqrt(d2);
              wi = wi / d;
              const float cos_x = dot(n, wi), cos_l = -dot(ls.normal, wi);
              if (cos_x > 0 && cos_l > 0 && d > 2 * eps) {
                RTCRay shadow;
                set_shadow_ray(shadow, xo, wi, 0.0f, d - 2 * eps);
                es.occluded_stream(&shadow, 1);
                ++ns;
                if (shadow.tfar >= 0)
                  L += beta * m.kd * ls.emission * (cos_x * cos_l / (kPi * d2 * ls.pdf_area));
              }
            }
            // Continue by a cosine-distributed bounce: BRDF x cos / pdf = kd.
            beta *= m.kd;
            if (depth + 1 >= opt.min_depth) {
              const float q = std::min(0.95f, std::max(beta.x, std::max(beta.y, beta.z)));
              if (!(q > 0) || rng.uniform() >= q) break;
              beta = beta * (1.0f / q);
            }
            org = xo;
            dir = Frame(n).to_world(cosine_hemisphere(rng.uniform(), rng.uniform()));
            count_emission = false;
          }
          sum += L;
        }
        img.set(pixel, sum * (1.0f / spp));
      }
      vertices += nv;
      shadow_rays += ns;
    });
    es.check("path trace");
    if (progress) progress->update(static_cast<double>(y1 - wy0) / (wy1 - wy0));
  }
  stats.paths += static_cast<std::size_t>(wx1 - wx0) * (wy1 - wy0) * spp;
  stats.vertices += vertices;
  stats.shadow_rays += shadow_rays;
  stats.seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return img;
}

}  // namespace bhcl::render
