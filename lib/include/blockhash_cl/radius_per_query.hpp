// Radius search with one radius per query (the progressive radius of each gather point, a
// per-point scale in a point cloud): query i gets every point p with sum((q_i - p)^2) <= r_i^2,
// in the layout of RadiusResult (offsets n + 1, ids, squared distances, each slice sorted by
// (distance, index)), for every method of the registry.
//
// How: the queries are grouped by radius into bands whose largest radius is at most
// kRadiusBandRatio times the smallest (radius 0 is a band of its own); each band is one
// Index::radius_search with the band's largest radius, and each slice is then cut to its own
// query's radius (a prefix: slices come sorted). A band's search finds at most ratio^3 = 1.68
// times the points its queries need, and the number of calls grows with the log of the radii's
// spread, not with n. So:
//  - exact methods (kd-tree, brute force, FLANN) return exactly the points within r_i, the
//    contract's boundary rule included: the same slices as a radius_search with r_i alone (a row
//    the float search cannot vouch for is answered in double for the band's radius, then cut by
//    its rounded distances);
//  - block hashing returns those of the points its search with the band's radius examines that
//    lie within r_i: a subset, as its radius_search's.
// RadiusParams apply as in radius_search: max_results caps each slice after the cut (found keeps
// the count within r_i), sorted = false may leave slices in any order, count_examined reports what
// the band's search examined per query.
#pragma once

#include <cstddef>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

// The widest band of radii one radius_search serves: 2^(1/4).
inline constexpr double kRadiusBandRatio = 1.189207115002721;

// radii: n Euclidean radii, each finite and >= 0 (bhcl::Error naming the first bad one and its
// query otherwise). queries: n x 3 floats; a query with a NaN/Inf coordinate gets an empty slice.
QueryStats radius_search_per_query(const Index& index, const float* queries, std::size_t n,
                                   const float* radii, const RadiusParams& params, RadiusResult& out);

}  // namespace bhcl
