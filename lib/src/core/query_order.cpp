#include "core/query_order.hpp"

#include "blockhash_cl/spatial_order.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <utility>

#include "core/parallel.hpp"
#include "sfc/hilbert.hpp"

namespace bhcl::detail {

namespace {

// The keys share the order's storage (written over them at the end): 64-bit size_t.
using Key = std::size_t;
static_assert(sizeof(Key) == 8, "the Hilbert keys are 49 bits");

struct KeyedRow {
  std::uint64_t key;
  std::size_t row;
};

// Stable LSD radix sort by key (11-bit digits; a digit every key shares is skipped): equal keys
// keep their order, as the sort by (key, index) the build uses. `tmp` is scratch of v's size.
// Every digit's histogram in one pass, and the two arrays swap roles pass by pass (one copy at
// the end when the result lies in tmp): the passes only scatter.
void radix_sort_by_key(KeyedRow* v, KeyedRow* tmp, std::size_t n, int key_bits) {
  constexpr int kDigit = 11;
  constexpr std::size_t kBuckets = std::size_t(1) << kDigit;
  const int digits = (key_bits + kDigit - 1) / kDigit;
  std::vector<std::size_t> count(kBuckets * static_cast<std::size_t>(digits), 0);
  for (std::size_t i = 0; i < n; ++i)
    for (int d = 0; d < digits; ++d) ++count[d * kBuckets + ((v[i].key >> (d * kDigit)) & (kBuckets - 1))];
  KeyedRow *from = v, *to = tmp;
  for (int d = 0; d < digits; ++d) {
    std::size_t* c = &count[d * kBuckets];
    if (std::find(c, c + kBuckets, n) != c + kBuckets) continue;  // one digit for all
    std::size_t sum = 0;
    for (std::size_t j = 0; j < kBuckets; ++j) {
      const std::size_t here = c[j];
      c[j] = sum;
      sum += here;
    }
    const int shift = d * kDigit;
    for (std::size_t i = 0; i < n; ++i) to[c[(from[i].key >> shift) & (kBuckets - 1)]++] = from[i];
    std::swap(from, to);
  }
  if (from != v) std::copy(from, from + n, v);
}

// The stable order by key of n keys below 2^49, n < 2^31, in parallel passes without a merge:
// each thread's histogram of the keys' top bits (KeyBuckets; counted by the key pass as it makes
// them, count_buckets); a stable scatter into those buckets of one word per query, (the key's
// lower bits, the query's index), so that sorting a bucket's words sorts it by (key, index); each
// bucket sorted on its own (a few dozen words at 1M queries) and its indices written out. Half
// the bytes of (key, row) pairs, and no pass is single-threaded.
constexpr int kKeyBits = 49;  // 3 x 16 bits, and the non-finite queries' key 2^48
bool fits_bucket_words(std::size_t n) { return n < (std::size_t(1) << 31); }

// The buckets of n keys: their top bits, about 64 queries a bucket (sort_words sorts them by
// radix), at most 2^16. At 8 a bucket the scatter's stores went to as many lines as queries on
// uniform queries, and surface queries left most buckets empty. With sort_words' 6-bit levels and
// the vector box pass, the whole order took 0.66-0.89 of the time before at 100k and 303k queries
// and 0.68-0.95 at 1M (Cornell, Autzen, uniform; AVX-512 Xeon, 2 threads;
// bench/results/e2e/query_order_s16.txt).
struct KeyBuckets {
  explicit KeyBuckets(std::size_t n) {
    while (top_bits < 16 && (std::size_t(1) << top_bits) < n / 64) ++top_bits;
  }
  int top_bits = 1;
  int low_bits() const { return kKeyBits - top_bits; }
  std::size_t count() const { return std::size_t(1) << top_bits; }
  std::size_t of(std::uint64_t key) const { return static_cast<std::size_t>(key >> low_bits()); }
};

// Keys [lo, hi) counted into their buckets (c: count() entries).
void count_buckets(const KeyBuckets& kb, const Key* keys, std::size_t lo, std::size_t hi, std::size_t* c) {
  for (std::size_t i = lo; i < hi; ++i) ++c[kb.of(keys[i])];
}

// Words [w, w + m) sorted in place, their top `bits` bits (from bit `top` down) still unsorted:
// where more than kSubMin, a stable counting pass by the next kSubBits of them into tmp and back,
// then each sub-run likewise (an MSD radix sort); fewer, an insertion sort (std::sort past
// kSubMin where the bits ran out). 6-bit levels (2 bits an axis) leave runs of a few queries even
// in the buckets surfaces crowd; 8-bit levels down to 64 and std::sort below had made the
// in-bucket sort half of the order's time (std::sort's calls on runs of tens).
constexpr int kSubBits = 6;
constexpr std::size_t kSubMin = 16;
inline void insertion_sort(std::uint64_t* w, std::size_t m) {
  for (std::size_t i = 1; i < m; ++i) {
    const std::uint64_t v = w[i];
    std::size_t j = i;
    for (; j > 0 && w[j - 1] > v; --j) w[j] = w[j - 1];
    w[j] = v;
  }
}
void sort_words(std::uint64_t* w, std::size_t m, int top, int bits, std::uint64_t* tmp) {
  if (m <= kSubMin) return insertion_sort(w, m);
  if (bits < kSubBits) return std::sort(w, w + m);
  const int shift = top - kSubBits;
  constexpr std::uint64_t mask = (1u << kSubBits) - 1;
  std::uint32_t start[(1u << kSubBits) + 1] = {};
  for (std::size_t j = 0; j < m; ++j) ++start[((w[j] >> shift) & mask) + 1];
  for (std::size_t s = 1; s <= (1u << kSubBits); ++s) start[s] += start[s - 1];
  std::uint32_t at[1u << kSubBits];
  std::copy(start, start + (1u << kSubBits), at);
  for (std::size_t j = 0; j < m; ++j) tmp[at[(w[j] >> shift) & mask]++] = w[j];
  std::copy(tmp, tmp + m, w);
  for (std::size_t s = 0; s < (1u << kSubBits); ++s)
    if (start[s + 1] - start[s] > 1) sort_words(w + start[s], start[s + 1] - start[s], shift, bits - kSubBits, tmp);
}

// pos: thread t's histogram at t * kb.count(), of keys [t * per, (t + 1) * per) with
// per = ceil(n / threads) (the key pass's split); used up here. The order is written over the
// keys (`keys`: n entries) once the scatter has read them (8 bytes a query of fresh pages fewer).
void order_by_buckets(Key* keys, std::size_t n, unsigned threads, const KeyBuckets& kb, std::vector<std::size_t>& pos,
                      const OrderSink* sink) {
  const int low_bits = kb.low_bits(), row_bits = 64 - low_bits;  // row_bits = 15 + top bits: n fits
  const std::uint64_t low_mask = (std::uint64_t(1) << low_bits) - 1, row_mask = (std::uint64_t(1) << row_bits) - 1;
  const std::size_t buckets = kb.count(), per = (n + threads - 1) / threads;
  std::vector<std::size_t> bucket_start(buckets + 1);
  std::size_t sum = 0;
  for (std::size_t b = 0; b < buckets; ++b) {
    bucket_start[b] = sum;
    for (unsigned t = 0; t < threads; ++t) {
      const std::size_t c = pos[t * buckets + b];
      pos[t * buckets + b] = sum;  // thread t's queries of bucket b after those of threads before it
      sum += c;
    }
  }
  bucket_start[buckets] = n;
  // Not value-initialised: its pages are first touched by the scatter's threads, not by one memset.
  std::unique_ptr<std::uint64_t[]> words(new std::uint64_t[n]);
  parallel_for(threads, [&](std::size_t tb0, std::size_t te) {
    for (std::size_t t = tb0; t < te; ++t) {
      std::size_t* at = &pos[t * buckets];
      for (std::size_t i = std::min(n, t * per), e = std::min(n, (t + 1) * per); i < e; ++i)
        words[at[keys[i] >> low_bits]++] = ((keys[i] & low_mask) << row_bits) | i;
    }
  }, threads, 1);
  std::size_t* order = keys;  // the keys are read no more
  // Buckets handed out in chunks: surface data fills some buckets and leaves most empty.
  parallel_chunks(buckets, 256, threads, [&](std::size_t, std::size_t lo, std::size_t hi) {
    std::vector<std::uint64_t> tmp;
    for (std::size_t b = lo; b < hi; ++b) {
      const std::size_t b0 = bucket_start[b], m = bucket_start[b + 1] - b0;
      if (tmp.size() < m) tmp.resize(m);
      // The words' top low_bits bits are the key's below the bucket's: those left to sort.
      sort_words(words.get() + b0, m, 64, low_bits, tmp.data());
      for (std::size_t j = b0; j < b0 + m; ++j) order[j] = words[j] & row_mask;
    }
    if (sink && bucket_start[hi] > bucket_start[lo]) (*sink)(bucket_start[lo], bucket_start[hi], order);
  });
}

}  // namespace

namespace {

// Bit b of v (16 bits) moved to bit 3b.
inline std::uint64_t spread3(std::uint64_t v) {
  v &= 0xffff;
  v = (v | (v << 32)) & 0x1f00000000ffffull;
  v = (v | (v << 16)) & 0x1f0000ff0000ffull;
  v = (v | (v << 8)) & 0x100f00f00f00f00full;
  v = (v | (v << 4)) & 0x10c30c30c30c30c3ull;
  v = (v | (v << 2)) & 0x1249249249249249ull;
  return v;
}

// Skilling's transpose as kernels/bhcl_arith.h's bh_hilbert_encode at 16 bits, for m <= kLanes
// cells at once: a mask instead of each of its tests, and the lanes innermost, so that the
// compiler runs the lanes in vector registers (one key is a chain of 45 dependent steps; lanes
// are independent). Bit b of axis i goes to key bit 3b + (2 - i). 32 lanes: two AVX-512 or four
// AVX2 registers an axis, whose chains the core overlaps; 16 lanes (one chain) had left it waiting
// on each step's latency: 1M Cornell keys on one thread of an AVX-512 EPYC, 16 / 32 / 64 lanes,
// AVX-512 clone 11.2 / 7.8 / 7.0 ms, AVX2 clone 9.9 / 8.1 / 8.5 ms (bench/results/e2e/query_keys.md).
constexpr std::size_t kLanes = 32;
inline void hilbert_keys16_lanes(const std::uint32_t* x0, const std::uint32_t* x1, const std::uint32_t* x2,
                          Key* keys, std::size_t m) {
  std::uint32_t X0[kLanes] = {}, X1[kLanes] = {}, X2[kLanes] = {};
  for (std::size_t l = 0; l < m; ++l) {
    X0[l] = x0[l];
    X1[l] = x1[l];
    X2[l] = x2[l];
  }
  for (std::uint32_t Q = 1u << 15; Q > 1; Q >>= 1) {
    const std::uint32_t P = Q - 1;
    for (std::size_t l = 0; l < kLanes; ++l) {
      std::uint32_t a = X0[l], b = X1[l], c = X2[l];
      a ^= P & (0u - ((a & Q) != 0));
      std::uint32_t set = 0u - ((b & Q) != 0), t = (a ^ b) & P & ~set;
      a ^= (P & set) | t;
      b ^= t;
      set = 0u - ((c & Q) != 0);
      t = (a ^ c) & P & ~set;
      a ^= (P & set) | t;
      c ^= t;
      X0[l] = a;
      X1[l] = b;
      X2[l] = c;
    }
  }
  for (std::size_t l = 0; l < kLanes; ++l) {
    X1[l] ^= X0[l];
    X2[l] ^= X1[l];
    std::uint32_t t = 0;
    for (std::uint32_t Q = 1u << 15; Q > 1; Q >>= 1) t ^= (Q - 1) & (0u - ((X2[l] & Q) != 0));
    X0[l] ^= t;
    X1[l] ^= t;
    X2[l] ^= t;
  }
  for (std::size_t l = 0; l < m; ++l) keys[l] = (spread3(X0[l]) << 2) | (spread3(X1[l]) << 1) | spread3(X2[l]);
}

// The quantiser's cell at 16 bits (sfc::Quantiser::cell without its per-call ldexp): the
// truncation is the floor where c > 0, and c <= 0 (or NaN) is cell 0, so no floor call; through
// int32 (the value is at most 65535), which AVX2 converts from double in a vector and uint32 not.
inline std::uint32_t cell16(double c) {
  return c > 0 ? static_cast<std::uint32_t>(static_cast<std::int32_t>(std::min(c, 65535.0))) : 0u;
}

// std::isfinite by the exponent's bits: a vector compare where the call had kept the cells' loop
// scalar (with it, the cells were a third of the keys' time).
inline bool finite_bits(float v) {
  std::uint32_t b;
  std::memcpy(&b, &v, sizeof b);
  return (b & 0x7f800000u) != 0x7f800000u;
}

// The library is built for the baseline x86-64 (SSE2: four 32-bit lanes); the keys, a chain of
// vector steps per kLanes queries, are also compiled for AVX2 and AVX-512 and the CPU's picked at
// load (GCC/Clang function multiversioning, glibc's ifunc): on one thread of an AVX-512 EPYC, 1M
// keys in 7.8 ms against 16 for the SSE2 code. The same keys on every path (integer steps; the
// cells' doubles are exact).
#if defined(__x86_64__) && defined(__GLIBC__) && (!defined(__clang__) || __clang_major__ >= 14)
#define BHCL_KEY_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define BHCL_KEY_CLONES
#endif

// The box of the finite queries of [lo, hi) (in float: the box of floats is exact in float) and
// their count, kLanes at a time: a query with a non-finite coordinate enters as +inf on the low
// side and -inf on the high side, a select where the branch past it had kept the loop scalar
// (0.55 -> 0.1 ms for 303k Cornell queries on 2 threads of the AVX-512 Xeon).
BHCL_KEY_CLONES void box_of_range(const float* xyz, std::size_t lo, std::size_t hi, std::array<float, 6>& box,
                                  std::size_t& finite) {
  float mn[3][kLanes], mx[3][kLanes];
  std::uint32_t cnt[kLanes];
  for (std::size_t l = 0; l < kLanes; ++l) {
    cnt[l] = 0;
    for (int d = 0; d < 3; ++d) mn[d][l] = INFINITY, mx[d][l] = -INFINITY;
  }
  std::size_t i0 = lo;
  for (; i0 + kLanes <= hi; i0 += kLanes) {
    const float* q = xyz + 3 * i0;
    float p[3][kLanes];
    for (std::size_t l = 0; l < kLanes; ++l) p[0][l] = q[3 * l], p[1][l] = q[3 * l + 1], p[2][l] = q[3 * l + 2];
    for (std::size_t l = 0; l < kLanes; ++l) {
      const bool ok = finite_bits(p[0][l]) & finite_bits(p[1][l]) & finite_bits(p[2][l]);
      cnt[l] += ok;
      for (int d = 0; d < 3; ++d) {
        const float a = ok ? p[d][l] : INFINITY, b = ok ? p[d][l] : -INFINITY;
        mn[d][l] = a < mn[d][l] ? a : mn[d][l];
        mx[d][l] = b > mx[d][l] ? b : mx[d][l];
      }
    }
  }
  std::size_t count = 0;
  float out[6] = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
  for (std::size_t l = 0; l < kLanes; ++l) {
    count += cnt[l];
    for (int d = 0; d < 3; ++d) out[d] = std::min(out[d], mn[d][l]), out[3 + d] = std::max(out[3 + d], mx[d][l]);
  }
  for (std::size_t i = i0; i < hi; ++i) {  // the tail
    const float* q = xyz + 3 * i;
    if (!(finite_bits(q[0]) & finite_bits(q[1]) & finite_bits(q[2]))) continue;
    ++count;
    for (int d = 0; d < 3; ++d) out[d] = std::min(out[d], q[d]), out[3 + d] = std::max(out[3 + d], q[d]);
  }
  for (int d = 0; d < 6; ++d) box[d] = out[d];
  finite = count;
}

// Keys of queries [lo, hi) (non-finite ones `last`), kLanes at a time, every lane computed (the
// tail's spare lanes repeat its first query) so that no lane test breaks the vector loop. The
// coordinates first split by axis (a whole block's stride-3 loads vectorise), then the cells.
BHCL_KEY_CLONES void hilbert_keys_of_range(const float* xyz, std::size_t lo, std::size_t hi,
                                           const sfc::Quantiser& qz, Key last, Key* keys) {
  const double o0 = qz.origin[0], o1 = qz.origin[1], o2 = qz.origin[2], scale = qz.scale;
  for (std::size_t i0 = lo; i0 < hi; i0 += kLanes) {
    const std::size_t m = std::min(kLanes, hi - i0);
    float p[3][kLanes];
    if (m == kLanes) {
      const float* q = xyz + 3 * i0;
      for (std::size_t l = 0; l < kLanes; ++l) p[0][l] = q[3 * l], p[1][l] = q[3 * l + 1], p[2][l] = q[3 * l + 2];
    } else {
      for (std::size_t l = 0; l < kLanes; ++l) {
        const float* q = xyz + 3 * (i0 + (l < m ? l : 0));
        p[0][l] = q[0], p[1][l] = q[1], p[2][l] = q[2];
      }
    }
    std::uint32_t c[3][kLanes];
    bool ok[kLanes];
    for (std::size_t l = 0; l < kLanes; ++l) {
      ok[l] = finite_bits(p[0][l]) & finite_bits(p[1][l]) & finite_bits(p[2][l]);
      c[0][l] = cell16((double(p[0][l]) - o0) * scale);
      c[1][l] = cell16((double(p[1][l]) - o1) * scale);
      c[2][l] = cell16((double(p[2][l]) - o2) * scale);
    }
    Key k16[kLanes];
    hilbert_keys16_lanes(c[0], c[1], c[2], k16, kLanes);
    for (std::size_t l = 0; l < m; ++l) keys[i0 + l] = ok[l] ? k16[l] : last;
  }
}

// The same order past 2^31 queries (the bucket words cannot hold the index): each thread's part
// radix-sorted as (key, row) pairs, the parts merged pairwise.
void order_by_merge(Key* keys, std::size_t n, unsigned threads, std::size_t per) {
  std::vector<KeyedRow> rows(n), tmp(n);
  parallel_for(threads, [&](std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t) {
      const std::size_t lo = std::min(n, t * per), hi = std::min(n, (t + 1) * per);
      for (std::size_t i = lo; i < hi; ++i) rows[i] = {keys[i], i};
      radix_sort_by_key(rows.data() + lo, tmp.data() + lo, hi - lo, kKeyBits);
    }
  }, threads, 1);
  // On equal keys the earlier part first (smaller rows).
  auto by_key = [](const KeyedRow& a, const KeyedRow& b) { return a.key < b.key; };
  for (std::size_t width = per; width < n; width *= 2) {
    for (std::size_t lo = 0; lo < n; lo += 2 * width) {
      const std::size_t mid = std::min(n, lo + width), hi = std::min(n, lo + 2 * width);
      std::merge(rows.begin() + lo, rows.begin() + mid, rows.begin() + mid, rows.begin() + hi, tmp.begin() + lo, by_key);
    }
    rows.swap(tmp);
  }
  for (std::size_t i = 0; i < n; ++i) keys[i] = rows[i].row;  // the order over the keys
}

}  // namespace

