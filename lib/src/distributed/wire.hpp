// What the distributed index sends between ranks and shares between its kNN (index.cpp) and
// radius (radius.cpp) queries.
#pragma once

#include <cstdint>
#include <exception>
#include <string>

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

inline std::string what_of(const std::exception& e) { return e.what()[0] ? e.what() : "unknown error"; }

inline void add_stats(QueryStats& into, const QueryStats& s) {
  into.batches += s.batches;
  into.compile_s += s.compile_s;
  into.upload_s += s.upload_s;
  into.query_s += s.query_s;
  into.download_s += s.download_s;
}

}  // namespace bhcl::distributed::wire
