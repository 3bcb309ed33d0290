// The pinhole camera and the film: a linear RGB float image, row 0 at the top.
#pragma once

#include <cmath>
#include <vector>

#include "scene.hpp"

namespace bhcl::render {

struct Image {
  int width = 0, height = 0;
  std::vector<float> rgb;  // width * height * 3, row-major, top row first

  Image() = default;
  Image(int w, int h) : width(w), height(h), rgb(static_cast<std::size_t>(w) * h * 3, 0.0f) {}
  std::size_t pixels() const { return static_cast<std::size_t>(width) * height; }
  Vec3 at(std::size_t i) const { return {rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]}; }
  void set(std::size_t i, Vec3 c) {
    rgb[3 * i] = c.x;
    rgb[3 * i + 1] = c.y;
    rgb[3 * i + 2] = c.z;
  }
};

// Square pixels; the scene's vertical field of view spans the image height.
class PinholeCamera {
 public:
  PinholeCamera(const Camera& c, int width, int height) : origin_(c.position) {
    Vec3 f = normalize(c.direction);
    Vec3 right = normalize(cross(f, c.up));  // right-handed, +y up, looking along +z: right = -x
    Vec3 up = cross(right, f);
    float th = std::tan(0.5f * c.vfov_deg * kPi / 180.0f);
    forward_ = f;
    du_ = right * (2.0f * th / height);
    dv_ = up * (-2.0f * th / height);
    corner_ = f - du_ * (0.5f * width) - dv_ * (0.5f * height);
  }
  Vec3 origin() const { return origin_; }
  // Unit direction through film position (x, y) in pixels (0,0 = top-left corner).
  Vec3 direction(float x, float y) const { return normalize(corner_ + du_ * x + dv_ * y); }

 private:
  Vec3 origin_, forward_, du_, dv_, corner_;
};

}  // namespace bhcl::render
