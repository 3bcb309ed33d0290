// Image comparison for "does block hashing change the picture?": error metrics of a render
// against the exact one, false-colour difference images and a side-by-side sheet.
#pragma once

#include <string>
#include <vector>

#include "film.hpp"
#include "png_io.hpp"
#include "text.hpp"

namespace bhcl::render {

struct ImageDiff {
  double rmse = 0;            // over all pixels and channels, linear radiance
  double relative_rmse = 0;   // rmse / mean of the reference
  double mean_rel_error = 0;  // mean over pixels of |lum(a) - lum(ref)| / lum(ref), pixels with
                              // lum(ref) > 1e-3 x mean luminance (black pixels would divide by 0)
  double max_abs = 0;         // largest channel difference
  std::size_t pixels_compared = 0;
};

// Throws bhcl::Error when the sizes differ.
ImageDiff image_diff(const Image& a, const Image& reference);

double mean_luminance(const Image& img);  // 0 for an empty image

// An image against a reference on blocks of b x b pixels, leaving out every block in which the
// reference sees an emitter (a pixel brighter than 8x the median luminance). Averaging over a block
// removes most of a render's per-pixel noise and keeps what a density estimator gets wrong (blur
// at corners and edges, dark bands by walls); the emitter's edge, sampled once per pixel against
// the reference's thousands, would swamp both.
struct BlockError {
  double relative_rmse = 0;  // of block luminance, over the mean reference block luminance
  double mean_bias = 0;      // (sum of luminance - the reference's) / the reference's, kept blocks
  // The kept block farthest from the reference: |block - reference block| / reference block (blocks
  // whose reference is black left out of this one), and its top-left pixel.
  double worst_relative = 0;
  int worst_x = -1, worst_y = -1;
  std::size_t blocks = 0, blocks_left_out = 0;
};
// Throws bhcl::Error when the sizes differ or b < 1.
BlockError block_error(const Image& img, const Image& reference, int b);

// Per-pixel relative luminance error |lum(a) - lum(ref)| / max(lum(ref), floor) shown with the
// Turbo colour map, 0 (dark blue) to `max_rel` (dark red); floor = 1% of the mean luminance.
// A pixel whose error is exactly 0 is black, so that "identical" stands apart from "small".
Rgb8 false_colour_difference(const Image& a, const Image& reference, float max_rel);
// A vertical colour-scale strip (bottom 0, top max) of the same map.
Rgb8 colour_scale(int width, int height);

// Rows of equally sized tiles, `gap` pixels apart on a dark grey background.
Rgb8 contact_sheet(const std::vector<std::vector<Rgb8>>& rows, int gap);

// The given percentile (0 to 1) of the per-pixel relative errors of false_colour_difference,
// over all the images given (0 when there are none): an automatic full scale.
float relative_error_percentile(const std::vector<const Image*>& images, const Image& reference, float q);

// A tile with its lines of text in a band above it.
struct Panel {
  Rgb8 image;
  std::vector<std::string> lines;
};
// Rows of panels (the text band as tall as the most lines any panel has); unlabelled when the
// painter is not ok().
Rgb8 labelled_sheet(const std::vector<std::vector<Panel>>& rows, int gap, const TextPainter& text);
// The colour scale with numbers: ticks at 0, 25, 50, 75 and 100 % of max_rel (in per cent), and
// a black swatch at the bottom for "exactly 0".
Rgb8 labelled_colour_scale(int width, int height, float max_rel, const TextPainter& text);

}  // namespace bhcl::render
