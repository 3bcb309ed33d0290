// Stage 3 of the block-hash build: per table and dimension a histogram of positions, integrated
// to a CDF and inverted at P stratified jittered samples, giving the thresholds of h_T.
#include <algorithm>
#include <cmath>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"

namespace bhcl::blockhash {
namespace {

// splitmix64: a tiny, portable generator, so thresholds are the same on every platform (the
// standard distributions are implementation-defined).
std::uint64_t splitmix64(std::uint64_t& s) {
  std::uint64_t z = (s += 0x9e3779b97f4a7c15ull);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

}  // namespace

Histogram histogram(const float* xyz, std::size_t n, int dim, int bins, std::size_t stride) {
  if (bins < 1) throw Error("blockhash: hist_bins must be >= 1, got " + std::to_string(bins));
  if (stride < 1) stride = 1;
  Histogram h;
  h.counts.assign(static_cast<std::size_t>(bins), 0);
  double lo = INFINITY, hi = -INFINITY;
  for (std::size_t i = 0; i < n; i += stride) {
    double v = xyz[3 * i + dim];
    lo = std::min(lo, v);
    hi = std::max(hi, v);
  }
  if (!(lo <= hi)) lo = hi = 0;  // no points
  h.lo = lo;
  h.hi = hi;
  const double w = hi - lo;
  for (std::size_t i = 0; i < n; i += stride) {
    double v = xyz[3 * i + dim];
    std::size_t b = 0;
    if (w > 0) {
      double f = std::floor((v - lo) / w * bins);
      b = f <= 0 ? 0 : std::min<std::size_t>(static_cast<std::size_t>(f), bins - 1);
    }
    ++h.counts[b];
    ++h.total;
  }
  return h;
}

std::vector<float> make_thresholds(const Histogram& h, int P, std::uint64_t seed, int table,
                                   int dim, bool guarded) {
  if (P < 1 || P > BHCL_BH_MAX_P)
    throw Error("blockhash: P must be in [1, " + std::to_string(BHCL_BH_MAX_P) + "], got " +
                std::to_string(P));
  const int nb = static_cast<int>(h.counts.size());
  std::vector<float> out(static_cast<std::size_t>(P), INFINITY);
  if (h.total == 0) return out;
  if (!(h.hi > h.lo)) {
    // A flat dimension: one slab holds everything. paper inverts the CDF of a point mass (every
    // threshold at the value); auto keeps no threshold at all.
    if (!guarded) std::fill(out.begin(), out.end(), static_cast<float>(h.lo));
    return out;
  }
  std::vector<double> cum(static_cast<std::size_t>(nb) + 1, 0.0);
  for (int b = 0; b < nb; ++b) cum[b + 1] = cum[b] + double(h.counts[b]);
  const double total = double(h.total), width = (h.hi - h.lo) / nb;
  // A different jitter per table (and dimension), reproducible from the seed.
  std::uint64_t state = seed * 0x2545f4914f6cdd1dull + std::uint64_t(table) * 0x9e3779b97f4a7c15ull +
                        std::uint64_t(dim) * 0xd1b54a32d192ed03ull + 1;
  std::vector<double> value(static_cast<std::size_t>(P));
  std::vector<int> edge(static_cast<std::size_t>(P));
  for (int i = 0; i < P; ++i) {
    double r = double(splitmix64(state) >> 11) * 0x1.0p-53;
    double c = (i + r) / P * total;  // stratified sample of the CDF
    int b = static_cast<int>(std::upper_bound(cum.begin(), cum.end(), c) - cum.begin()) - 1;
    b = std::clamp(b, 0, nb - 1);
    while (b < nb - 1 && h.counts[b] == 0) ++b;  // c on a flat stretch of the CDF
    double frac = h.counts[b] ? (c - cum[b]) / double(h.counts[b]) : 0.0;
    frac = std::clamp(frac, 0.0, 1.0);
    value[i] = h.lo + (b + frac) * width;
    edge[i] = static_cast<int>(std::lround(b + frac));
  }
  if (!guarded) {
    for (int i = 0; i < P; ++i) out[i] = static_cast<float>(value[i]);
    std::sort(out.begin(), out.end());
    return out;
  }
  // Guards (docs/ACCURACY.md, "Guards"). A heavy bin holds more than one stratum (N / P points): a wall
  // or floor of planar data. Thresholds crowd into such a bin and cut it into slabs a fraction of a
  // bin thick, so that queries just off the surface land in empty cells. Snap to bin edges, move a
  // threshold that borders a heavy bin one bin away (the heavy bin and its neighbour bin share a
  // cell), drop thresholds on the range's ends (they bound empty slabs) and duplicates.
  auto heavy = [&](int b) { return b >= 0 && b < nb && double(h.counts[b]) * P > total; };
  std::vector<int> edges;
  for (int i = 0; i < P; ++i) {
    int e = edge[i];
    if (heavy(e) && !heavy(e - 1)) --e;
    else if (heavy(e - 1) && !heavy(e)) ++e;
    if (e <= 0 || e >= nb) continue;
    edges.push_back(e);
  }
  std::sort(edges.begin(), edges.end());
  edges.erase(std::unique(edges.begin(), edges.end()), edges.end());
  std::vector<float> vals;
  for (int e : edges) {
    float v = static_cast<float>(h.edge(e));
    if (vals.empty() || v > vals.back()) vals.push_back(v);  // float rounding can merge edges
  }
  std::copy(vals.begin(), vals.end(), out.begin());
  return out;
}

void build_thresholds(const TableBuildParams& p, Structure& s) {
  const int L = s.info.L, P = s.info.P;
  s.thresholds.assign(std::size_t(L) * 3 * std::size_t(P), INFINITY);
  // Histograms over the sorted points (any order gives the same histogram).
  std::vector<float> pts(3 * s.n_points);
  for (std::size_t i = 0; i < s.n_points; ++i) s.point(i, &pts[3 * i]);
  for (int d = 0; d < 3; ++d) {
    Histogram h = histogram(pts.data(), s.n_points, d, p.hist_bins);
    for (int t = 0; t < L; ++t) {
      std::vector<float> thr = make_thresholds(h, P, p.seed, t, d, s.info.guard_thresholds);
      std::copy(thr.begin(), thr.end(), s.thresholds.begin() + (std::size_t(t) * 3 + d) * P);
    }
  }
}

}  // namespace bhcl::blockhash
