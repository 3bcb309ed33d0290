// The 3D Hilbert curve (sfc/hilbert.hpp): positions quantised in the bounding box, Hilbert keys,
// and the stable sort by (key, original index) that makes every use deterministic.
#include <algorithm>
#include <cmath>
#include <numeric>

#include "sfc/hilbert.hpp"

#include "bhcl_arith.h"
#include "blockhash_cl/error.hpp"
#include "core/parallel.hpp"

namespace bhcl::sfc {

Quantiser make_quantiser(const float* xyz, std::size_t n, int bits) {
  if (bits < 1 || bits > 21) throw Error("hilbert_bits must be in [1, 21], got " + std::to_string(bits));
  Quantiser q;
  q.bits = bits;
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (std::size_t i = 0; i < n; ++i)
    for (int d = 0; d < 3; ++d) {
      double v = xyz[3 * i + d];
      lo[d] = std::min(lo[d], v);
      hi[d] = std::max(hi[d], v);
    }
  double extent = 0;
  for (int d = 0; d < 3; ++d) {
    q.origin[d] = n ? lo[d] : 0.0;
    if (n) extent = std::max(extent, hi[d] - lo[d]);  // double: no overflow for any finite floats
  }
  // One scale for all axes: a flat or thin box keeps its aspect, so Hilbert order stays local in
  // space; an all-equal point set (extent 0) maps everything to cell 0.
  q.scale = extent > 0 ? std::ldexp(1.0, bits) / extent : 0.0;
  return q;
}

std::uint32_t Quantiser::cell(int dim, float v) const {
  double c = std::floor((double(v) - origin[dim]) * scale);
  double top = std::ldexp(1.0, bits) - 1;
  if (!(c > 0)) return 0;  // also catches NaN
  return static_cast<std::uint32_t>(std::min(c, top));
}

// The kernels' bh_hilbert_encode (kernels/bhcl_arith.h): one definition for host and device.
std::uint64_t hilbert_encode(std::uint32_t x, std::uint32_t y, std::uint32_t z, int bits) {
  return bh_hilbert_encode(x, y, z, static_cast<std::uint32_t>(bits));
}

void hilbert_decode(std::uint64_t key, int bits, std::uint32_t out[3]) {
  std::uint32_t X[3] = {0, 0, 0};
  for (int b = bits - 1; b >= 0; --b)
    for (int i = 0; i < 3; ++i) {
      int shift = 3 * b + (2 - i);
      X[i] |= std::uint32_t((key >> shift) & 1u) << b;
    }
  const std::uint32_t N = 2u << (bits - 1);
  std::uint32_t t = X[2] >> 1;
  for (int i = 2; i > 0; --i) X[i] ^= X[i - 1];
  X[0] ^= t;
  for (std::uint32_t Q = 2; Q != N; Q <<= 1) {
    std::uint32_t P = Q - 1;
    for (int i = 2; i >= 0; --i) {
      if (X[i] & Q) {
        X[0] ^= P;
      } else {
        std::uint32_t s = (X[0] ^ X[i]) & P;
        X[0] ^= s;
        X[i] ^= s;
      }
    }
  }
  out[0] = X[0];
  out[1] = X[1];
  out[2] = X[2];
}

std::vector<std::uint64_t> hilbert_keys(const float* xyz, std::size_t n, const Quantiser& q) {
  std::vector<std::uint64_t> keys(n);
  detail::parallel_for(n, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i)
      keys[i] = hilbert_encode(q.cell(0, xyz[3 * i]), q.cell(1, xyz[3 * i + 1]),
                               q.cell(2, xyz[3 * i + 2]), q.bits);
  });
  return keys;
}

std::vector<std::int32_t> hilbert_order(const std::vector<std::uint64_t>& keys) {
  // Sort (key, index) pairs: equal keys (duplicates, or points sharing a grid cell) keep the
  // caller's order, so the build is deterministic.
  std::vector<std::pair<std::uint64_t, std::int32_t>> kv(keys.size());
  for (std::size_t i = 0; i < keys.size(); ++i) kv[i] = {keys[i], static_cast<std::int32_t>(i)};
  // Two halves sorted in parallel, then merged: the same total order as one sort.
  const std::size_t half = kv.size() / 2;
  if (kv.size() >= (std::size_t(1) << 16) && detail::default_threads() > 1) {
    detail::parallel_for(2, [&](std::size_t b, std::size_t) {
      if (b == 0) std::sort(kv.begin(), kv.begin() + half);
      else std::sort(kv.begin() + half, kv.end());
    }, 2, 1);
    std::inplace_merge(kv.begin(), kv.begin() + half, kv.end());
  } else {
    std::sort(kv.begin(), kv.end());
  }
  std::vector<std::int32_t> order(keys.size());
  for (std::size_t i = 0; i < kv.size(); ++i) order[i] = kv[i].second;
  return order;
}

}  // namespace bhcl::sfc
