// Spatial order of 3D points along a Hilbert curve: the order the library dispatches query
// batches in, public so that callers can lay out their own data the same way (a photon map whose
// records neighbours read together, a batch of queries built elsewhere).
#pragma once

#include <cstddef>
#include <functional>
#include <vector>

namespace bhcl {

// The order that visits the points along a 3D Hilbert curve over their own bounding box (16 bits
// per axis; points with equal keys keep their order); points with a non-finite coordinate go
// last, in their own order. order[i] = the index of the i-th point to visit. n = 0: empty.
std::vector<std::size_t> hilbert_order(const float* xyz, std::size_t n);

namespace detail {
// The library's own order takes a sink: called with each range [lo, hi) of dispatch positions
// as soon as order[lo, hi) is final (lib/src/core/query_order.hpp); here, not there, because
// Index's private query pipeline (knn.hpp) names it too.
using OrderSink = std::function<void(std::size_t lo, std::size_t hi, const std::size_t* order)>;
}  // namespace detail

}  // namespace bhcl
