#include "png_io.hpp"

#include <png.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <cerrno>
#include <memory>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"
#include <string>

namespace bhcl::render {

void Rgb8::blit(const Rgb8& src, int x0, int y0) {
  for (int y = 0; y < src.height; ++y) {
    int ty = y0 + y;
    if (ty < 0 || ty >= height) continue;
    for (int x = 0; x < src.width; ++x) {
      int tx = x0 + x;
      if (tx < 0 || tx >= width) continue;
      for (int c = 0; c < 3; ++c)
        px[(static_cast<std::size_t>(ty) * width + tx) * 3 + c] =
            src.px[(static_cast<std::size_t>(y) * src.width + x) * 3 + c];
    }
  }
}

namespace {
std::uint8_t srgb8(float v) {
  v = std::clamp(v, 0.0f, 1.0f);
  float s = v <= 0.0031308f ? 12.92f * v : 1.055f * std::pow(v, 1.0f / 2.4f) - 0.055f;
  return static_cast<std::uint8_t>(std::lround(s * 255.0f));
}

struct FileCloser {
  void operator()(std::FILE* f) const { if (f) std::fclose(f); }
};
}  // namespace

Rgb8 tonemap(const Image& image, float exposure) {
  Rgb8 out(image.width, image.height);
  for (std::size_t i = 0; i < image.rgb.size(); ++i) {
    float v = image.rgb[i];
    out.px[i] = srgb8(std::isfinite(v) ? v * exposure : 0.0f);
  }
  return out;
}

float auto_exposure(const Image& image) {
  std::vector<float> lum;
  lum.reserve(image.pixels());
  for (std::size_t i = 0; i < image.pixels(); ++i) {
    float l = luminance(image.at(i));
    if (std::isfinite(l)) lum.push_back(l);
  }
  if (lum.empty()) return 1.0f;
  // Pixels that see an emitter (the Cornell light is 40x the walls) would set the 99th
  // percentile whenever they cover more than 1 % of the image and leave the rest dark: the
  // percentile is taken over the pixels at most 8x the median (the lit scene, noise included).
  std::size_t mid = lum.size() / 2;
  std::nth_element(lum.begin(), lum.begin() + static_cast<std::ptrdiff_t>(mid), lum.end());
  const float median = lum[mid];
  if (median > 0) lum.erase(std::remove_if(lum.begin(), lum.end(), [&](float l) { return l > 8 * median; }), lum.end());
  std::size_t k = std::min(lum.size() - 1, static_cast<std::size_t>(0.99 * lum.size()));
  std::nth_element(lum.begin(), lum.begin() + static_cast<std::ptrdiff_t>(k), lum.end());
  return lum[k] > 0 ? 1.0f / lum[k] : 1.0f;
}

namespace {
void png_append(png_structp png, png_bytep data, png_size_t n) {
  static_cast<std::string*>(png_get_io_ptr(png))->append(reinterpret_cast<const char*>(data), n);
}
void png_no_flush(png_structp) {}
}  // namespace

void write_png(const std::string& path, const Rgb8& image) {
  // Encoded into memory, then written whole by bhcl::write_file (a temporary renamed over the
  // target: a failed write leaves the old image intact and names the reason).
  std::string bytes;
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  if (!png || !info) {
    png_destroy_write_struct(&png, &info);
    throw Error(path + ": libpng could not start (out of memory)");
  }
  // libpng reports errors by longjmp; nothing with a destructor is created below this point.
  if (setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    throw Error(path + ": writing the PNG failed");
  }
  png_set_write_fn(png, &bytes, png_append, png_no_flush);
  png_set_IHDR(png, info, static_cast<png_uint_32>(image.width), static_cast<png_uint_32>(image.height), 8,
               PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  png_set_sRGB(png, info, PNG_sRGB_INTENT_PERCEPTUAL);
  png_write_info(png, info);
  for (int y = 0; y < image.height; ++y)
    png_write_row(png, const_cast<png_bytep>(image.px.data() + static_cast<std::size_t>(y) * image.width * 3));
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  write_file(path, {bytes}, "the PNG");
}

Rgb8 read_png(const std::string& path) {
  png_image img{};
  img.version = PNG_IMAGE_VERSION;
  if (!png_image_begin_read_from_file(&img, path.c_str()))
    throw Error(path + ": reading the PNG failed: " + img.message);
  img.format = PNG_FORMAT_RGB;
  Rgb8 out(static_cast<int>(img.width), static_cast<int>(img.height));
  if (!png_image_finish_read(&img, nullptr, out.px.data(), 0, nullptr)) {
    std::string msg = img.message;
    png_image_free(&img);
    throw Error(path + ": reading the PNG failed: " + msg);
  }
  return out;
}

}  // namespace bhcl::render
