// The luminance of an OpenEXR image, for the hand-built image tools of bench/results
// (progressive/tile_errors.cpp, render/issue41/image_errors.cpp): one reader, so that their errors
// are measured on the same per-pixel values. Header-only: each tool stays one g++ command.
#pragma once

#include <ImfArray.h>
#include <ImfRgbaFile.h>

#include <cstddef>
#include <vector>

// Rec. 709 luminance of every pixel, row by row (y * W + x), in T (the tools sum in double either
// way; tile_errors keeps its float pixels); W and H receive the image's size.
template <class T>
std::vector<T> exr_luminance(const char* path, int& W, int& H) {
  Imf::RgbaInputFile in(path);
  Imath::Box2i dw = in.dataWindow();
  W = dw.max.x - dw.min.x + 1;
  H = dw.max.y - dw.min.y + 1;
  Imf::Array2D<Imf::Rgba> px(H, W);
  in.setFrameBuffer(&px[0][0] - dw.min.x - dw.min.y * W, 1, W);
  in.readPixels(dw.min.y, dw.max.y);
  std::vector<T> l(static_cast<std::size_t>(W) * H);
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x)
      l[std::size_t(y) * W + x] = T(0.2126) * px[y][x].r + T(0.7152) * px[y][x].g + T(0.0722) * px[y][x].b;
  return l;
}
