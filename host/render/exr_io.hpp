// Linear images as OpenEXR: R, G, B channels, ZIP compression; half floats when every value fits
// the half range, else float32 channels (as pbrt writes), so radiance above 65504 (a bright
// emitter seen directly) is kept, never turned into +inf.
#pragma once

#include <string>

#include "film.hpp"

namespace bhcl::render {

// Auto: half unless a finite value exceeds the half range (then float32). Half: half always (a
// warning on stderr when values become +inf). Float: float32 always.
enum class ExrPixels { Auto, Half, Float };
// True when a finite value of the image is beyond the half-float range.
bool needs_float_exr(const Image& image);
// Written atomically (bhcl::write_file); throws bhcl::Error naming the file and the reason.
void write_exr(const std::string& path, const Image& image, ExrPixels pixels = ExrPixels::Auto);
Image read_exr(const std::string& path);  // any R, G, B channels (missing ones read as 0)

}  // namespace bhcl::render
