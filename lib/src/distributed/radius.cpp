// DistributedIndex::radius_search: each query's radius ball sent to every rank whose shard box
// it meets, the slices gathered back in the caller's order.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "blockhash_cl/distributed.hpp"
#include "blockhash_cl/error.hpp"
#include "distributed/agreement.hpp"
#include "distributed/mpi_util.hpp"
#include "distributed/wire.hpp"

namespace bhcl {

using distributed::exchange;
using distributed::Stopwatch;
using namespace distributed::wire;

QueryStats DistributedIndex::radius_search(const float* queries, std::size_t n, float r,
                                           const RadiusParams& params, RadiusResult& out,
                                           DistributedQueryStats* stats) const {
  require_int32_ids("radius_search");
  RadiusResult64 wide;
  const QueryStats st = radius_search(queries, n, r, params, wide, stats);
  out.n = wide.n;
  out.offsets = std::move(wide.offsets);
  out.ids.assign(wide.ids.begin(), wide.ids.end());  // every id fits: checked above
  out.dist2 = std::move(wide.dist2);
  out.found = std::move(wide.found);
  out.truncated_queries = wide.truncated_queries;
  out.examined = std::move(wide.examined);
  return st;
}

namespace {

// The answers, per record: (count, found, examined), then its entries (global id, distance).
struct Counts {
  std::int64_t count, found, examined;
};
struct Entry {
  std::int64_t id;  // global
  float d2;
  std::uint32_t pad;
};
static_assert(sizeof(Counts) == 24 && sizeof(Entry) == 16, "sent as raw bytes");

// This rank's answers to the records that came in (`in`, recv_counts[src] from rank src), and
// how many entries go back to each rank.
struct Answers {
  std::vector<Counts> counts;
  std::vector<Entry> entries;
  std::vector<std::size_t> entries_to;
};

Answers answer_locally(const Index* local, const std::vector<std::int64_t>& shard_ids,
                       const std::vector<unsigned char>& in, const std::vector<std::size_t>& recv_counts, float r,
                       const RadiusParams& params, QueryStats& st) {
  const std::size_t R = recv_counts.size(), m = in.size() / sizeof(QueryRecord);
  Answers a;
  a.counts.resize(m);
  a.entries_to.assign(R, 0);
  if (m > 0 && !local) throw Error("queries reached a rank with an empty shard");
  if (m == 0) return a;
  std::vector<float> xyz(3 * m);
  for (std::size_t i = 0; i < m; ++i) std::memcpy(&xyz[3 * i], in.data() + i * sizeof(QueryRecord), 12);
  RadiusResult rr;
  RadiusParams p = params;
  p.sort_queries = 0;  // records are grouped by source rank, already in key order per rank
  add_stats(st, local->radius_search(xyz.data(), m, r, p, rr));
  a.entries.resize(rr.total());
  for (std::size_t j = 0; j < rr.total(); ++j)
    a.entries[j] = Entry{shard_ids[static_cast<std::size_t>(rr.ids[j])], rr.dist2[j], 0};
  std::size_t rec = 0;
  for (std::size_t src = 0; src < R; ++src)
    for (std::size_t c = 0; c < recv_counts[src]; ++c, ++rec) {
      a.counts[rec] = Counts{static_cast<std::int64_t>(rr.count(rec)), rr.found[rec],
                             params.count_examined ? rr.examined[rec] : 0};
      a.entries_to[src] += rr.count(rec);
    }
  return a;
}

// Merges the answers that came back (counts `cb` and entries `eb`, in the order the records were
// sent: that of `routes`) into n rows sorted by (distance, global id), capped at max_results.
void merge_answers(RadiusResult64& out, std::size_t n, const std::vector<Route>& routes,
                   const std::vector<unsigned char>& cb, const std::vector<unsigned char>& eb,
                   const RadiusParams& params) {
  std::vector<std::vector<std::pair<float, std::int64_t>>> rows(n);
  std::vector<std::int64_t> found(n, 0), examined(n, 0);
  std::size_t at = 0;
  for (std::size_t j = 0; j < routes.size(); ++j) {
    Counts c;
    std::memcpy(&c, cb.data() + j * sizeof(Counts), sizeof c);
    const std::size_t i = routes[j].query;
    found[i] += c.found;
    examined[i] += c.examined;
    for (std::int64_t t = 0; t < c.count; ++t, ++at) {
      Entry en;
      std::memcpy(&en, eb.data() + at * sizeof(Entry), sizeof en);
      rows[i].emplace_back(en.d2, en.id);
    }
  }
  out.n = n;
  out.offsets.assign(n + 1, 0);
  out.ids.clear();
  out.dist2.clear();
  out.found = found;
  out.truncated_queries = 0;
  out.examined.assign(params.count_examined ? n : 0, 0);
  for (std::size_t i = 0; i < n; ++i) {
    auto& row = rows[i];
    std::sort(row.begin(), row.end());
    std::size_t keep = row.size();
    if (params.max_results && keep > params.max_results) keep = params.max_results;
    if (static_cast<std::int64_t>(keep) < found[i]) ++out.truncated_queries;
    for (std::size_t t = 0; t < keep; ++t) {
      out.dist2.push_back(row[t].first);
      out.ids.push_back(row[t].second);
    }
    out.offsets[i + 1] = static_cast<std::int64_t>(out.ids.size());
    if (params.count_examined) out.examined[i] = static_cast<std::int32_t>(std::min<std::int64_t>(examined[i], INT32_MAX));
  }
}

}  // namespace

// Checks the call's parameters on every rank and agrees them.
void DistributedIndex::check_radius_params(const float* queries, std::size_t n, float r,
                                           const RadiusParams& params) const {
  std::string err;
  try {
    if (std::isnan(r) || r < 0)  // +inf: every point, as Index::radius_search takes it
      throw Error("radius_search: the radius must be >= 0 (+inf: every point), got " + std::to_string(r));
    if (n > 0 && queries == nullptr) throw Error("queries is null with n = " + std::to_string(n));
    if (params.count_examined && local_ && !local_->counts_examined())
      throw Error("count_examined: method " + method_ + " does not count the points it examines");
  } catch (const std::exception& e) {
    err = what_of(e);
  }
  mpi_agree(comm_, err, std::string(kWhat) + "::radius_search");
  // Every radius parameter as rank 0's (the radius, the cap and count_examined shape every
  // rank's answer).
  distributed::agree_parameters(comm_, distributed::radius_parameters(r, params),
                                std::string(kWhat) + "::radius_search");
}

QueryStats DistributedIndex::radius_search(const float* queries, std::size_t n, float r,
                                           const RadiusParams& params, RadiusResult64& out,
                                           DistributedQueryStats* stats) const {
  Stopwatch wall;
  QueryStats st;
  st.n_queries = n;
  DistributedQueryStats ds;
  const std::size_t R = static_cast<std::size_t>(ranks_), me = static_cast<std::size_t>(rank_);
  check_radius_params(queries, n, r, params);
  // Each finite query to its owner and to every other rank with a box meeting the ball.
  route_to_owners(queries, n, st, ds);
  const double r2 = double(r) * double(r);
  std::vector<Route> routes;
  std::vector<int> met;
  for (std::size_t i = 0; i < n; ++i) {
    if (ds.owner[i] < 0) continue;
    routes.push_back({ds.owner[i], 0, i});
    ranks_meeting(queries + 3 * i, r2, ds.owner[i], met);
    for (int m : met) routes.push_back({m, 0, i});
    ds.ranks_visited[i] += static_cast<std::int32_t>(met.size());
    if (!met.empty()) ++ds.multi_rank_queries;
  }
  const Outbox box = group_by_rank(routes, queries, R);
  std::vector<std::size_t> recv_counts, back_counts, entry_counts_back;
  const std::vector<unsigned char> in =
      exchange(comm_, box.records.data(), box.send_counts, sizeof(QueryRecord), recv_counts, "radius (queries)");
  Answers a;
  std::string e;
  try {
    a = answer_locally(local_.get(), shard_ids_, in, recv_counts, r, params, st);
  } catch (const std::exception& ex) {
    e = std::string("radius: ") + what_of(ex);
  }
  mpi_agree(comm_, e, std::string(kWhat) + "::radius_search");
  ds.answered = in.size() / sizeof(QueryRecord);
  const std::vector<unsigned char> cb = exchange(comm_, a.counts.data(), recv_counts, sizeof(Counts), back_counts,
                                                 "radius (counts)");
  const std::vector<unsigned char> eb = exchange(comm_, a.entries.data(), a.entries_to, sizeof(Entry),
                                                 entry_counts_back, "radius (results)");
  const std::size_t to = to_others(box.send_counts, me), from = to_others(recv_counts, me);
  const std::size_t entries_out = to_others(a.entries_to, me), entries_in = to_others(entry_counts_back, me);
  ds.owner_sent = to;
  ds.owner_received = from;
  ds.bytes_sent = to * sizeof(QueryRecord) + from * sizeof(Counts) + entries_out * sizeof(Entry);
  ds.bytes_received = from * sizeof(QueryRecord) + to * sizeof(Counts) + entries_in * sizeof(Entry);
  merge_answers(out, n, routes, cb, eb, params);
  st.wall_s = wall.seconds();
  if (stats) *stats = std::move(ds);
  return st;
}

}  // namespace bhcl
