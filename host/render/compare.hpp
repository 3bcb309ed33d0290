// Image comparison for "does block hashing change the picture?": error metrics of a render
// against the exact one, false-colour difference images and a side-by-side sheet.
#pragma once

#include <string>
#include <vector>

#include "film.hpp"
#include "png_io.hpp"

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

// Per-pixel relative luminance error |lum(a) - lum(ref)| / max(lum(ref), floor) shown with the
// Turbo colour map, 0 (dark blue) to `max_rel` (dark red); floor = 1% of the mean luminance.
Rgb8 false_colour_difference(const Image& a, const Image& reference, float max_rel);
// A vertical colour-scale strip (bottom 0, top max) of the same map.
Rgb8 colour_scale(int width, int height);

// Rows of equally sized tiles, `gap` pixels apart on a dark grey background.
Rgb8 contact_sheet(const std::vector<std::vector<Rgb8>>& rows, int gap);

}  // namespace bhcl::render
