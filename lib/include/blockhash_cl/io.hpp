// Point files: raw little-endian float32, N x 3 (x y z per point), no header; N = size / 12.
// Result files: raw int32 / float32, n x k row-major.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace bhcl {

// Reads a point file. Throws bhcl::Error naming the path for a missing/unreadable file, a size
// that is not a multiple of 12 bytes, or (when require_finite) the first point with a NaN/Inf
// coordinate. An empty file gives an empty vector.
std::vector<float> read_points_file(const std::string& path, bool require_finite = true);

// Parses the bytes of a point file (what read_points_file does after reading); `what` names the
// source in errors. The fuzz target drives this.
std::vector<float> parse_points(const void* data, std::size_t size, const std::string& what,
                                bool require_finite = true);

void write_points_file(const std::string& path, const std::vector<float>& xyz);

// Writes raw bytes; throws bhcl::Error naming the path on failure.
void write_raw_file(const std::string& path, const void* data, std::size_t bytes);

}  // namespace bhcl
