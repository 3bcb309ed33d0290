// Mean radiance (luminance and RGB) of an OpenEXR image over rectangles given as fractions of
// the image size, for the per-region figures of docs/RENDER.md. Build (see docs/RENDER.md):
//   g++ -O2 -std=c++17 region_means.cpp $(pkg-config --cflags --libs OpenEXR) -o region_means
// Usage: region_means IMAGE.exr NAME:x0,y0,x1,y1 ...   (fractions in [0, 1], x to the right, y down)
#include <ImfArray.h>
#include <ImfRgbaFile.h>

#include <cstdio>
#include <string>

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s IMAGE.exr NAME:x0,y0,x1,y1 ...\n", argv[0]);
    return 2;
  }
  try {
    Imf::RgbaInputFile in(argv[1]);
    Imath::Box2i dw = in.dataWindow();
    const int W = dw.max.x - dw.min.x + 1, H = dw.max.y - dw.min.y + 1;
    Imf::Array2D<Imf::Rgba> px(H, W);
    in.setFrameBuffer(&px[0][0] - dw.min.x - dw.min.y * W, 1, W);
    in.readPixels(dw.min.y, dw.max.y);
    std::printf("%-14s %8s %8s %8s %8s %7s\n", "region", "lum", "R", "G", "B", "pixels");
    for (int a = 1; a < argc; ++a) {
      std::string spec = a == 1 ? "all:0,0,1,1" : argv[a];
      float f[4];
      auto colon = spec.find(':');
      if (colon == std::string::npos ||
          std::sscanf(spec.c_str() + colon + 1, "%f,%f,%f,%f", &f[0], &f[1], &f[2], &f[3]) != 4) {
        std::fprintf(stderr, "bad region '%s' (NAME:x0,y0,x1,y1)\n", spec.c_str());
        return 2;
      }
      int x0 = static_cast<int>(f[0] * W), y0 = static_cast<int>(f[1] * H);
      int x1 = static_cast<int>(f[2] * W), y1 = static_cast<int>(f[3] * H);
      double s[3] = {0, 0, 0};
      long n = 0;
      for (int y = y0; y < y1 && y < H; ++y)
        for (int x = x0; x < x1 && x < W; ++x, ++n) {
          s[0] += px[y][x].r;
          s[1] += px[y][x].g;
          s[2] += px[y][x].b;
        }
      if (n == 0) continue;
      for (double& v : s) v /= n;
      double lum = 0.2126 * s[0] + 0.7152 * s[1] + 0.0722 * s[2];
      std::printf("%-14s %8.4f %8.4f %8.4f %8.4f %7ld\n", spec.substr(0, colon).c_str(), lum, s[0], s[1], s[2], n);
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s: %s\n", argv[1], e.what());
    return 1;
  }
}
