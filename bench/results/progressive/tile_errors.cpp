// Per-tile mean luminance of an OpenEXR image against a reference, for finding which 32-px tiles
// of a progressive render are off and by how much (issue 24). Build:
//   g++ -O2 -std=c++17 tile_errors.cpp $(pkg-config --cflags --libs OpenEXR) -o tile_errors
// Usage: tile_errors IMAGE.exr REFERENCE.exr [BLOCK=32]
// Prints a grid of signed relative errors (per cent, (img - ref) / ref) and the reference's tile
// means; tiles where the reference sees an emitter (a pixel > 8x the median) are marked "L".
#include <algorithm>
#include <cstdio>
#include <string>
#include <vector>

#include "../exr_luminance.hpp"

int main(int argc, char** argv) {
  if (argc < 3) {
    std::fprintf(stderr, "usage: %s IMAGE.exr REFERENCE.exr [BLOCK]\n", argv[0]);
    return 2;
  }
  try {
    int W, H, W2, H2;
    std::vector<float> a = exr_luminance<float>(argv[1], W, H), r = exr_luminance<float>(argv[2], W2, H2);
    if (W != W2 || H != H2) throw std::runtime_error("sizes differ");
    const int b = argc > 3 ? std::stoi(argv[3]) : 32;
    std::vector<float> s = r;
    std::nth_element(s.begin(), s.begin() + s.size() / 2, s.end());
    const float bright = 8 * s[s.size() / 2];
    std::string err, mean;
    char buf[64];
    for (int by = 0; by < H; by += b) {
      std::snprintf(buf, sizeof buf, "y%4d ", by);
      err += buf;
      mean += buf;
      for (int bx = 0; bx < W; bx += b) {
        double sa = 0, sr = 0;
        bool light = false;
        for (int y = by; y < std::min(H, by + b); ++y)
          for (int x = bx; x < std::min(W, bx + b); ++x) {
            sa += a[y * W + x];
            sr += r[y * W + x];
            light = light || r[y * W + x] > bright;
          }
        const int n = (std::min(H, by + b) - by) * (std::min(W, bx + b) - bx);
        if (light) std::snprintf(buf, sizeof buf, "%8s", "L");
        else std::snprintf(buf, sizeof buf, "%+8.2f", sr > 0 ? 100 * (sa - sr) / sr : 0.0);
        err += buf;
        std::snprintf(buf, sizeof buf, "%8.4f", sr / n);
        mean += buf;
      }
      err += "\n";
      mean += "\n";
    }
    std::printf("relative error of tile means, %% (columns x = 0, %d, ...)\n%s\nreference tile means\n%s", b,
                err.c_str(), mean.c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s\n", e.what());
    return 1;
  }
}
