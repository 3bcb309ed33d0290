// Radius search with one radius per query (radius_per_query.hpp): bands of radii, one
// radius_search per band, each slice cut to its query's radius.
#include "blockhash_cl/radius_per_query.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <sstream>
#include <vector>

#include "blockhash_cl/error.hpp"

namespace bhcl {

QueryStats radius_search_per_query(const Index& index, const float* queries, std::size_t n,
                                   const float* radii, const RadiusParams& params, RadiusResult& out) {
  const auto t0 = std::chrono::steady_clock::now();
  if (n > 0 && !queries) throw Error("radius_search_per_query: queries is null with n = " + std::to_string(n));
  if (n > 0 && !radii) throw Error("radius_search_per_query: radii is null with n = " + std::to_string(n));
  for (std::size_t i = 0; i < n; ++i)
    if (!std::isfinite(radii[i]) || radii[i] < 0) {
      std::ostringstream os;
      os << "radius_search_per_query: the radius of query " << i << " must be finite and >= 0, got " << radii[i];
      throw Error(os.str());
    }
  QueryStats st;
  st.n_queries = n;
  out = RadiusResult{};
  out.n = n;
  out.offsets.assign(n + 1, 0);
  out.found.assign(n, 0);
  out.examined.assign(params.count_examined ? n : 0, 0);
  if (n == 0) return st;

  // Bands over the radii in ascending order: a band starts at its smallest radius and takes every
  // radius up to ratio times it; zero radii form their own band (ratio x 0 would be 0 anyway).
  std::vector<std::size_t> order(n);
  std::iota(order.begin(), order.end(), std::size_t(0));
  std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return radii[a] < radii[b]; });
  // The band's search returns whole sorted slices; the cap is applied after the cut, so that a
  // query's nearest within r_i are kept, not the band radius's.
  RadiusParams bp = params;
  bp.max_results = 0;
  bp.sorted = true;
  std::vector<std::int64_t> len(n, 0);  // each query's slice after the cut (and the cap)
  std::vector<std::vector<std::int32_t>> ids(n);
  std::vector<std::vector<float>> d2s(n);
  std::vector<float> qb;
  RadiusResult band;
  for (std::size_t a = 0; a < n;) {
    const float lo = radii[order[a]];
    std::size_t b = a + 1;
    const double top = lo * kRadiusBandRatio;
    while (b < n && (lo == 0 ? radii[order[b]] == 0 : double(radii[order[b]]) <= top)) ++b;
    const float rband = radii[order[b - 1]];
    qb.resize(3 * (b - a));
    for (std::size_t j = a; j < b; ++j) std::copy_n(queries + 3 * order[j], 3, qb.data() + 3 * (j - a));
    const QueryStats s = index.radius_search(qb.data(), b - a, rband, bp, band);
    st.add_slice(s);
    for (std::size_t j = a; j < b; ++j) {
      const std::size_t q = order[j], row = j - a;
      const float ri = radii[q];
      const float r2 = ri * ri;  // the contract's rule: within when dist2 <= r*r in float
      const std::int64_t from = band.offsets[row], to = band.offsets[row + 1];
      std::int64_t m = from;
      while (m < to && band.dist2[static_cast<std::size_t>(m)] <= r2) ++m;
      const std::size_t found = static_cast<std::size_t>(m - from);
      const std::size_t keep = params.max_results ? std::min(params.max_results, found) : found;
      out.found[q] = static_cast<std::int64_t>(found);
      if (keep < found) ++out.truncated_queries;
      ids[q].assign(band.ids.begin() + from, band.ids.begin() + from + static_cast<std::int64_t>(keep));
      d2s[q].assign(band.dist2.begin() + from, band.dist2.begin() + from + static_cast<std::int64_t>(keep));
      len[q] = static_cast<std::int64_t>(keep);
      if (params.count_examined) out.examined[q] = band.examined[row];
    }
    a = b;
  }
  for (std::size_t i = 0; i < n; ++i) out.offsets[i + 1] = out.offsets[i] + len[i];
  out.ids.reserve(static_cast<std::size_t>(out.offsets[n]));
  out.dist2.reserve(static_cast<std::size_t>(out.offsets[n]));
  for (std::size_t i = 0; i < n; ++i) {
    out.ids.insert(out.ids.end(), ids[i].begin(), ids[i].end());
    out.dist2.insert(out.dist2.end(), d2s[i].begin(), d2s[i].end());
  }
  st.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return st;
}

}  // namespace bhcl
