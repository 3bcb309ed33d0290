// Text on the comparison sheets: FreeType rasterising a TrueType font (DejaVu Sans from Debian's
// fonts-dejavu-core), so that panels carry their method, A, timings and errors.
#pragma once

#include <memory>
#include <string>

#include "png_io.hpp"
#include "vec.hpp"

namespace bhcl::render {

class TextPainter {
 public:
  // Loads the font: $BHCL_FONT when set, else DejaVu Sans from the usual Debian and other paths.
  // Never throws: without FreeType (not found at build time) or without a font, ok() is false,
  // why() says which, and draw() draws nothing (the sheet is still written, unlabelled).
  explicit TextPainter(int pixel_height);
  ~TextPainter();
  TextPainter(const TextPainter&) = delete;
  TextPainter& operator=(const TextPainter&) = delete;

  bool ok() const;
  const std::string& why() const { return why_; }
  int line_height() const { return line_height_; }
  // Draws `text` (ASCII; other bytes are skipped) with the top of its line at y, alpha-blended,
  // clipped to the image. Returns the x after the last glyph.
  int draw(Rgb8& image, int x, int y, const std::string& text, Vec3 colour) const;
  int width(const std::string& text) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  std::string why_;
  int line_height_;
};

}  // namespace bhcl::render
