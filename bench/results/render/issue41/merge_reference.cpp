// Two independent path-traced images of one scene merged into one reference, each pixel the mean
// of the two weighted by their paths a pixel, except inside the given windows, which keep the
// first image's pixels (windows traced again at many more paths, part2.sh's --window runs).
// Issue 41: the 2048-path reference's own noise on the dim tiles (1.5-2.5 %, a 4096-path render
// of another seed against it) is as large as the 2 % to be measured. Build:
//   g++ -O2 -std=c++17 merge_reference.cpp $(pkg-config --cflags --libs OpenEXR) -o merge_reference
// Usage: merge_reference OUT.exr A.exr PATHS_A B.exr PATHS_B [X0,Y0,X1,Y1 ...]   (windows in pixels)
// OUT is written to OUT.tmp and renamed over OUT.
#include <ImfArray.h>
#include <ImfRgbaFile.h>

#include <cstdio>
#include <stdexcept>
#include <string>
#include <vector>

namespace {

struct Rgb {
  int w = 0, h = 0;
  std::vector<float> px;  // 3 per pixel
};

Rgb read_rgb(const char* path) {
  Imf::RgbaInputFile in(path);
  const Imath::Box2i dw = in.dataWindow();
  Rgb img;
  img.w = dw.max.x - dw.min.x + 1;
  img.h = dw.max.y - dw.min.y + 1;
  Imf::Array2D<Imf::Rgba> a(img.h, img.w);
  in.setFrameBuffer(&a[0][0] - dw.min.x - dw.min.y * img.w, 1, img.w);
  in.readPixels(dw.min.y, dw.max.y);
  for (int y = 0; y < img.h; ++y)
    for (int x = 0; x < img.w; ++x) img.px.insert(img.px.end(), {float(a[y][x].r), float(a[y][x].g), float(a[y][x].b)});
  return img;
}

void write_rgb(const std::string& path, const Rgb& img) {
  std::vector<Imf::Rgba> px(static_cast<std::size_t>(img.w) * img.h);
  for (std::size_t i = 0; i < px.size(); ++i) px[i] = Imf::Rgba(img.px[3 * i], img.px[3 * i + 1], img.px[3 * i + 2], 1.0f);
  const std::string tmp = path + ".tmp";
  {
    Imf::RgbaOutputFile out(tmp.c_str(), img.w, img.h, Imf::WRITE_RGBA);
    out.setFrameBuffer(px.data(), 1, img.w);
    out.writePixels(img.h);
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) throw std::runtime_error("cannot rename " + tmp + " to " + path);
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 6) {
    std::fprintf(stderr, "usage: merge_reference OUT.exr A.exr PATHS_A B.exr PATHS_B [X0,Y0,X1,Y1 ...]\n");
    return 2;
  }
  try {
    const Rgb a = read_rgb(argv[2]), b = read_rgb(argv[4]);
    const double na = std::stod(argv[3]), nb = std::stod(argv[5]);
    if (a.w != b.w || a.h != b.h) throw std::runtime_error("the images' sizes differ");
    if (!(na > 0) || !(nb > 0)) throw std::runtime_error("PATHS_A and PATHS_B must be > 0");
    std::vector<int> win;
    for (int i = 6; i < argc; ++i) {
      int x0, y0, x1, y1;
      if (std::sscanf(argv[i], "%d,%d,%d,%d", &x0, &y0, &x1, &y1) != 4 || x0 < 0 || y0 < 0 || x1 > a.w || y1 > a.h ||
          x0 >= x1 || y0 >= y1)
        throw std::runtime_error(std::string("bad window '") + argv[i] + "' (X0,Y0,X1,Y1 inside the image)");
      win.insert(win.end(), {x0, y0, x1, y1});
    }
    Rgb out = a;
    for (int y = 0; y < a.h; ++y)
      for (int x = 0; x < a.w; ++x) {
        bool keep = false;
        for (std::size_t k = 0; k < win.size(); k += 4)
          keep = keep || (x >= win[k] && y >= win[k + 1] && x < win[k + 2] && y < win[k + 3]);
        if (keep) continue;
        const std::size_t i = 3 * (static_cast<std::size_t>(y) * a.w + x);
        for (int c = 0; c < 3; ++c) out.px[i + c] = static_cast<float>((na * a.px[i + c] + nb * b.px[i + c]) / (na + nb));
      }
    write_rgb(argv[1], out);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "merge_reference: %s\n", e.what());
    return 1;
  }
  return 0;
}
