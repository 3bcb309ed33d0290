// Stage 1 of the block-hash build: the points in Hilbert order (sfc/hilbert.hpp, the curve's own
// module, whose names build.hpp brings into the stage), each block's first key and the
// query-side quantiser.
#include <algorithm>

#include "blockhash/build.hpp"
#include "sfc/hilbert.hpp"

namespace bhcl::blockhash {

std::uint64_t query_hilbert_key(const Structure& s, const float q[3]) {
  const float top = float((1u << s.q_bits) - 1);
  std::uint32_t c[3];
  for (int d = 0; d < 3; ++d) {
    float v = std::floor((q[d] - s.q_origin[d]) * s.q_scale);
    if (!(v > 0.0f)) v = 0.0f;  // also NaN (inf * 0)
    if (v > top) v = top;
    c[d] = static_cast<std::uint32_t>(v);
  }
  return hilbert_encode(c[0], c[1], c[2], s.q_bits);
}

void sort_points(const float* xyz, std::size_t n, int bits, Structure& s) {
  Quantiser q = make_quantiser(xyz, n, bits);
  std::vector<std::uint64_t> keys = hilbert_keys(xyz, n, q);
  s.order = hilbert_order(keys);
  const std::size_t X = static_cast<std::size_t>(s.info.X);
  s.block_keys.resize((n + X - 1) / X);
  for (std::size_t b = 0; b < s.block_keys.size(); ++b) s.block_keys[b] = keys[s.order[b * X]];
  for (int d = 0; d < 3; ++d) s.q_origin[d] = static_cast<float>(q.origin[d]);
  // Finite even for a 1e-38-wide box (the clamp then maps every query to the grid's edge cells).
  s.q_scale = static_cast<float>(std::min(q.scale, 3.0e38));
  s.q_bits = q.bits;
}

}  // namespace bhcl::blockhash
