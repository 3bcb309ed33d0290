// Query batches sorted along a space-filling curve before dispatch (as cudaKDTree and ArborX do):
// neighbouring work-items then walk the same buckets, blocks and tree nodes, which is what caches
// and GPU memory coalescing reward.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <vector>

#include "blockhash_cl/spatial_order.hpp"  // OrderSink

namespace bhcl::detail {

// The order that visits the queries along a 3D Hilbert curve over their own bounding box
// (16 bits per axis); queries with a non-finite coordinate go last, in their own order.
// order[i] = the caller's index of the i-th query to dispatch.
// nonfinite (when not null): how many queries have a non-finite coordinate (the box pass counts them).
std::vector<std::size_t> hilbert_query_order(const float* xyz, std::size_t n, std::size_t* nonfinite = nullptr);
// The same into order (n entries, used as the keys' scratch first) ...
// sink (when set): called with each range [lo, hi) of dispatch positions as soon as order[lo, hi)
// is final (every position once, from the sort's threads, ranges in any order): the query
// pipeline gathers the queries into the device's buffer there, in the sort's last pass.
void hilbert_query_order_into(const float* xyz, std::size_t n, std::size_t* order, std::size_t* nonfinite = nullptr,
                              const OrderSink* sink = nullptr);
// ... and into fresh memory not filled first: its pages are first touched by the key pass's
// threads, not by one thread's memset (16 MB of fresh pages at 1M queries; the query pipeline's).
std::unique_ptr<std::size_t[]> hilbert_query_order_fresh(const float* xyz, std::size_t n, std::size_t* nonfinite = nullptr,
                                                         const OrderSink* sink = nullptr);

// sfc::hilbert_encode(x, y, z, 16), computed without branches (the query order's keys).
std::uint64_t hilbert_key16(std::uint32_t x, std::uint32_t y, std::uint32_t z);

// The queries in that order: row i of the result is row order[i] of xyz (n x 3).
std::vector<float> queries_in_order(const float* xyz, const std::vector<std::size_t>& order);

}  // namespace bhcl::detail
