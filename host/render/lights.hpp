// Sampling points on the emitters, by power: used to emit photons and to aim shadow rays.
#pragma once

#include <cstdint>
#include <vector>

#include "scene.hpp"

namespace bhcl::render {

class LightSampler {
 public:
  explicit LightSampler(const Scene& scene);

  struct Sample {
    Vec3 position, normal, emission;  // normal: the emitting (front) side
    float pdf_area = 0;               // per unit area, over all emitters
    std::uint32_t triangle = 0;
  };
  // A point on an emitter: triangle chosen with probability proportional to area x emission
  // (sum of channels), then uniformly on it.
  Sample sample(float u_select, float u1, float u2) const;

  // Total emitted power, per channel: sum over emitters of pi * Le * area (Lambertian emitters).
  // With the area in mm^2 this is in radiance units x mm^2.
  Vec3 total_power() const { return total_power_; }
  std::size_t count() const { return tris_.size(); }

 private:
  const Scene& scene_;
  std::vector<std::uint32_t> tris_;
  std::vector<float> cdf_;  // normalised, cdf_.back() == 1
  std::vector<float> prob_;
  Vec3 total_power_{0, 0, 0};
};

}  // namespace bhcl::render
