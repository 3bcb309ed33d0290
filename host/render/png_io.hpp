// 8-bit sRGB PNG previews of linear images (libpng).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "film.hpp"

namespace bhcl::render {

// An 8-bit RGB raster.
struct Rgb8 {
  int width = 0, height = 0;
  std::vector<std::uint8_t> px;  // width * height * 3
  Rgb8() = default;
  Rgb8(int w, int h, std::uint8_t fill = 0)
      : width(w), height(h), px(static_cast<std::size_t>(w) * h * 3, fill) {}
  void blit(const Rgb8& src, int x0, int y0);  // copies src with its top-left corner at (x0, y0)
};

// Tone mapping (documented choice): scale by `exposure`, clamp to [0, 1], sRGB transfer curve.
Rgb8 tonemap(const Image& image, float exposure);
// The exposure that maps the 99th percentile of pixel luminance to 1 (1 for a black image), the
// percentile taken over the pixels at most 8x the median luminance, so that a light seen
// directly (however many pixels it covers) does not darken the rest.
float auto_exposure(const Image& image);

void write_png(const std::string& path, const Rgb8& image);  // throws bhcl::Error naming path
Rgb8 read_png(const std::string& path);                      // 8-bit RGB/RGBA/grey, for tests

}  // namespace bhcl::render
