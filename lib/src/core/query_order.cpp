#include "core/query_order.hpp"

#include "blockhash_cl/spatial_order.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>

#include "core/parallel.hpp"
#include "sfc/hilbert.hpp"

namespace bhcl::detail {

namespace {

struct KeyedRow {
  std::uint64_t key;
  std::size_t row;
};

// Stable LSD radix sort by key (11-bit digits; a digit every key shares is skipped): equal keys
// keep their order, as the sort by (key, index) the build uses. `tmp` is scratch of v's size.
void radix_sort_by_key(KeyedRow* v, KeyedRow* tmp, std::size_t n, int key_bits) {
  constexpr int kDigit = 11;
  constexpr std::size_t kBuckets = std::size_t(1) << kDigit;
  std::vector<std::size_t> count(kBuckets);
  for (int shift = 0; shift < key_bits; shift += kDigit) {
    std::fill(count.begin(), count.end(), 0);
    for (std::size_t i = 0; i < n; ++i) ++count[(v[i].key >> shift) & (kBuckets - 1)];
    if (std::find(count.begin(), count.end(), n) != count.end()) continue;  // one digit for all
    std::size_t sum = 0;
    for (auto& c : count) {
      const std::size_t here = c;
      c = sum;
      sum += here;
    }
    for (std::size_t i = 0; i < n; ++i) tmp[count[(v[i].key >> shift) & (kBuckets - 1)]++] = v[i];
    std::copy(tmp, tmp + n, v);
  }
}

}  // namespace

std::vector<std::size_t> hilbert_query_order(const float* xyz, std::size_t n) {
  // One parallel pass for the queries' box (finite ones only), one for the keys, a radix sort of
  // each thread's part and a merge: the order of the stable sort by (key, index), at a few
  // milliseconds for 10^5 queries instead of tens.
  constexpr int kBits = 16;
  const unsigned threads = n < 16384 ? 1u : std::max(1u, std::min(default_threads(), 8u));
  const std::size_t per = (n + threads - 1) / threads;
  std::vector<std::array<double, 6>> boxes(threads, {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY});
  std::vector<std::size_t> finite_of(threads, 0);
  parallel_for(threads, [&](std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t) {
      auto& bx = boxes[t];
      for (std::size_t i = t * per; i < std::min(n, (t + 1) * per); ++i) {
        const float* q = xyz + 3 * i;
        if (!(std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]))) continue;
        ++finite_of[t];
        for (int d = 0; d < 3; ++d) {
          bx[d] = std::min(bx[d], double(q[d]));
          bx[3 + d] = std::max(bx[3 + d], double(q[d]));
        }
      }
    }
  }, threads, 1);
  std::size_t finite = 0;
  std::array<double, 6> box = boxes[0];
  for (unsigned t = 0; t < threads; ++t) {
    finite += finite_of[t];
    for (int d = 0; d < 3; ++d) {
      box[d] = std::min(box[d], boxes[t][d]);
      box[3 + d] = std::max(box[3 + d], boxes[t][3 + d]);
    }
  }
  std::vector<std::size_t> order(n);
  if (finite == 0) {
    for (std::size_t i = 0; i < n; ++i) order[i] = i;
    return order;
  }
  // The curve's quantiser over the finite queries' box (sfc::make_quantiser's rule).
  sfc::Quantiser qz;
  qz.bits = kBits;
  double extent = 0;
  for (int d = 0; d < 3; ++d) {
    qz.origin[d] = box[d];
    extent = std::max(extent, box[3 + d] - box[d]);
  }
  qz.scale = extent > 0 ? std::ldexp(1.0, kBits) / extent : 0.0;
  // Non-finite queries get the key past every finite one: last, in their own order.
  const std::uint64_t last = std::uint64_t(1) << (3 * kBits);
  std::vector<KeyedRow> rows(n), tmp(n);
  parallel_for(threads, [&](std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t) {
      const std::size_t lo = std::min(n, t * per), hi = std::min(n, (t + 1) * per);
      for (std::size_t i = lo; i < hi; ++i) {
        const float* q = xyz + 3 * i;
        const bool ok = std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]);
        rows[i] = {ok ? sfc::hilbert_encode(qz.cell(0, q[0]), qz.cell(1, q[1]), qz.cell(2, q[2]), kBits) : last, i};
      }
      radix_sort_by_key(rows.data() + lo, tmp.data() + lo, hi - lo, 3 * kBits + 1);
    }
  }, threads, 1);
  // The threads' sorted parts merged pairwise; on equal keys the earlier part first (smaller rows).
  auto by_key = [](const KeyedRow& a, const KeyedRow& b) { return a.key < b.key; };
  for (std::size_t width = per; width < n; width *= 2) {
    for (std::size_t lo = 0; lo < n; lo += 2 * width) {
      const std::size_t mid = std::min(n, lo + width), hi = std::min(n, lo + 2 * width);
      std::merge(rows.begin() + lo, rows.begin() + mid, rows.begin() + mid, rows.begin() + hi, tmp.begin() + lo, by_key);
    }
    rows.swap(tmp);
  }
  for (std::size_t i = 0; i < n; ++i) order[i] = rows[i].row;
  return order;
}

std::vector<float> queries_in_order(const float* xyz, const std::vector<std::size_t>& order) {
  std::vector<float> sorted(3 * order.size());
  for (std::size_t i = 0; i < order.size(); ++i)
    for (int d = 0; d < 3; ++d) sorted[3 * i + d] = xyz[3 * order[i] + d];
  return sorted;
}

}  // namespace bhcl::detail

namespace bhcl {

std::vector<std::size_t> hilbert_order(const float* xyz, std::size_t n) { return detail::hilbert_query_order(xyz, n); }

}  // namespace bhcl
