// Accuracy of an approximate kNN result against exact truth (both under the result contract).
#pragma once

#include <cstddef>
#include <string>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

struct Accuracy {
  std::size_t queries = 0;           // rows compared (rows whose truth is empty are skipped)
  // recall@k with ties tolerated: a returned neighbour counts when its squared distance is within
  // the true k-th squared distance (relative tolerance 1e-6). Mean over queries of hits / true count.
  double recall = 0.0;
  // Share of the true neighbours (by index) missing from the result: the talk's false negatives.
  // Ties swapped for equally near points count here but not against recall.
  double false_negative_rate = 0.0;
  // Distance dilation: (returned k-th distance) / (true k-th distance), distances not squared,
  // over queries with a complete row and a non-zero true k-th distance.
  double max_dilation = 1.0;
  double mean_dilation = 1.0;
  // Mean of (returned j-th distance - true j-th distance) / true j-th distance over all ranks with
  // a non-zero true distance.
  double mean_rel_distance_error = 0.0;
  // Queries that returned fewer neighbours than the truth has.
  std::size_t incomplete_queries = 0;
  // Queries whose row equals the truth exactly (ids and distances).
  std::size_t identical_rows = 0;

  std::string summary() const;  // one line: "recall 0.9912  FN 0.0101  dil max 1.23 mean 1.002 ..."
};

// Throws bhcl::Error when the shapes differ (n or k).
Accuracy evaluate_accuracy(const KnnResult& approx, const KnnResult& truth);

// Accuracy of a radius search against the exact one (both Index::radius_search with the same r
// and no cap): the points of each query's ball that were found. Points are compared by index, as
// sets (the slices' order does not matter).
struct RadiusAccuracy {
  std::size_t queries = 0;             // queries compared (all of them)
  // Mean over queries with a non-empty true ball of |found and true| / |true| (1 when none has one).
  double recall = 1.0;
  double found_fraction = 1.0;         // total points found in the balls / total true (pooled)
  std::size_t missing = 0;             // true points not returned, over all queries
  std::size_t false_positives = 0;    // returned points not in the true ball (should be 0 always)
  std::size_t incomplete_queries = 0;  // queries missing at least one true point
  std::size_t identical_slices = 0;    // queries returning exactly the true set
  double mean_true = 0, mean_found = 0;  // points per query

  std::string summary() const;  // one line
};

// Throws bhcl::Error when the query counts differ or a result's offsets are inconsistent.
RadiusAccuracy evaluate_radius_accuracy(const RadiusResult& approx, const RadiusResult& truth);

}  // namespace bhcl
