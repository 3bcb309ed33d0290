#include "text.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <vector>

#ifdef BHCL_HAVE_FREETYPE
#include <ft2build.h>
#include FT_FREETYPE_H
#endif

namespace bhcl::render {

#ifdef BHCL_HAVE_FREETYPE
struct TextPainter::Impl {
  FT_Library lib = nullptr;
  FT_Face face = nullptr;
  int ascender = 0;
  ~Impl() {
    if (face) FT_Done_Face(face);
    if (lib) FT_Done_FreeType(lib);
  }
};

TextPainter::TextPainter(int pixel_height) : line_height_(pixel_height + pixel_height / 4) {
  auto impl = std::make_unique<Impl>();
  if (FT_Init_FreeType(&impl->lib)) {
    why_ = "FreeType did not start";
    return;
  }
  std::vector<std::string> paths;
  if (const char* env = std::getenv("BHCL_FONT"); env && *env) paths.emplace_back(env);
  for (const char* p : {"/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", "/usr/share/fonts/TTF/DejaVuSans.ttf",
                        "/usr/share/fonts/dejavu/DejaVuSans.ttf", "/usr/local/share/fonts/DejaVuSans.ttf"})
    paths.emplace_back(p);
  for (const auto& p : paths)
    if (!FT_New_Face(impl->lib, p.c_str(), 0, &impl->face)) break;
  if (!impl->face) {
    why_ = "no font found (install fonts-dejavu-core or set BHCL_FONT to a .ttf file)";
    return;
  }
  if (FT_Set_Pixel_Sizes(impl->face, 0, static_cast<FT_UInt>(std::max(4, pixel_height)))) {
    why_ = "the font cannot be scaled to " + std::to_string(pixel_height) + " pixels";
    return;
  }
  impl->ascender = static_cast<int>(impl->face->size->metrics.ascender >> 6);
  line_height_ = static_cast<int>(impl->face->size->metrics.height >> 6);
  impl_ = std::move(impl);
}

int TextPainter::draw(Rgb8& img, int x, int y, const std::string& text, Vec3 colour) const {
  if (!impl_) return x;
  FT_Face face = impl_->face;
  const int base = y + impl_->ascender;
  for (unsigned char ch : text) {
    if (ch < 32 || ch > 126) continue;
    if (FT_Load_Char(face, ch, FT_LOAD_RENDER)) continue;
    const FT_GlyphSlot g = face->glyph;
    const int x0 = x + g->bitmap_left, y0 = base - g->bitmap_top;
    for (unsigned r = 0; r < g->bitmap.rows; ++r)
      for (unsigned c = 0; c < g->bitmap.width; ++c) {
        const int px = x0 + static_cast<int>(c), py = y0 + static_cast<int>(r);
        if (px < 0 || py < 0 || px >= img.width || py >= img.height) continue;
        const float a = g->bitmap.buffer[r * static_cast<unsigned>(g->bitmap.pitch) + c] / 255.0f;
        std::uint8_t* d = &img.px[(static_cast<std::size_t>(py) * img.width + px) * 3];
        for (int k = 0; k < 3; ++k)
          d[k] = static_cast<std::uint8_t>(std::lround(d[k] * (1 - a) + 255.0f * colour[k] * a));
      }
    x += static_cast<int>(g->advance.x >> 6);
  }
  return x;
}

int TextPainter::width(const std::string& text) const {
  if (!impl_) return 0;
  int w = 0;
  for (unsigned char ch : text)
    if (ch >= 32 && ch <= 126 && !FT_Load_Char(impl_->face, ch, FT_LOAD_DEFAULT))
      w += static_cast<int>(impl_->face->glyph->advance.x >> 6);
  return w;
}
#else
struct TextPainter::Impl {};
TextPainter::TextPainter(int pixel_height) : why_("built without FreeType"), line_height_(pixel_height) {}
int TextPainter::draw(Rgb8&, int x, int, const std::string&, Vec3) const { return x; }
int TextPainter::width(const std::string&) const { return 0; }
#endif

TextPainter::~TextPainter() = default;
bool TextPainter::ok() const { return impl_ != nullptr; }

}  // namespace bhcl::render
