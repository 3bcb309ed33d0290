// Linear images as OpenEXR: half-float R, G, B channels, ZIP compression.
#pragma once

#include <string>

#include "film.hpp"

namespace bhcl::render {

// Throws bhcl::Error naming the file on failure.
void write_exr(const std::string& path, const Image& image);
Image read_exr(const std::string& path);  // any R, G, B channels (missing ones read as 0)

}  // namespace bhcl::render
