#include "compare.hpp"

#include <algorithm>
#include <cstdio>
#include <cmath>

#include "blockhash_cl/error.hpp"

namespace bhcl::render {
namespace {

// Turbo colour map (Google, 2019), polynomial approximation by its author; t in [0, 1].
Vec3 turbo(float t) {
  t = std::clamp(t, 0.0f, 1.0f);
  const float r = 0.13572138f + t * (4.61539260f + t * (-42.66032258f + t * (132.13108234f + t * (-152.94239396f + t * 59.28637943f))));
  const float g = 0.09140261f + t * (2.19418839f + t * (4.84296658f + t * (-14.18503333f + t * (4.27729857f + t * 2.82956604f))));
  const float b = 0.10667330f + t * (12.64194608f + t * (-60.58204836f + t * (110.36276771f + t * (-89.90310912f + t * 27.34824973f))));
  return {std::clamp(r, 0.0f, 1.0f), std::clamp(g, 0.0f, 1.0f), std::clamp(b, 0.0f, 1.0f)};
}

void check_sizes(const Image& a, const Image& b) {
  if (a.width != b.width || a.height != b.height)
    throw Error("image comparison: sizes differ (" + std::to_string(a.width) + "x" + std::to_string(a.height) +
                " vs " + std::to_string(b.width) + "x" + std::to_string(b.height) + ")");
}

}  // namespace

double mean_luminance(const Image& img) {
  double s = 0;
  for (std::size_t i = 0; i < img.pixels(); ++i) s += luminance(img.at(i));
  return img.pixels() ? s / img.pixels() : 0.0;
}


ImageDiff image_diff(const Image& a, const Image& ref) {
  check_sizes(a, ref);
  ImageDiff d;
  double se = 0, sum_ref = 0;
  for (std::size_t i = 0; i < a.rgb.size(); ++i) {
    double e = static_cast<double>(a.rgb[i]) - ref.rgb[i];
    se += e * e;
    sum_ref += ref.rgb[i];
    d.max_abs = std::max(d.max_abs, std::fabs(e));
  }
  const double n = static_cast<double>(a.rgb.size());
  d.rmse = n > 0 ? std::sqrt(se / n) : 0.0;
  d.relative_rmse = sum_ref > 0 ? d.rmse / (sum_ref / n) : 0.0;
  const double floor = 1e-3 * mean_luminance(ref);
  double rel = 0;
  for (std::size_t i = 0; i < a.pixels(); ++i) {
    double lr = luminance(ref.at(i));
    if (!(lr > floor)) continue;
    rel += std::fabs(luminance(a.at(i)) - lr) / lr;
    ++d.pixels_compared;
  }
  d.mean_rel_error = d.pixels_compared ? rel / d.pixels_compared : 0.0;
  return d;
}

Rgb8 false_colour_difference(const Image& a, const Image& ref, float max_rel) {
  check_sizes(a, ref);
  const float floor = static_cast<float>(0.01 * mean_luminance(ref));
  Rgb8 out(a.width, a.height);
  for (std::size_t i = 0; i < a.pixels(); ++i) {
    float lr = luminance(ref.at(i));
    float e = std::fabs(luminance(a.at(i)) - lr) / std::max(lr, std::max(floor, 1e-30f));
    Vec3 c = e == 0 ? Vec3{0, 0, 0} : turbo(max_rel > 0 ? e / max_rel : 0.0f);
    for (int k = 0; k < 3; ++k) out.px[3 * i + k] = static_cast<std::uint8_t>(std::lround(c[k] * 255.0f));
  }
  return out;
}

Rgb8 colour_scale(int width, int height) {
  Rgb8 out(width, height);
  for (int y = 0; y < height; ++y) {
    Vec3 c = turbo(height > 1 ? 1.0f - static_cast<float>(y) / (height - 1) : 0.0f);
    for (int x = 0; x < width; ++x)
      for (int k = 0; k < 3; ++k)
        out.px[(static_cast<std::size_t>(y) * width + x) * 3 + k] = static_cast<std::uint8_t>(std::lround(c[k] * 255.0f));
  }
  return out;
}

Rgb8 contact_sheet(const std::vector<std::vector<Rgb8>>& rows, int gap) {
  int tw = 0, th = 0;
  std::size_t cols = 0;
  for (const auto& r : rows) {
    cols = std::max(cols, r.size());
    for (const auto& t : r) {
      tw = std::max(tw, t.width);
      th = std::max(th, t.height);
    }
  }
  const int W = static_cast<int>(cols) * tw + (static_cast<int>(cols) + 1) * gap;
  const int H = static_cast<int>(rows.size()) * th + (static_cast<int>(rows.size()) + 1) * gap;
  Rgb8 sheet(W, H, 40);
  for (std::size_t r = 0; r < rows.size(); ++r)
    for (std::size_t c = 0; c < rows[r].size(); ++c)
      sheet.blit(rows[r][c], gap + static_cast<int>(c) * (tw + gap), gap + static_cast<int>(r) * (th + gap));
  return sheet;
}

float relative_error_percentile(const std::vector<const Image*>& images, const Image& ref, float q) {
  std::vector<float> e;
  const float floor = static_cast<float>(0.01 * mean_luminance(ref));
  for (const Image* a : images) {
    check_sizes(*a, ref);
    for (std::size_t i = 0; i < a->pixels(); ++i) {
      float lr = luminance(ref.at(i));
      float v = std::fabs(luminance(a->at(i)) - lr) / std::max(lr, std::max(floor, 1e-30f));
      if (std::isfinite(v)) e.push_back(v);
    }
  }
  if (e.empty()) return 0.0f;
  std::size_t k = std::min(e.size() - 1, static_cast<std::size_t>(std::clamp(q, 0.0f, 1.0f) * e.size()));
  std::nth_element(e.begin(), e.begin() + static_cast<std::ptrdiff_t>(k), e.end());
  return e[k];
}

Rgb8 labelled_sheet(const std::vector<std::vector<Panel>>& rows, int gap, const TextPainter& text) {
  std::size_t lines = 0;
  for (const auto& r : rows)
    for (const auto& p : r) lines = std::max(lines, p.lines.size());
  const int band = text.ok() ? static_cast<int>(lines) * text.line_height() + 2 : 0;
  std::vector<std::vector<Rgb8>> tiles;
  for (const auto& r : rows) {
    tiles.emplace_back();
    for (const auto& p : r) {
      Rgb8 t(p.image.width, p.image.height + band, 40);
      t.blit(p.image, 0, band);
      for (std::size_t l = 0; l < p.lines.size(); ++l)
        text.draw(t, 1, static_cast<int>(l) * text.line_height(), p.lines[l], Vec3{1, 1, 1});
      tiles.back().push_back(std::move(t));
    }
  }
  return contact_sheet(tiles, gap);
}

Rgb8 labelled_colour_scale(int width, int height, float max_rel, const TextPainter& text) {
  const int swatch = std::max(std::max(4, height / 16), text.line_height());  // black: "exactly 0"
  const int bar_w = std::max(6, width / 4);
  const int bar_h = std::max(2, height - swatch - 2);
  Rgb8 out(width, height, 40);
  Rgb8 bar = colour_scale(bar_w, bar_h);
  out.blit(bar, 0, 0);
  out.blit(Rgb8(bar_w, swatch, 0), 0, height - swatch);
  const int lh = text.line_height();
  for (int t = 0; t <= 4; ++t) {
    const int y = (bar_h - 1) - t * (bar_h - 1) / 4;  // the tick's row
    for (int x = bar_w; x < std::min(width, bar_w + 3); ++x)
      for (int k = 0; k < 3; ++k) out.px[(static_cast<std::size_t>(y) * width + x) * 3 + k] = 255;
    char b[32];
    std::snprintf(b, sizeof b, "%.3g%%", 100.0 * max_rel * t / 4);
    // The 0 tick's label sits above its tick, clear of the swatch's label below it.
    text.draw(out, bar_w + 4, std::clamp(t == 0 ? y - lh : y - lh / 2, 0, std::max(0, height - lh)), b,
              Vec3{1, 1, 1});
  }
  text.draw(out, bar_w + 4, height - swatch, "black: exactly 0", Vec3{0.8f, 0.8f, 0.8f});
  return out;
}

BlockError block_error(const Image& img, const Image& ref, int b) {
  check_sizes(img, ref);
  if (b < 1) throw Error("block_error: the block size must be >= 1");
  std::vector<float> lum(ref.pixels());
  for (std::size_t i = 0; i < ref.pixels(); ++i) lum[i] = luminance(ref.at(i));
  std::vector<float> sorted = lum;
  std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
  const float bright = 8.0f * sorted[sorted.size() / 2];
  BlockError out;
  double se = 0, sum_ref = 0, sum_img = 0, kept_pixels = 0;
  for (int by = 0; by < ref.height; by += b)
    for (int bx = 0; bx < ref.width; bx += b) {
      double a = 0, r = 0;
      bool emitter = false;
      int n = 0;
      for (int y = by; y < std::min(ref.height, by + b); ++y)
        for (int x = bx; x < std::min(ref.width, bx + b); ++x, ++n) {
          const std::size_t i = static_cast<std::size_t>(y) * ref.width + x;
          emitter = emitter || lum[i] > bright;
          a += luminance(img.at(i));
          r += lum[i];
        }
      if (emitter) {
        ++out.blocks_left_out;
        continue;
      }
      ++out.blocks;
      if (r > 0 && std::fabs(a - r) / r > out.worst_relative) {
        out.worst_relative = std::fabs(a - r) / r;
        out.worst_x = bx;
        out.worst_y = by;
      }
      kept_pixels += n;
      se += (a - r) * (a - r) / (static_cast<double>(n) * n);
      sum_ref += r;
      sum_img += a;
    }
  if (out.blocks > 0 && sum_ref > 0) {
    out.relative_rmse = std::sqrt(se / out.blocks) / (sum_ref / kept_pixels);
    out.mean_bias = (sum_img - sum_ref) / sum_ref;
  }
  return out;
}

}  // namespace bhcl::render
