// The 3D Hilbert curve, a module of its own that any layer may use: positions quantised in a
// bounding box, Hilbert keys (Skilling's transpose algorithm, the kernels' bh_hilbert_encode), and
// the stable sort by (key, index) that makes every use deterministic. Block hashing's build sorts
// its points with it (stage 1), the query path sorts query batches with it (core/query_order.cpp).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace bhcl::sfc {

// Maps coordinates to a 2^bits grid over the points' bounding box. One scale for all three axes
// (the largest extent), so a flat box keeps its shape and a zero extent maps to cell 0; computed in
// double from the offset to the box's corner, so tiny, huge and far-offset boxes keep their
// resolution.
struct Quantiser {
  double origin[3] = {0, 0, 0};
  double scale = 0;  // cells per unit length
  int bits = 21;
  std::uint32_t cell(int dim, float v) const;
};
// Throws bhcl::Error for bits outside [1, 21].
Quantiser make_quantiser(const float* xyz, std::size_t n, int bits);

// The Hilbert index of grid cell (x, y, z), each < 2^bits, bits <= 21. hilbert_decode is its inverse.
std::uint64_t hilbert_encode(std::uint32_t x, std::uint32_t y, std::uint32_t z, int bits);
void hilbert_decode(std::uint64_t key, int bits, std::uint32_t out[3]);

std::vector<std::uint64_t> hilbert_keys(const float* xyz, std::size_t n, const Quantiser& q);
// The permutation that sorts by (key, original index): order[i] = original index of the i-th point.
std::vector<std::int32_t> hilbert_order(const std::vector<std::uint64_t>& keys);

}  // namespace bhcl::sfc
