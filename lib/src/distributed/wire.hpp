// What the distributed index sends between ranks and shares between its kNN (index.cpp) and
// radius (radius.cpp) queries.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <exception>
#include <string>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl::distributed::wire {

inline constexpr const char* kWhat = "DistributedIndex";

// A point on its way to its shard: its position over all ranks (its global id less id_base).
struct PointRecord {
  float xyz[3];
  std::uint32_t pad;
  std::uint64_t position;
};
static_assert(sizeof(PointRecord) == 24, "PointRecord is sent as 24 raw bytes");

// A query on its way to a rank; budget_class 1 asks for the border budget (approximate methods).
struct QueryRecord {
  float xyz[3];
  std::int32_t budget_class;
};
static_assert(sizeof(QueryRecord) == 16, "QueryRecord is sent as 16 raw bytes");

// One query of this rank on its way to one rank: the caller's query `query`, with its budget class.
struct Route {
  int rank;
  std::int32_t budget_class;
  std::size_t query;
};

// The records of a list of routes, grouped by destination rank: send_counts[r] of them for rank r.
struct Outbox {
  std::vector<QueryRecord> records;
  std::vector<std::size_t> send_counts;
};

// Groups `routes` by destination rank, a rank's routes in their order in `routes` (a stable
// counting sort), and returns their records. `routes` is reordered to match: record j asks for
// the caller's query routes[j].query, and the answers, which come back in the order sent, follow.
inline Outbox group_by_rank(std::vector<Route>& routes, const float* queries, std::size_t ranks) {
  Outbox box;
  box.send_counts.assign(ranks, 0);
  for (const Route& r : routes) ++box.send_counts[static_cast<std::size_t>(r.rank)];
  std::vector<std::size_t> pos(ranks, 0);
  for (std::size_t r = 1; r < ranks; ++r) pos[r] = pos[r - 1] + box.send_counts[r - 1];
  std::vector<Route> grouped(routes.size());
  box.records.resize(routes.size());
  for (const Route& r : routes) {
    const std::size_t j = pos[static_cast<std::size_t>(r.rank)]++;
    grouped[j] = r;
    std::memcpy(box.records[j].xyz, queries + 3 * r.query, 12);
    box.records[j].budget_class = r.budget_class;
  }
  routes.swap(grouped);
  return box;
}

// The sum of per-rank counts over the ranks other than `me`: what crossed between ranks.
inline std::size_t to_others(const std::vector<std::size_t>& counts, std::size_t me) {
  std::size_t sum = 0;
  for (std::size_t r = 0; r < counts.size(); ++r) sum += r == me ? 0 : counts[r];
  return sum;
}

inline std::string what_of(const std::exception& e) { return e.what()[0] ? e.what() : "unknown error"; }

inline void add_stats(QueryStats& into, const QueryStats& s) {
  into.batches += s.batches;
  into.compile_s += s.compile_s;
  into.upload_s += s.upload_s;
  into.query_s += s.query_s;
  into.download_s += s.download_s;
}

}  // namespace bhcl::distributed::wire