std::uint64_t hilbert_key16(std::uint32_t x, std::uint32_t y, std::uint32_t z) {
  Key key;
  hilbert_keys16_lanes(&x, &y, &z, &key, 1);
  return key;
}

void hilbert_query_order_into(const float* xyz, std::size_t n, std::size_t* order, std::size_t* nonfinite,
                              const OrderSink* sink) {
  // One parallel pass for the queries' box (finite ones only), one for the keys, then the
  // bucket sort (order_by_buckets): the order of the stable sort by (key, index).
  constexpr int kBits = 16;
  const unsigned threads = n < 16384 ? 1u : std::max(1u, std::min(default_threads(), 8u));
  const std::size_t per = (n + threads - 1) / threads;
  std::vector<std::array<float, 6>> boxes(threads);
  std::vector<std::size_t> finite_of(threads, 0);
  parallel_for(threads, [&](std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t)
      box_of_range(xyz, std::min(n, t * per), std::min(n, (t + 1) * per), boxes[t], finite_of[t]);
  }, threads, 1);
  std::size_t finite = 0;
  std::array<float, 6> fbox = boxes[0];
  for (unsigned t = 0; t < threads; ++t) {
    finite += finite_of[t];
    for (int d = 0; d < 3; ++d) {
      fbox[d] = std::min(fbox[d], boxes[t][d]);
      fbox[3 + d] = std::max(fbox[3 + d], boxes[t][3 + d]);
    }
  }
  const std::array<double, 6> box = {fbox[0], fbox[1], fbox[2], fbox[3], fbox[4], fbox[5]};
  if (nonfinite) *nonfinite = n - finite;
  if (finite == 0) {
    for (std::size_t i = 0; i < n; ++i) order[i] = i;
    if (sink && n) (*sink)(0, n, order);
    return;
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
  const Key last = Key(1) << (3 * kBits);
  Key* keys = order;  // the keys first, then the order over them
  const bool buckets = fits_bucket_words(n);
  const KeyBuckets kb(n);
  std::vector<std::size_t> pos(buckets ? kb.count() * threads : 0, 0);
  // Each thread's keys counted into its buckets as they are made (hot in its cache, and no pass
  // of its own: a thread start less, which costs most on a loaded machine).
  parallel_for(threads, [&](std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t) {
      const std::size_t lo = std::min(n, t * per), hi = std::min(n, (t + 1) * per);
      hilbert_keys_of_range(xyz, lo, hi, qz, last, keys);
      if (buckets) count_buckets(kb, keys, lo, hi, &pos[t * kb.count()]);
    }
  }, threads, 1);
  if (buckets) {
    order_by_buckets(keys, n, threads, kb, pos, sink);
  } else {
    order_by_merge(keys, n, threads, per);
    if (sink && n) (*sink)(0, n, order);
  }
}

std::vector<std::size_t> hilbert_query_order(const float* xyz, std::size_t n, std::size_t* nonfinite) {
  std::vector<std::size_t> order(n);
  hilbert_query_order_into(xyz, n, order.data(), nonfinite);
  return order;
}

std::unique_ptr<std::size_t[]> hilbert_query_order_fresh(const float* xyz, std::size_t n, std::size_t* nonfinite,
                                                         const OrderSink* sink) {
  std::unique_ptr<std::size_t[]> order(new std::size_t[std::max<std::size_t>(n, 1)]);  // not value-initialised
  hilbert_query_order_into(xyz, n, order.get(), nonfinite, sink);
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
