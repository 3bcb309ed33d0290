// Issue 41, part 2: an image's error against a converged reference, as a user judges a render,
// with bhcl render --reference's definitions (host/render/compare.cpp, block_error): over the
// TILE x TILE tiles whose reference sees no emitter (no pixel over 8x the median), the RMSE of the
// tile-mean luminance over the mean reference tile, and the worst tile's |tile - reference| /
// reference; and the relative error of one region's mean luminance (the
// caustic: the floor under the glass). Build:
//   g++ -O2 -std=c++17 image_errors.cpp $(pkg-config --cflags --libs OpenEXR) -o image_errors
// Usage: image_errors IMAGE.exr REFERENCE.exr TILE X0,Y0,X1,Y1   (region in fractions of the image)
// Prints: tile_rmse worst_tile region_error   (fractions, not per cent)
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <string>
#include <vector>

#include "../../exr_luminance.hpp"

namespace {

double mean_of(const std::vector<double>& l, int W, int x0, int y0, int x1, int y1) {
  double s = 0;
  for (int y = y0; y < y1; ++y)
    for (int x = x0; x < x1; ++x) s += l[std::size_t(y) * W + x];
  return s / double((x1 - x0) * (y1 - y0));
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 5) {
    std::fprintf(stderr, "usage: image_errors IMAGE.exr REFERENCE.exr TILE X0,Y0,X1,Y1\n");
    return 2;
  }
  try {
    int W, H, RW, RH;
    const std::vector<double> img = exr_luminance<double>(argv[1], W, H), ref = exr_luminance<double>(argv[2], RW, RH);
    if (W != RW || H != RH) throw std::runtime_error("the images' sizes differ");
    const int T = std::stoi(argv[3]);
    if (T < 1) throw std::runtime_error("TILE must be >= 1");
    double f[4];
    if (std::sscanf(argv[4], "%lf,%lf,%lf,%lf", &f[0], &f[1], &f[2], &f[3]) != 4)
      throw std::runtime_error("the region must be X0,Y0,X1,Y1");
    std::vector<double> sorted = ref;
    std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
    const double bright = 8 * sorted[sorted.size() / 2];
    double se = 0, worst = 0, sum_ref = 0;
    int tiles = 0;
    for (int ty = 0; ty + T <= H; ty += T)
      for (int tx = 0; tx + T <= W; tx += T) {
        bool emitter = false;
        for (int y = ty; y < ty + T; ++y)
          for (int x = tx; x < tx + T; ++x) emitter = emitter || ref[std::size_t(y) * W + x] > bright;
        if (emitter) continue;
        const double r = mean_of(ref, W, tx, ty, tx + T, ty + T), a = mean_of(img, W, tx, ty, tx + T, ty + T);
        se += (a - r) * (a - r);
        sum_ref += r;
        if (r > 0) worst = std::max(worst, std::fabs(a - r) / r);
        ++tiles;
      }
    const int x0 = int(f[0] * W), y0 = int(f[1] * H), x1 = int(f[2] * W), y1 = int(f[3] * H);
    if (!(x0 >= 0 && y0 >= 0 && x1 <= W && y1 <= H && x0 < x1 && y0 < y1))
      throw std::runtime_error("the region is empty or outside the image");
    const double rr = mean_of(ref, W, x0, y0, x1, y1);
    const double region = (mean_of(img, W, x0, y0, x1, y1) - rr) / rr;
    const double rmse = tiles && sum_ref > 0 ? std::sqrt(se / tiles) / (sum_ref / tiles) : 0.0;
    std::printf("%.6g %.6g %.6g\n", rmse, worst, std::fabs(region));
  } catch (const std::exception& e) {
    std::fprintf(stderr, "image_errors: %s\n", e.what());
    return 1;
  }
  return 0;
}
