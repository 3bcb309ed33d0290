#include "exr_io.hpp"

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfInputFile.h>
#include <OpenEXR/ImfOutputFile.h>
#include <OpenEXR/ImfStdIO.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <OpenEXR/ImfStringAttribute.h>
#include <Imath/half.h>

#include <exception>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"

namespace bhcl::render {

namespace {

// An OpenEXR output stream into memory: the file is then written whole by bhcl::write_file
// (a temporary renamed over the target, so a failed write leaves the old image intact).
class MemoryOStream : public Imf::OStream {
 public:
  explicit MemoryOStream(const char* name) : Imf::OStream(name) {}
  void write(const char c[], int n) override {
    if (pos_ + static_cast<std::size_t>(n) > buf_.size()) buf_.resize(pos_ + static_cast<std::size_t>(n));
    std::memcpy(&buf_[pos_], c, static_cast<std::size_t>(n));
    pos_ += static_cast<std::size_t>(n);
  }
  uint64_t tellp() override { return pos_; }
  void seekp(uint64_t pos) override { pos_ = static_cast<std::size_t>(pos); }
  const std::string& bytes() const { return buf_; }

 private:
  std::string buf_;
  std::size_t pos_ = 0;
};

}  // namespace

bool needs_float_exr(const Image& image) {
  const float half_max = 65504.0f;  // HALF_MAX: larger values would be written as +inf
  for (float v : image.rgb)
    if (std::isfinite(v) && std::fabs(v) > half_max) return true;
  return false;
}

void write_exr(const std::string& path, const Image& image, ExrPixels pixels) {
  if (image.width <= 0 || image.height <= 0) throw Error(path + ": cannot write an empty image");
  std::string bytes;
  try {
    const int w = image.width, h = image.height;
    const bool as_float = pixels == ExrPixels::Float || (pixels == ExrPixels::Auto && needs_float_exr(image));
    if (as_float && pixels == ExrPixels::Auto)
      std::fprintf(stderr, "note: %s: radiance above the half-float range (65504): float32 channels written\n",
                   path.c_str());
    if (pixels == ExrPixels::Half && needs_float_exr(image))
      std::fprintf(stderr, "warning: %s: radiance above the half-float range (65504) is written as +inf "
                           "(half pixels were asked for)\n", path.c_str());
    std::vector<Imath::half> px;
    if (!as_float) {
      px.resize(image.pixels() * 3);
      for (std::size_t i = 0; i < px.size(); ++i) px[i] = Imath::half(image.rgb[i]);
    }
    Imf::Header header(w, h);
    header.compression() = Imf::ZIP_COMPRESSION;
    header.insert("software", Imf::StringAttribute("blockhash_cl bhcl render"));
    const char* names[3] = {"R", "G", "B"};
    Imf::FrameBuffer fb;
    for (int c = 0; c < 3; ++c) {
      if (as_float) {
        header.channels().insert(names[c], Imf::Channel(Imf::FLOAT));
        fb.insert(names[c], Imf::Slice(Imf::FLOAT, const_cast<char*>(reinterpret_cast<const char*>(image.rgb.data() + c)),
                                       3 * sizeof(float), 3 * sizeof(float) * w));
      } else {
        header.channels().insert(names[c], Imf::Channel(Imf::HALF));
        fb.insert(names[c], Imf::Slice(Imf::HALF, reinterpret_cast<char*>(px.data() + c),
                                       3 * sizeof(Imath::half), 3 * sizeof(Imath::half) * w));
      }
    }
    MemoryOStream stream(path.c_str());
    {
      Imf::OutputFile file(stream, header);
      file.setFrameBuffer(fb);
      file.writePixels(h);
    }
    bytes = stream.bytes();
  } catch (const std::exception& e) {
    throw Error(path + ": writing the OpenEXR image failed: " + e.what());
  }
  write_file(path, {bytes}, "the OpenEXR image");
}

Image read_exr(const std::string& path) {
  try {
    Imf::InputFile file(path.c_str());
    Imath::Box2i dw = file.header().dataWindow();
    const int w = dw.max.x - dw.min.x + 1, h = dw.max.y - dw.min.y + 1;
    Image img(w, h);
    Imf::FrameBuffer fb;
    const char* names[3] = {"R", "G", "B"};
    for (int c = 0; c < 3; ++c) {
      // The slice base points at pixel (0,0) of the data window's coordinate system.
      char* base = reinterpret_cast<char*>(img.rgb.data() + c) -
                   (static_cast<std::ptrdiff_t>(dw.min.x) + static_cast<std::ptrdiff_t>(dw.min.y) * w) *
                       3 * static_cast<std::ptrdiff_t>(sizeof(float));
      fb.insert(names[c], Imf::Slice(Imf::FLOAT, base, 3 * sizeof(float), 3 * sizeof(float) * w, 1, 1, 0.0));
    }
    file.setFrameBuffer(fb);
    file.readPixels(dw.min.y, dw.max.y);
    return img;
  } catch (const std::exception& e) {
    throw Error(path + ": reading the OpenEXR image failed: " + e.what());
  }
}

}  // namespace bhcl::render
