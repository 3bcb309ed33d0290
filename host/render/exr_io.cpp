#include "exr_io.hpp"

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfInputFile.h>
#include <OpenEXR/ImfOutputFile.h>
#include <OpenEXR/ImfStdIO.h>

#include <fstream>
#include <OpenEXR/ImfStringAttribute.h>
#include <Imath/half.h>

#include <exception>

#include "blockhash_cl/error.hpp"

namespace bhcl::render {

void write_exr(const std::string& path, const Image& image) {
  if (image.width <= 0 || image.height <= 0) throw Error(path + ": cannot write an empty image");
  try {
    const int w = image.width, h = image.height;
    std::vector<Imath::half> px(image.pixels() * 3);
    for (std::size_t i = 0; i < px.size(); ++i) px[i] = Imath::half(image.rgb[i]);
    Imf::Header header(w, h);
    header.compression() = Imf::ZIP_COMPRESSION;
    header.insert("software", Imf::StringAttribute("blockhash_cl bhcl render"));
    const char* names[3] = {"R", "G", "B"};
    Imf::FrameBuffer fb;
    for (int c = 0; c < 3; ++c) {
      header.channels().insert(names[c], Imf::Channel(Imf::HALF));
      fb.insert(names[c], Imf::Slice(Imf::HALF, reinterpret_cast<char*>(px.data() + c),
                                     3 * sizeof(Imath::half), 3 * sizeof(Imath::half) * w));
    }
    // Our own stream, so that its close (where a full disk shows) is checked.
    std::ofstream os(path, std::ios::binary | std::ios::trunc);
    if (!os) throw Error(path + ": cannot open the OpenEXR image for writing");
    {
      Imf::StdOFStream stream(os, path.c_str());
      Imf::OutputFile file(stream, header);
      file.setFrameBuffer(fb);
      file.writePixels(h);
    }
    os.close();
    if (!os) throw Error(path + ": writing the OpenEXR image failed (disk full?)");
  } catch (const bhcl::Error&) {
    throw;
  } catch (const std::exception& e) {
    throw Error(path + ": writing the OpenEXR image failed: " + e.what());
  }
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
