#include "core/query_order.hpp"

#include "blockhash_cl/spatial_order.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>

#include "sfc/hilbert.hpp"

namespace bhcl::detail {

std::vector<std::size_t> hilbert_query_order(const float* xyz, std::size_t n) {
  std::vector<std::size_t> finite, rest;
  for (std::size_t i = 0; i < n; ++i) {
    const float* q = xyz + 3 * i;
    (std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]) ? finite : rest).push_back(i);
  }
  if (finite.empty()) return rest;
  std::vector<float> compact(3 * finite.size());
  for (std::size_t j = 0; j < finite.size(); ++j)
    for (int d = 0; d < 3; ++d) compact[3 * j + d] = xyz[3 * finite[j] + d];
  // The curve's quantiser and Hilbert keys (sfc/hilbert.hpp), over the queries' own box.
  const sfc::Quantiser q = sfc::make_quantiser(compact.data(), finite.size(), 16);
  std::vector<std::uint64_t> keys = sfc::hilbert_keys(compact.data(), finite.size(), q);
  std::vector<std::size_t> order;
  order.reserve(n);
  if (finite.size() <= static_cast<std::size_t>(std::numeric_limits<std::int32_t>::max())) {
    // The build's sort (two halves on two threads, then merged; equal keys keep their order).
    for (std::int32_t j : sfc::hilbert_order(keys)) order.push_back(finite[static_cast<std::size_t>(j)]);
  } else {
    std::vector<std::pair<std::uint64_t, std::size_t>> by_key(finite.size());
    for (std::size_t j = 0; j < finite.size(); ++j) by_key[j] = {keys[j], finite[j]};
    std::sort(by_key.begin(), by_key.end());
    for (const auto& kv : by_key) order.push_back(kv.second);
  }
  order.insert(order.end(), rest.begin(), rest.end());
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
