#include "lights.hpp"

#include <algorithm>

#include "blockhash_cl/error.hpp"

namespace bhcl::render {

LightSampler::LightSampler(const Scene& scene) : scene_(scene) {
  double total = 0;
  std::vector<double> w;
  for (std::uint32_t i = 0; i < scene.triangles.size(); ++i) {
    const Material& m = scene.material_of(i);
    float a = scene.triangle_area(i);
    if (!m.is_light() || !(a > 0)) continue;
    tris_.push_back(i);
    double wi = static_cast<double>(a) * (m.emission.x + m.emission.y + m.emission.z);
    w.push_back(wi);
    total += wi;
    total_power_ += m.emission * (kPi * a);
  }
  if (tris_.empty() || !(total > 0)) throw Error("scene '" + scene.name + "': no emitter to sample");
  double acc = 0;
  for (double wi : w) {
    acc += wi;
    cdf_.push_back(static_cast<float>(acc / total));
    prob_.push_back(static_cast<float>(wi / total));
  }
  cdf_.back() = 1.0f;
}

LightSampler::Sample LightSampler::sample(float u_select, float u1, float u2) const {
  std::size_t i = static_cast<std::size_t>(std::upper_bound(cdf_.begin(), cdf_.end(), u_select) - cdf_.begin());
  if (i >= tris_.size()) i = tris_.size() - 1;
  std::uint32_t tri = tris_[i];
  const auto& t = scene_.triangles[tri];
  Sample s;
  s.triangle = tri;
  s.position = sample_triangle(scene_.vertices[t[0]], scene_.vertices[t[1]], scene_.vertices[t[2]], u1, u2);
  s.normal = scene_.geometric_normal(tri);
  s.emission = scene_.material_of(tri).emission;
  s.pdf_area = prob_[i] / scene_.triangle_area(tri);
  return s;
}

}  // namespace bhcl::render
