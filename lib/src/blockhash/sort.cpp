// Stage 1 of the block-hash build: the points in Hilbert order (sfc/hilbert.hpp, the curve's own
// module), each block's first key and the query-side quantiser. The stage-1 names build.hpp
// declares forward to the sfc module (build.hpp may declare them as aliases of sfc's instead).
#include <algorithm>

#include "blockhash/build.hpp"
#include "sfc/hilbert.hpp"

namespace bhcl::blockhash {
namespace {

sfc::Quantiser to_sfc(const Quantiser& q) {
  sfc::Quantiser s;
  for (int d = 0; d < 3; ++d) s.origin[d] = q.origin[d];
  s.scale = q.scale;
  s.bits = q.bits;
  return s;
}

}  // namespace

Quantiser make_quantiser(const float* xyz, std::size_t n, int bits) {
  const sfc::Quantiser s = sfc::make_quantiser(xyz, n, bits);
  Quantiser q;
  for (int d = 0; d < 3; ++d) q.origin[d] = s.origin[d];
  q.scale = s.scale;
  q.bits = s.bits;
  return q;
}

std::uint32_t Quantiser::cell(int dim, float v) const { return to_sfc(*this).cell(dim, v); }

std::uint64_t hilbert_encode(std::uint32_t x, std::uint32_t y, std::uint32_t z, int bits) {
  return sfc::hilbert_encode(x, y, z, bits);
}

void hilbert_decode(std::uint64_t key, int bits, std::uint32_t out[3]) { sfc::hilbert_decode(key, bits, out); }

std::vector<std::uint64_t> hilbert_keys(const float* xyz, std::size_t n, const Quantiser& q) {
  return sfc::hilbert_keys(xyz, n, to_sfc(q));
}

std::vector<std::int32_t> hilbert_order(const std::vector<std::uint64_t>& keys) { return sfc::hilbert_order(keys); }

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
