// Tests of bhcl::DistributedIndex, run by CTest under mpirun at 1, 2 and 4 ranks (its own program:
// the doctest binary runs without MPI). Every rank runs every case; a failed check is counted on
// its rank and printed with the rank, and the program fails when any rank counted one. A check
// never throws, so the ranks always reach the same collective calls.
//
// What it checks:
//  - every exact method gives, through the distributed index, the single-process answer bit for
//    bit (ids, float distances, counts), for point sets that stress the sharding (uniform,
//    clustered, long runs of duplicates that straddle shard borders, flat), k = 1, 10, 64, with
//    and without a maximum radius, with points and queries spread unevenly over the ranks (one
//    rank passing none), and with fewer points than ranks;
//  - block hashing's recall through the distributed index is that of one process (within 0.02);
//  - NaN queries get empty rows; the statistics add up across ranks;
//  - radius search: exact methods equal one process bit for bit (with and without a cap), block
//    hashing a subset within r with one process's recall;
//  - a rank given a NaN point, an unknown method on one rank, or ranks passing different k make
//    the call throw on every rank with a message naming the failing rank;
//  - ranks passing different build or search parameters (method, an option, boxes, A, the
//    recall target, the radius, the cap) are refused on every rank naming rank and parameter;
//  - global ids are int64: with an id base past 2^32 the answers are the base-0 ones plus the
//    base, the int32 calls refuse such an index, and too many points per rank are refused from
//    the counts alone;
//  - insert and remove (issue 39): after each of a sequence of updates (new points inside and
//    outside the build's box and on existing positions, spread unevenly over the ranks; a 10 %
//    remove of old and new ids; a crop that empties a shard; points inserted where it was), every
//    method's kNN and radius answers are those of one process's index of the same method after
//    the same updates (ids equal, distances bit-equal), the new ids are id_bound(), ... in rank
//    order, and the boxes bound every live point and no removed region; the errors of
//    Index::insert / remove (a NaN point, no points, a null array, an id outside, removed,
//    repeated across ranks, removing all) throw the same message on every rank and leave the
//    index as it was; with an id base past 2^32 the updated answers are base 0's plus the base;
//  - with --hang-rank R (its own CTest case): a rank that stops answering ends the job within
//    the deadline with a message naming it, never a hang.
#include <mpi.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <thread>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/distributed.hpp"

namespace {

int g_rank = 0, g_ranks = 1;
int g_failures = 0;

#define EXPECT(cond, ...)                                                   \
  do {                                                                      \
    if (!(cond)) {                                                          \
      ++g_failures;                                                         \
      std::fprintf(stderr, "rank %d: %s:%d: FAILED: %s: ", g_rank, __FILE__, \
                   __LINE__, #cond);                                        \
      std::fprintf(stderr, __VA_ARGS__);                                    \
      std::fputc('\n', stderr);                                             \
    }                                                                       \
  } while (0)

std::shared_ptr<bhcl::Runtime> runtime() {
  static std::shared_ptr<bhcl::Runtime> rt = std::make_shared<bhcl::Runtime>();
  return rt;
}

// Rank r's slice of `count` items: unequal parts (rank r gets a share growing with r), and rank 1
// gets none when there are 3 ranks or more, so that the API's "any split" is exercised.
std::pair<std::size_t, std::size_t> slice(std::size_t count, int rank, int ranks, int skew) {
  std::vector<std::size_t> weight(static_cast<std::size_t>(ranks));
  for (int r = 0; r < ranks; ++r) weight[static_cast<std::size_t>(r)] = static_cast<std::size_t>((r + skew) % ranks + 1);
  if (ranks >= 3) weight[1] = 0;
  std::size_t total = 0;
  for (auto w : weight) total += w;
  std::size_t first = 0;
  for (int r = 0; r < rank; ++r) first += count * weight[static_cast<std::size_t>(r)] / total;
  std::size_t len = rank + 1 == ranks ? count - first : count * weight[static_cast<std::size_t>(rank)] / total;
  return {first, len};
}

struct Set {
  std::string name;
  std::vector<float> points, queries;
};

// Queries: uniform over the box grown by 10 %, exact copies of points (distance-0 ties) and
// points moved by a tiny jitter (near-ties).
std::vector<float> queries_for(const std::vector<float>& pts, std::uint64_t seed, std::size_t each) {
  float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  const std::size_t n = pts.size() / 3;
  for (std::size_t i = 0; i < n; ++i)
    for (int d = 0; d < 3; ++d) lo[d] = std::min(lo[d], pts[3 * i + d]), hi[d] = std::max(hi[d], pts[3 * i + d]);
  std::mt19937_64 rng(seed);
  std::vector<float> q;
  for (std::size_t i = 0; i < each; ++i)
    for (int d = 0; d < 3; ++d) {
      const float pad = 0.1f * (hi[d] - lo[d]);
      q.push_back(std::uniform_real_distribution<float>(lo[d] - pad, hi[d] + pad)(rng));
    }
  std::uniform_int_distribution<std::size_t> pick(0, n - 1);
  for (std::size_t i = 0; i < each; ++i) {
    const std::size_t j = pick(rng);
    q.insert(q.end(), {pts[3 * j], pts[3 * j + 1], pts[3 * j + 2]});
  }
  std::normal_distribution<float> jitter(0.0f, 1e-6f);
  for (std::size_t i = 0; i < each; ++i) {
    const std::size_t j = pick(rng);
    for (int d = 0; d < 3; ++d) q.push_back(pts[3 * j + d] + jitter(rng));
  }
  return q;
}

std::vector<Set> exact_sets() {
  std::vector<Set> sets;
  auto add = [&](const std::string& name, std::vector<float> pts, std::uint64_t seed) {
    std::vector<float> q = queries_for(pts, seed, 60);
    sets.push_back({name, std::move(pts), std::move(q)});
  };
  add("uniform", bhcl::datasets::uniform(2500, 101), 1);
  add("clustered", bhcl::datasets::clustered(2500, 102, 8, 0.002f), 2);
  {
    // Long runs of one position: 40 % of the points on 3 positions, so runs of equal keys
    // straddle every shard border at 2 and 4 ranks; ties are broken by global index only.
    auto pts = bhcl::datasets::uniform(2500, 103);
    for (std::size_t i = 0; i < 1000; ++i) {
      const float v = i % 3 == 0 ? 0.25f : i % 3 == 1 ? 0.5f : 0.75f;
      std::size_t j = (i * 7919) % 2500;
      pts[3 * j] = pts[3 * j + 1] = pts[3 * j + 2] = v;
    }
    add("duplicates", std::move(pts), 3);
  }
  {
    auto pts = bhcl::datasets::uniform(2500, 105);
    for (std::size_t i = 0; i < pts.size(); i += 3) pts[i + 2] = 0.5f;  // flat: z = const
    add("flat", std::move(pts), 5);
  }
  return sets;
}

// Bit-exact equality of the rows of `got` with rows [first, first + got.n) of `ref`.
bool identical_rows(const bhcl::KnnResult& got, const bhcl::KnnResult& ref, std::size_t first,
                    std::string& why) {
  const std::size_t k = static_cast<std::size_t>(ref.k);
  if (got.k != ref.k) {
    why = "k " + std::to_string(got.k) + " vs " + std::to_string(ref.k);
    return false;
  }
  for (std::size_t i = 0; i < got.n; ++i) {
    if (got.counts[i] != ref.counts[first + i]) {
      why = "query " + std::to_string(first + i) + ": count " + std::to_string(got.counts[i]) + " vs " +
            std::to_string(ref.counts[first + i]);
      return false;
    }
    for (std::size_t j = 0; j < k; ++j) {
      const float a = got.dist2[i * k + j], b = ref.dist2[(first + i) * k + j];
      if (got.ids[i * k + j] != ref.ids[(first + i) * k + j] || std::memcmp(&a, &b, 4) != 0) {
        char buf[200];
        std::snprintf(buf, sizeof buf, "query %zu column %zu: (%d, %.9g) vs single process (%d, %.9g)",
                      first + i, j, got.ids[i * k + j], a, ref.ids[(first + i) * k + j], b);
        why = buf;
        return false;
      }
    }
  }
  return true;
}

// The distributed index of `method` over this rank's share of the set's points (8 routing boxes
// a rank): the build every comparison with one process starts from.
std::unique_ptr<bhcl::DistributedIndex> shard_of(const Set& s, const std::string& method) {
  const auto [pf, pl] = slice(s.points.size() / 3, g_rank, g_ranks, 0);
  bhcl::DistributedBuildParams bp;
  bp.method = method;
  bp.boxes_per_rank = 8;
  return std::make_unique<bhcl::DistributedIndex>(MPI_COMM_WORLD, runtime(), s.points.data() + 3 * pf, pl, bp);
}

// Every exact method, every set, k 1 / 10 / 64, with and without a radius, against one process.
void exact_methods_match_single_process() {
  for (const Set& s : exact_sets()) {
    const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
    auto [qf, ql] = slice(n, g_rank, g_ranks, 1);
    for (const std::string& method : bhcl::exact_method_names()) {
      const auto dist = shard_of(s, method);
      EXPECT(dist->size() == N, "%s: size %zu", s.name.c_str(), dist->size());
      std::unique_ptr<bhcl::Index> single = bhcl::make_index(method, runtime(), s.points.data(), N);
      for (int k : {1, 10, 64})
        for (bool radius : {false, true}) {
          bhcl::SearchParams p;
          p.k = k;
          // A radius that cuts many rows short: about the typical 8th-neighbour distance.
          if (radius) p.max_radius = s.name == "clustered" ? 0.0005f : 0.04f;
          bhcl::KnnResult ref, got;
          single->query(s.queries.data(), n, p, ref);
          bhcl::DistributedQueryStats ds;
          bhcl::QueryStats st = dist->query(s.queries.data() + 3 * qf, ql, p, got, &ds);
          std::string why;
          EXPECT(identical_rows(got, ref, qf, why), "%s %s k=%d radius=%d: %s", method.c_str(),
                 s.name.c_str(), k, int(radius), why.c_str());
          EXPECT(st.n_queries == ql && ds.ranks_visited.size() == ql, "%s: stats sizes", method.c_str());
          for (std::size_t i = 0; i < ql; ++i)
            EXPECT(ds.ranks_visited[i] >= 1 && ds.ranks_visited[i] <= g_ranks && ds.owner[i] >= 0,
                   "query %zu visited %d ranks, owner %d", qf + i, ds.ranks_visited[i], ds.owner[i]);
        }
    }
  }
}

// Fewer points than ranks: some shards are empty; rows are still the single-process rows.
void fewer_points_than_ranks() {
  const std::vector<float> pts = {0, 0, 0, 1, 0, 0, 0.5f, 0.5f, 0.5f};
  const std::vector<float> qs = {0.1f, 0, 0, 0.9f, 0.1f, 0, 2, 2, 2};
  // All points on the last rank, all queries on rank 0.
  const bool last = g_rank == g_ranks - 1, first = g_rank == 0;
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), last ? pts.data() : nullptr, last ? 3 : 0);
  std::size_t nonempty = 0;
  for (auto c : dist.build_stats().shard_points_all) nonempty += c > 0;
  EXPECT(nonempty == std::min<std::size_t>(3, std::size_t(g_ranks)), "%zu non-empty shards", nonempty);
  auto single = bhcl::make_index("kdtree", runtime(), pts.data(), 3);
  bhcl::SearchParams p;
  p.k = 5;
  bhcl::KnnResult ref, got;
  single->query(qs.data(), 3, p, ref);
  dist.query(first ? qs.data() : nullptr, first ? 3 : 0, p, got);
  std::string why;
  if (first) EXPECT(identical_rows(got, ref, 0, why), "%s", why.c_str());
  EXPECT(got.n == (first ? 3u : 0u), "rows %zu", got.n);
}

// Radius search: every exact method, every set, with and without a cap, equals one process bit
// for bit; block hashing's answer is a subset within r whose recall is one process's (within
// 0.02); a NaN query gets an empty slice; ranks passing different radii fail on every rank.
bool identical_slices(const bhcl::RadiusResult& got, const bhcl::RadiusResult& ref, std::size_t first,
                      std::string& why) {
  for (std::size_t i = 0; i < got.n; ++i) {
    const std::size_t a = static_cast<std::size_t>(got.offsets[i]), b = static_cast<std::size_t>(ref.offsets[first + i]);
    if (got.count(i) != ref.count(first + i) || got.found[i] != ref.found[first + i]) {
      why = "query " + std::to_string(first + i) + ": " + std::to_string(got.count(i)) + " results (" +
            std::to_string(got.found[i]) + " found) vs " + std::to_string(ref.count(first + i)) + " (" +
            std::to_string(ref.found[first + i]) + ")";
      return false;
    }
    for (std::size_t j = 0; j < got.count(i); ++j)
      if (got.ids[a + j] != ref.ids[b + j] || std::memcmp(&got.dist2[a + j], &ref.dist2[b + j], 4) != 0) {
        why = "query " + std::to_string(first + i) + " entry " + std::to_string(j) + ": id " +
              std::to_string(got.ids[a + j]) + " vs " + std::to_string(ref.ids[b + j]);
        return false;
      }
  }
  return true;
}

void radius_search_as_one_process() {
  for (const Set& s : exact_sets()) {
    const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
    auto [qf, ql] = slice(n, g_rank, g_ranks, 1);
    const float r = s.name == "clustered" ? 0.0008f : 0.05f;
    for (const std::string& method : bhcl::method_names()) {
      const auto dist = shard_of(s, method);
      std::unique_ptr<bhcl::Index> single = bhcl::make_index(method, runtime(), s.points.data(), N);
      for (std::size_t cap : {std::size_t(0), std::size_t(4)}) {
        bhcl::RadiusParams p;
        p.max_results = cap;
        bhcl::RadiusResult ref, got;
        single->radius_search(s.queries.data(), n, r, p, ref);
        bhcl::DistributedQueryStats ds;
        dist->radius_search(s.queries.data() + 3 * qf, ql, r, p, got, &ds);
        EXPECT(got.n == ql && got.offsets.size() == ql + 1, "%s: %zu slices", method.c_str(), got.n);
        if (single->exact()) {
          std::string why;
          EXPECT(identical_slices(got, ref, qf, why), "radius %s %s cap %zu: %s", method.c_str(), s.name.c_str(),
                 cap, why.c_str());
          continue;
        }
        // Block hashing: every result within r and in the exact answer; recall near one process's.
        auto exact = bhcl::make_index("bruteforce", runtime(), s.points.data(), N);
        bhcl::RadiusResult truth;
        exact->radius_search(s.queries.data(), n, r, {}, truth);
        std::size_t hit = 0, total = 0, hit1 = 0;
        for (std::size_t i = 0; i < ql; ++i) {
          const auto* t0 = truth.ids.data() + truth.offsets[qf + i];
          std::vector<std::int32_t> t(t0, t0 + truth.count(qf + i));
          std::sort(t.begin(), t.end());
          total += t.size();
          for (auto j = got.offsets[i]; j < got.offsets[i + 1]; ++j) {
            const bool in = std::binary_search(t.begin(), t.end(), got.ids[j]);
            EXPECT(in, "blockhash radius: id %d is not within r of query %zu", got.ids[j], qf + i);
            hit += in;
          }
          for (auto j = ref.offsets[qf + i]; j < ref.offsets[qf + i + 1]; ++j)
            hit1 += std::binary_search(t.begin(), t.end(), ref.ids[j]);
        }
        long long v[3] = {(long long)hit, (long long)total, (long long)hit1}, g[3];
        MPI_Allreduce(v, g, 3, MPI_LONG_LONG, MPI_SUM, MPI_COMM_WORLD);
        if (cap == 0 && g[1] > 0) {
          const double rec = double(g[0]) / double(g[1]), rec1 = double(g[2]) / double(g[1]);
          EXPECT(rec >= rec1 - 0.02, "blockhash radius recall %.4f vs one process %.4f on %s", rec, rec1,
                 s.name.c_str());
        }
      }
    }
  }
  // A NaN query: an empty slice. Different radii on the ranks: an error on every rank.
  const auto pts = bhcl::datasets::uniform(500, 9);
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), g_rank == 0 ? pts.data() : nullptr, g_rank == 0 ? 500 : 0);
  const float qs[6] = {std::numeric_limits<float>::quiet_NaN(), 0, 0, 0.5f, 0.5f, 0.5f};
  bhcl::RadiusResult got;
  bhcl::QueryStats st = dist.radius_search(qs, 2, 0.2f, {}, got);
  EXPECT(got.count(0) == 0 && got.count(1) > 0 && st.nonfinite_queries == 1, "NaN query: %zu, %zu",
         got.count(0), got.count(1));
  std::string msg;
  try {
    dist.radius_search(qs, 2, g_rank == 0 ? 0.2f : 0.3f, {}, got);
  } catch (const std::exception& e) {
    msg = e.what();
  }
  if (g_ranks > 1)
    EXPECT(msg.find("has radius = 0.300000012 where rank 0 has 0.200000003") != std::string::npos, "message: '%s'", msg.c_str());
}

// NaN queries get empty rows and are counted; the exchange counts balance over the ranks.
void nonfinite_queries_and_stats() {
  const std::vector<float> pts = bhcl::datasets::clustered(4000, 7, 4, 0.05f);
  std::vector<float> qs = bhcl::datasets::clustered(300, 8, 4, 0.05f);
  qs[3 * 5 + 1] = std::numeric_limits<float>::quiet_NaN();
  qs[3 * 17] = std::numeric_limits<float>::infinity();
  auto [pf, pl] = slice(4000, g_rank, g_ranks, 2);
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), pts.data() + 3 * pf, pl);
  const auto& bs = dist.build_stats();
  std::size_t sum = 0, largest = 0;
  for (auto c : bs.shard_points_all) sum += c, largest = std::max(largest, c);
  EXPECT(sum == 4000 && bs.shard_points == bs.shard_points_all[std::size_t(g_rank)], "shards sum to %zu", sum);
  EXPECT(largest <= 4000 / std::size_t(g_ranks) + 1, "largest shard %zu", largest);
  EXPECT(dist.shard_ids().size() == bs.shard_points &&
             std::is_sorted(dist.shard_ids().begin(), dist.shard_ids().end()),
         "shard ids");
  unsigned long long moved[2] = {bs.points_sent, bs.points_received}, moved_all[2];
  MPI_Allreduce(moved, moved_all, 2, MPI_UNSIGNED_LONG_LONG, MPI_SUM, MPI_COMM_WORLD);
  EXPECT(moved_all[0] == moved_all[1], "points sent %llu, received %llu", moved_all[0], moved_all[1]);

  // Every rank asks the same queries (a valid use: rows come back to each asker).
  bhcl::SearchParams p;
  p.k = 8;
  bhcl::KnnResult got, ref;
  bhcl::DistributedQueryStats ds;
  bhcl::QueryStats st = dist.query(qs.data(), 300, p, got, &ds);
  auto single = bhcl::make_index("kdtree", runtime(), pts.data(), 4000);
  single->query(qs.data(), 300, p, ref);
  std::string why;
  EXPECT(identical_rows(got, ref, 0, why), "%s", why.c_str());
  EXPECT(st.nonfinite_queries == 2, "nonfinite %zu", st.nonfinite_queries);
  EXPECT(got.counts[5] == 0 && got.counts[17] == 0 && ds.ranks_visited[5] == 0 && ds.owner[17] == -1,
         "non-finite rows");
  std::size_t multi = 0;
  for (auto v : ds.ranks_visited) multi += v > 1;
  EXPECT(multi == ds.multi_rank_queries, "multi %zu vs %zu", multi, ds.multi_rank_queries);
  unsigned long long c[6] = {ds.owner_sent, ds.owner_received, ds.extra_sent, ds.extra_received,
                             ds.bytes_sent, ds.bytes_received},
                     call[6];
  MPI_Allreduce(c, call, 6, MPI_UNSIGNED_LONG_LONG, MPI_SUM, MPI_COMM_WORLD);
  EXPECT(call[0] == call[1] && call[2] == call[3] && call[4] == call[5],
         "moved queries %llu/%llu, %llu/%llu, bytes %llu/%llu", call[0], call[1], call[2], call[3],
         call[4], call[5]);
  if (g_ranks == 1) EXPECT(call[0] + call[2] + call[4] == 0, "one rank moves nothing");
  // The queries each rank answered add up to the visits (an exact method answers no query twice).
  EXPECT(ds.reanswered == 0, "reanswered %zu", ds.reanswered);
  unsigned long long visits = 0, answered = ds.answered, all_answered = 0, all_visits = 0;
  for (auto v : ds.ranks_visited) visits += static_cast<unsigned long long>(v);
  MPI_Allreduce(&visits, &all_visits, 1, MPI_UNSIGNED_LONG_LONG, MPI_SUM, MPI_COMM_WORLD);
  MPI_Allreduce(&answered, &all_answered, 1, MPI_UNSIGNED_LONG_LONG, MPI_SUM, MPI_COMM_WORLD);
  EXPECT(all_visits == all_answered, "visits %llu, answered %llu", all_visits, all_answered);
}

// Block hashing: recall@10 of the distributed index against that of one process (both against
// the exact answer), on a photon-map-like set.
void blockhash_recall_as_one_process() {
  const std::size_t N = 30000, n = 3000;
  const std::vector<float> pts = bhcl::datasets::cornell_photons(N, 11);
  const std::vector<float> qs = bhcl::datasets::cornell_queries(n, 12);
  auto [pf, pl] = slice(N, g_rank, g_ranks, 0);
  bhcl::DistributedBuildParams bp;
  bp.method = "blockhash";
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), pts.data() + 3 * pf, pl, bp);
  EXPECT(!dist.exact() && dist.method() == "blockhash", "method %s", dist.method().c_str());
  bhcl::SearchParams p;
  p.k = 10;
  p.A = 4;
  bhcl::KnnResult got, approx, truth;
  bhcl::DistributedQueryStats ds;
  dist.query(qs.data(), n, p, got, &ds);  // every rank asks all: each checks the whole answer
  bhcl::make_index("blockhash", runtime(), pts.data(), N)->query(qs.data(), n, p, approx);
  bhcl::make_index("kdtree", runtime(), pts.data(), N)->query(qs.data(), n, p, truth);
  const double r_dist = bhcl::evaluate_accuracy(got, truth).recall;
  const double r_single = bhcl::evaluate_accuracy(approx, truth).recall;
  if (g_rank == 0)
    std::printf("blockhash recall@10 (A 4, Cornell-like 30k): %d rank(s) %.4f, one process %.4f, "
                "%zu of %zu queries visited more than one rank\n",
                g_ranks, r_dist, r_single, ds.multi_rank_queries, n);
  // Issue 25: the shards' grids share one process's cell side (DistributedIndex's build).
  EXPECT(r_dist >= r_single - 0.005, "recall %.4f vs one process %.4f", r_dist, r_single);
  // The default search (A = 0: the grid's exact mode) is one process's exactly.
  bhcl::SearchParams pd;
  pd.k = 10;
  bhcl::KnnResult got_d, single_d;
  dist.query(qs.data(), n, pd, got_d);
  bhcl::make_index("blockhash", runtime(), pts.data(), N)->query(qs.data(), n, pd, single_d);
  const double rd = bhcl::evaluate_accuracy(got_d, truth).recall, rs = bhcl::evaluate_accuracy(single_d, truth).recall;
  EXPECT(rd == rs && rd == 1.0, "default recall %.4f vs one process %.4f", rd, rs);
  // Every border query got its owner's second answer (border_factor 2 by default).
  EXPECT(ds.reanswered == ds.multi_rank_queries, "reanswered %zu of %zu", ds.reanswered, ds.multi_rank_queries);
  EXPECT(r_single > 0.8, "one-process recall %.4f", r_single);
}

// Runs `f`, which must throw bhcl::Error on every rank with a message containing each of
// `needles`.
template <typename F>
void expect_collective_error(const char* what, F f, std::vector<std::string> needles) {
  std::string msg;
  bool threw = false;
  try {
    f();
  } catch (const bhcl::Error& e) {
    threw = true;
    msg = e.what();
  }
  EXPECT(threw, "%s: no error", what);
  for (const auto& needle : needles)
    EXPECT(msg.find(needle) != std::string::npos, "%s: message '%s' lacks '%s'", what, msg.c_str(),
           needle.c_str());
  if (g_rank == 0 && threw) std::printf("%s -> %s\n", what, msg.c_str());
}

// An index that refused calls still answers: the 3 nearest of its first point (built from pts on
// rank 0) start with that point itself.
void expect_still_answers(bhcl::DistributedIndex& dist, const std::vector<float>& pts) {
  bhcl::SearchParams p;
  p.k = 3;
  bhcl::KnnResult r;
  dist.query(pts.data(), 4, p, r);
  EXPECT(r.counts[0] == 3 && r.ids[0] == 0 && r.dist2[0] == 0.0f, "row 0: %d %d %g", r.counts[0], r.ids[0], r.dist2[0]);
}

void failures_reach_every_rank() {
  const std::vector<float> pts = bhcl::datasets::uniform(1000, 21);
  const int bad = g_ranks - 1;
  {
    // The last rank's part holds a NaN point: every rank's constructor throws, naming it.
    std::vector<float> mine = pts;
    if (g_rank == bad) mine[3 * 10 + 2] = std::numeric_limits<float>::quiet_NaN();
    expect_collective_error(
        "a NaN point on one rank",
        [&] { bhcl::DistributedIndex d(MPI_COMM_WORLD, runtime(), mine.data(), 1000); },
        {"rank " + std::to_string(bad), "non-finite", "point " + std::to_string(1000 * bad + 10)});
  }
  {
    bhcl::DistributedBuildParams bp;
    bp.method = g_rank == bad ? "no-such-method" : "kdtree";
    expect_collective_error(
        "an unknown method on one rank",
        [&] { bhcl::DistributedIndex d(MPI_COMM_WORLD, runtime(), pts.data(), 1000, bp); },
        {"rank " + std::to_string(bad), "no-such-method"});
  }
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), pts.data(), g_rank == 0 ? 1000 : 0);
  {
    bhcl::SearchParams p;
    p.k = g_rank == bad ? 0 : 5;
    bhcl::KnnResult r;
    expect_collective_error("k = 0 on one rank", [&] { dist.query(pts.data(), 10, p, r); },
                            {"rank " + std::to_string(bad), "k = 0"});
    p.k = g_rank == bad ? 6 : 5;
    if (g_ranks > 1)
      expect_collective_error("different k per rank", [&] { dist.query(pts.data(), 10, p, r); },
                              {"rank " + std::to_string(bad) + " has k = 6 where rank 0 has 5"});
  }
  {
    // A failure inside the local query (count_examined on a method that does not count) on
    // whichever rank answers: every rank gets it.
    bhcl::SearchParams p;
    p.count_examined = true;
    bhcl::KnnResult r;
    expect_collective_error("count_examined on kdtree", [&] { dist.query(pts.data(), 10, p, r); },
                            {"count_examined"});
  }
  expect_still_answers(dist, pts);  // after the failures
}

// Issue 22: ranks started with different parameters are refused on every rank, naming the first
// differing rank, the parameter and both values (a hash of every build and search parameter is
// checked on the build and on each call); before, a different method or A on one rank ran and
// reported "exact" while the rows it answered were another method's.
void parameters_must_agree() {
  if (g_ranks < 2) return;
  const std::vector<float> pts = bhcl::datasets::uniform(2000, 23);
  const int bad = g_ranks - 1;
  const std::string who = "rank " + std::to_string(bad) + " has ";
  {
    bhcl::DistributedBuildParams bp;
    bp.method = g_rank == bad ? "bruteforce" : "kdtree";
    expect_collective_error(
        "a different method on one rank",
        [&] { bhcl::DistributedIndex d(MPI_COMM_WORLD, runtime(), pts.data(), 2000, bp); },
        {who + "method = bruteforce where rank 0 has kdtree"});
  }
  {
    bhcl::DistributedBuildParams bp;
    if (g_rank == bad) bp.options.set("leaf-size", "8");
    expect_collective_error(
        "a method option on one rank only",
        [&] { bhcl::DistributedIndex d(MPI_COMM_WORLD, runtime(), pts.data(), 2000, bp); },
        {who + "option leaf-size = 8 where rank 0 has (not set)"});
  }
  {
    bhcl::DistributedBuildParams bp;
    bp.boxes_per_rank = g_rank == bad ? 4 : 16;
    expect_collective_error(
        "different boxes_per_rank",
        [&] { bhcl::DistributedIndex d(MPI_COMM_WORLD, runtime(), pts.data(), 2000, bp); },
        {who + "boxes_per_rank = 4 where rank 0 has 16"});
  }
  bhcl::DistributedBuildParams bp;
  bp.method = "blockhash";
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), pts.data(), g_rank == 0 ? 2000 : 0, bp);
  {
    bhcl::SearchParams p;
    p.k = 5;
    p.A = g_rank == bad ? 2.0f : 4.0f;
    bhcl::KnnResult r;
    expect_collective_error("a different A on one rank", [&] { dist.query(pts.data(), 10, p, r); },
                            {who + "A = 2 where rank 0 has 4"});
    p.A = 4;
    p.recall_target = g_rank == bad ? 0.9 : 0.0;
    expect_collective_error("a different recall target on one rank", [&] { dist.query(pts.data(), 10, p, r); },
                            {who + "recall_target = 0.9"});
  }
  {
    bhcl::RadiusParams rp;
    rp.max_results = g_rank == bad ? 3 : 0;
    bhcl::RadiusResult rr;
    expect_collective_error("a different cap on one rank",
                            [&] { dist.radius_search(pts.data(), 10, 0.1f, rp, rr); },
                            {who + "max_results = 3 where rank 0 has 0"});
    rp.max_results = 0;
    expect_collective_error("a different radius on one rank",
                            [&] { dist.radius_search(pts.data(), 10, g_rank == bad ? 0.2f : 0.1f, rp, rr); },
                            {who + "radius = 0.200000003 where rank 0 has 0.100000001"});
  }
  expect_still_answers(dist, pts);  // agreeing again
}

// Issue 25: global ids are int64. With an id base past 2^32 every id of the answer is the base
// plus the single-process id (kNN and radius, exact methods and block hashing, ids spread over
// every rank's shard); the int32 calls refuse such an index on every rank before any work and
// answer one whose largest id is exactly 2^31 - 1; a bad id base, one differing between ranks,
// and more points than the ranks' shards can hold (2^31 - 2 each) are refused on every rank
// before any point is read or allocated.
void ids_past_int32() {
  const std::vector<float> pts = bhcl::datasets::uniform(2500, 31);
  const std::vector<float> qs = queries_for(pts, 32, 40);
  const std::size_t N = pts.size() / 3, n = qs.size() / 3;
  auto [pf, pl] = slice(N, g_rank, g_ranks, 0);
  auto [qf, ql] = slice(n, g_rank, g_ranks, 1);
  const std::int64_t base = (std::int64_t(1) << 32) + 5;
  for (const std::string method : {"kdtree", "blockhash"}) {
    bhcl::DistributedBuildParams b0, bp;
    b0.method = bp.method = method;
    bp.id_base = base;
    bhcl::DistributedIndex d0(MPI_COMM_WORLD, runtime(), pts.data() + 3 * pf, pl, b0);
    bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), pts.data() + 3 * pf, pl, bp);
    EXPECT(dist.id_base() == base && dist.id_bound() == base + std::int64_t(N) && !dist.ids_fit_int32() &&
               d0.ids_fit_int32(),
           "%s: id_base %lld id_bound %lld", method.c_str(), (long long)dist.id_base(), (long long)dist.id_bound());
    bool shard_ok = dist.shard_ids().size() == d0.shard_ids().size();
    for (std::size_t i = 0; shard_ok && i < dist.shard_ids().size(); ++i)
      shard_ok = dist.shard_ids()[i] == d0.shard_ids()[i] + base;
    EXPECT(shard_ok, "%s: shard ids are not the base plus base 0's", method.c_str());
    // The reference: exact methods one process, block hashing the same distributed build at base 0.
    std::unique_ptr<bhcl::Index> single = bhcl::make_index(method, runtime(), pts.data(), N);
    for (int k : {1, 10}) {
      bhcl::SearchParams p;
      p.k = k;
      if (method == "blockhash") p.A = 2;  // a budget: the approximate path (border re-answers)
      bhcl::KnnResult ref32;
      bhcl::KnnResult64 got, ref;
      if (method == "kdtree") {
        single->query(qs.data(), n, p, ref32);
        ref.resize(ql, k);
        for (std::size_t i = 0; i < ql * std::size_t(k); ++i) {
          ref.ids[i] = ref32.ids[qf * std::size_t(k) + i];
          ref.dist2[i] = ref32.dist2[qf * std::size_t(k) + i];
        }
        for (std::size_t i = 0; i < ql; ++i) ref.counts[i] = ref32.counts[qf + i];
      } else {
        d0.query(qs.data() + 3 * qf, ql, p, ref);
      }
      dist.query(qs.data() + 3 * qf, ql, p, got);
      std::size_t bad = 0, past = 0;
      for (std::size_t i = 0; i < ql * std::size_t(k); ++i) {
        const std::int64_t want = ref.ids[i] < 0 ? -1 : ref.ids[i] + base;
        bad += got.ids[i] != want || std::memcmp(&got.dist2[i], &ref.dist2[i], 4) != 0;
        past += got.ids[i] > std::int64_t(0x7fffffff);
      }
      for (std::size_t i = 0; i < ql; ++i) bad += got.counts[i] != ref.counts[i];
      EXPECT(bad == 0 && (ql == 0 || past > 0), "%s k=%d: %zu entries differ from the reference + base, %zu past 2^31",
             method.c_str(), k, bad, past);
    }
    // Radius search, int64 slices: the base plus the reference's ids.
    {
      const float r = 0.06f;
      bhcl::RadiusResult64 got, ref;
      bhcl::RadiusParams rp;
      d0.radius_search(qs.data() + 3 * qf, ql, r, rp, ref);
      dist.radius_search(qs.data() + 3 * qf, ql, r, rp, got);
      bool same = got.offsets == ref.offsets && got.found == ref.found && got.dist2 == ref.dist2;
      for (std::size_t j = 0; same && j < got.ids.size(); ++j) same = got.ids[j] == ref.ids[j] + base;
      EXPECT(same, "%s radius: the slices are not base 0's plus the base", method.c_str());
    }
    // The int32 calls: refused on every rank, naming the way out.
    bhcl::SearchParams p;
    p.k = 3;
    bhcl::KnnResult r32;
    expect_collective_error("int32 kNN ids past 2^31", [&] { dist.query(qs.data(), g_rank == 0 ? 5 : 0, p, r32); },
                            {"the global ids reach 4294969800", "past int32: pass a KnnResult64"});
    bhcl::RadiusResult rr32;
    expect_collective_error("int32 radius ids past 2^31",
                            [&] { dist.radius_search(qs.data(), g_rank == 0 ? 5 : 0, 0.1f, {}, rr32); },
                            {"past int32: pass a RadiusResult64"});
  }
  {
    // The largest id exactly 2^31 - 1: the int32 call answers, ids as the int64 call's.
    bhcl::DistributedBuildParams bp;
    bp.id_base = std::int64_t(0x7fffffff) - std::int64_t(N) + 1;
    bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), pts.data() + 3 * pf, pl, bp);
    bhcl::SearchParams p;
    p.k = 4;
    bhcl::KnnResult r32;
    bhcl::KnnResult64 r64;
    dist.query(qs.data() + 3 * qf, ql, p, r32);
    dist.query(qs.data() + 3 * qf, ql, p, r64);
    bool same = r32.ids.size() == r64.ids.size() && dist.ids_fit_int32();
    for (std::size_t i = 0; same && i < r32.ids.size(); ++i) same = std::int64_t(r32.ids[i]) == r64.ids[i];
    EXPECT(same, "int32 ids at the edge differ from the int64 call's");
  }
  {
    bhcl::DistributedBuildParams bp;
    bp.id_base = -1;
    expect_collective_error("a negative id base",
                            [&] { bhcl::DistributedIndex d(MPI_COMM_WORLD, runtime(), pts.data() + 3 * pf, pl, bp); },
                            {"id_base must be in [0, 2^62], got -1"});
  }
  if (g_ranks > 1) {
    bhcl::DistributedBuildParams bp;
    bp.id_base = g_rank == g_ranks - 1 ? 7 : 0;
    expect_collective_error("a different id base on one rank",
                            [&] { bhcl::DistributedIndex d(MPI_COMM_WORLD, runtime(), pts.data() + 3 * pf, pl, bp); },
                            {"rank " + std::to_string(g_ranks - 1) + " has id_base = 7 where rank 0 has 0"});
  }
  {
    // 2^31 points per rank, from a 16-point buffer: more than one shard per rank can hold. Refused
    // from the counts alone (the points are never read: a read would fault).
    const std::size_t huge = std::size_t(1) << 31;
    const std::vector<float> tiny(48, 0.5f);
    expect_collective_error(
        "2^31 points per rank", [&] { bhcl::DistributedIndex d(MPI_COMM_WORLD, runtime(), tiny.data(), huge); },
        {"points over " + std::to_string(g_ranks) + " ranks make shards of up to 2147483648 points",
         "past one index's int32 id range (2^31 - 2 points): use at least " + std::to_string(g_ranks + 1) + " ranks"});
  }
}

// --- insert and remove (issue 39)

// Every rank's `mine`, concatenated in rank order, on every rank.
template <typename T>
std::vector<T> gathered(const std::vector<T>& mine) {
  const int n = static_cast<int>(mine.size() * sizeof(T));
  std::vector<int> counts(static_cast<std::size_t>(g_ranks)), displ(static_cast<std::size_t>(g_ranks));
  MPI_Allgather(&n, 1, MPI_INT, counts.data(), 1, MPI_INT, MPI_COMM_WORLD);
  int total = 0;
  for (int r = 0; r < g_ranks; ++r) displ[static_cast<std::size_t>(r)] = total, total += counts[static_cast<std::size_t>(r)];
  std::vector<T> all(static_cast<std::size_t>(total) / sizeof(T));
  MPI_Allgatherv(mine.data(), n, MPI_BYTE, all.data(), counts.data(), displ.data(), MPI_BYTE, MPI_COMM_WORLD);
  return all;
}

// kNN (k 1 and 10, and 10 within a radius) and radius search of this rank's share of `qs`
// through `dist`, against `single` over all of them: bit for bit. Empty when equal, else what differs.
std::string differs_from_one_process(const bhcl::DistributedIndex& dist, const bhcl::Index& single,
                                     const std::vector<float>& qs, float radius) {
  const std::size_t n = qs.size() / 3;
  auto [qf, ql] = slice(n, g_rank, g_ranks, 1);
  std::string why;
  for (int k : {1, 10})
    for (bool cut : {false, true}) {
      if (cut && k == 1) continue;
      bhcl::SearchParams p;
      p.k = k;
      if (cut) p.max_radius = radius * 0.5f;
      bhcl::KnnResult ref, got;
      single.query(qs.data(), n, p, ref);
      dist.query(qs.data() + 3 * qf, ql, p, got);
      if (!identical_rows(got, ref, qf, why)) return "k=" + std::to_string(k) + (cut ? " within a radius: " : ": ") + why;
    }
  bhcl::RadiusResult ref, got;
  single.radius_search(qs.data(), n, radius, {}, ref);
  dist.radius_search(qs.data() + 3 * qf, ql, radius, {}, got);
  if (!identical_slices(got, ref, qf, why)) return "radius: " + why;
  return {};
}

// Every live point of every shard lies in one of its rank's boxes, and every box holds a live
// point of its shard (a remove shrank it): checked on each rank for its own shard, with its points
// fetched from `all` (every point issued, by id).
std::string boxes_wrong(const bhcl::DistributedIndex& dist, const std::vector<float>& all) {
  const std::vector<std::int64_t> live = dist.shard_live_ids();
  const auto& boxes = dist.boxes(dist.rank());
  std::vector<bool> used(boxes.size(), false);
  for (std::int64_t id : live) {
    const float* p = &all[3 * static_cast<std::size_t>(id)];
    bool in = false;
    for (std::size_t j = 0; j < boxes.size(); ++j) {
      const bhcl::ShardBox& b = boxes[j];
      const bool inside = p[0] >= b.lo[0] && p[0] <= b.hi[0] && p[1] >= b.lo[1] && p[1] <= b.hi[1] &&
                          p[2] >= b.lo[2] && p[2] <= b.hi[2];
      in = in || inside;
      if (inside) used[j] = true;
    }
    if (!in) return "live point " + std::to_string(id) + " lies in none of its rank's boxes";
  }
  for (std::size_t j = 0; j < boxes.size(); ++j)
    if (!used[j]) return "box " + std::to_string(j) + " holds no live point of its shard";
  return {};
}

// Points around `near` (copies moved by up to `spread`), some outside the build's box.
std::vector<float> new_points(const std::vector<float>& near, std::size_t count, float spread, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<std::size_t> pick(0, near.size() / 3 - 1);
  std::uniform_real_distribution<float> move(-spread, spread), box(-0.3f, 1.3f);
  std::vector<float> out;
  for (std::size_t i = 0; i < count; ++i) {
    const std::size_t j = pick(rng);
    for (int d = 0; d < 3; ++d) {
      // A fifth exact copies (distance ties with older ids), a fifth anywhere in a grown box.
      const float v = i % 5 == 0 ? near[3 * j + d] : i % 5 == 1 ? box(rng) : near[3 * j + d] + move(rng);
      out.push_back(v);
    }
  }
  return out;
}

// One update sequence on `dist` and `single`, checked after each step against one process.
void update_sequence(const Set& s, const std::string& method) {
  const std::size_t N = s.points.size() / 3;
  const auto dist = shard_of(s, method);
  std::unique_ptr<bhcl::Index> single = bhcl::make_index(method, runtime(), s.points.data(), N);
  std::vector<float> all = s.points;  // every point issued, by id
  const float radius = s.name == "clustered" ? 0.0008f : 0.05f;
  const std::string tag = method + " " + s.name;
  auto check = [&](const char* step, const std::vector<float>& extra_queries) {
    std::vector<float> qs = s.queries;
    qs.insert(qs.end(), extra_queries.begin(), extra_queries.end());
    const std::string why = differs_from_one_process(*dist, *single, qs, radius);
    EXPECT(why.empty(), "%s after %s: %s", tag.c_str(), step, why.c_str());
    EXPECT(dist->size() == single->size() && dist->id_bound() == single->id_bound(),
           "%s after %s: size %zu vs %zu, id_bound %lld vs %d", tag.c_str(), step, dist->size(), single->size(),
           (long long)dist->id_bound(), single->id_bound());
    const std::string boxes = boxes_wrong(*dist, all);
    EXPECT(boxes.empty(), "%s after %s: %s", tag.c_str(), step, boxes.c_str());
  };
  auto insert_both = [&](const std::vector<float>& batch, int skew, const char* step) {
    const std::size_t m = batch.size() / 3;
    auto [f, l] = slice(m, g_rank, g_ranks, skew);
    const std::int64_t bound = dist->id_bound();
    bhcl::DistributedUpdateStats us;
    const std::int64_t first = dist->insert(batch.data() + 3 * f, l, &us);
    const std::int32_t first1 = single->insert(batch.data(), m);
    all.insert(all.end(), batch.begin(), batch.end());
    EXPECT(first == bound + std::int64_t(f) && first1 == bound && us.n_global == m && us.n_input == l,
           "%s %s: first id %lld (rank's offset %zu), one process %d, id_bound before %lld", tag.c_str(), step,
           (long long)first, f, first1, (long long)bound);
    check(step, batch);
  };
  auto remove_both = [&](const std::vector<std::int64_t>& ids, int skew, const char* step) {
    auto [f, l] = slice(ids.size(), g_rank, g_ranks, skew);
    dist->remove(ids.data() + f, l);
    std::vector<std::int32_t> ids32(ids.begin(), ids.end());
    single->remove(ids32.data(), ids32.size());
    check(step, {});
  };

  // 1. 10 % new points, uneven over the ranks (rank 1 none at 3 ranks or more).
  insert_both(new_points(s.points, N / 10, 0.02f, 7), 2, "a 10 % insert");
  // 2. 10 % of the issued ids removed, old and new alike, in a shuffled order.
  {
    std::vector<std::int64_t> ids(static_cast<std::size_t>(dist->id_bound()));
    for (std::size_t i = 0; i < ids.size(); ++i) ids[i] = std::int64_t(i);
    std::shuffle(ids.begin(), ids.end(), std::mt19937_64(11));
    ids.resize(ids.size() / 10);
    remove_both(ids, 1, "a 10 % remove");
  }
  // 3. The crop: every live point of the last non-empty shard removed (that rank leaves the
  //    routing), by the rank holding them; then points inserted where they were (they go to other
  //    ranks). At one rank: the points in the lower x half.
  std::vector<float> where;
  {
    std::vector<std::int64_t> mine;
    const auto& sizes = dist->build_stats().shard_points_all;
    int last = -1;
    for (int r = 0; r < g_ranks; ++r)
      if (sizes[static_cast<std::size_t>(r)] > 0) last = r;
    if (g_ranks > 1 && g_rank == last) mine = dist->shard_live_ids();
    std::vector<std::int64_t> ids = gathered(mine);
    if (g_ranks == 1)
      for (std::int64_t id : dist->shard_live_ids())
        if (all[3 * std::size_t(id)] < 0.5f) ids.push_back(id);
    for (std::int64_t id : ids) where.insert(where.end(), &all[3 * std::size_t(id)], &all[3 * std::size_t(id)] + 3);
    remove_both(ids, 0, "a crop");
    if (g_ranks > 1 && g_rank == last) EXPECT(dist->shard_size() == 0 && !dist->local_index(), "%s: the cropped shard holds %zu", tag.c_str(), dist->shard_size());
  }
  // 4. New points where the crop was, then a small (1 %) insert anywhere.
  if (!where.empty()) insert_both(new_points(where, std::max<std::size_t>(N / 20, 1), 0.01f, 13), 0, "an insert into the cropped region");
  insert_both(new_points(s.points, N / 100, 0.02f, 17), 1, "a 1 % insert");
}

void updates_match_single_process() {
  for (const Set& s : exact_sets())
    for (const std::string& method : bhcl::method_names()) {
      // Block hashing (its default search, exact) and FLANN on two sets: the rest on all four.
      if ((method == "blockhash" || method == "flann") && s.name != "uniform" && s.name != "duplicates") continue;
      update_sequence(s, method);
    }
}

// Index::insert / remove's errors, through the distributed index: the same message on every
// rank, and the index unchanged (its answers are still one process's).
void update_errors_reach_every_rank() {
  const std::vector<float> pts = bhcl::datasets::uniform(1000, 41);
  const std::vector<float> qs = queries_for(pts, 42, 30);
  const std::size_t N = pts.size() / 3;
  auto [pf, pl] = slice(N, g_rank, g_ranks, 0);
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), pts.data() + 3 * pf, pl);
  auto single = bhcl::make_index("kdtree", runtime(), pts.data(), N);
  const int last = g_ranks - 1;
  const std::string rl = "rank " + std::to_string(last);
  // A NaN point on the last rank: named by the id it would take, its rank and its place there.
  {
    std::vector<float> mine = {0.5f, 0.5f, 0.5f, 0.25f, 0.25f, 0.25f};
    if (g_rank == last) mine.insert(mine.end(), {0.1f, std::numeric_limits<float>::quiet_NaN(), 0.1f});
    const std::string id = std::to_string(N + 2 * std::size_t(g_ranks));  // the last rank's third point
    expect_collective_error("a NaN point inserted on one rank",
                            [&] { dist.insert(mine.data(), mine.size() / 3); },
                            {"DistributedIndex::insert: " + rl + ": inserted points: point " + id +
                             " (this rank's point 2) has a non-finite coordinate"});
  }
  expect_collective_error("an insert of no points", [&] { dist.insert(nullptr, 0); },
                          {"DistributedIndex::insert: no points on any rank"});
  expect_collective_error("a null point array", [&] { dist.insert(nullptr, g_rank == last ? 4 : 0); },
                          {"DistributedIndex::insert: " + rl + ": points is null with n = 4"});
  EXPECT(dist.id_bound() == std::int64_t(N) && dist.size() == N, "a refused insert changed the index: id_bound %lld",
         (long long)dist.id_bound());
  // Removes: one valid, then the refused ones.
  {
    const std::int64_t five = 5;
    dist.remove(&five, g_rank == 0 ? 1 : 0);
    const std::int32_t five32 = 5;
    single->remove(&five32, 1);
  }
  auto remove_on = [&](int rank, std::vector<std::int64_t> ids) {
    return [&dist, rank, ids] { dist.remove(ids.data(), g_rank == rank ? ids.size() : 0); };
  };
  expect_collective_error("an id outside on one rank", remove_on(last, {3, 1000}),
                          {"DistributedIndex::remove: id 1000 (" + rl + "'s entry 1) is outside the issued ids [0, 1000)"});
  expect_collective_error("a negative id", remove_on(0, {-1}), {"id -1 (rank 0's entry 0) is outside"});
  expect_collective_error("an id removed before", remove_on(last, {9, 5}),
                          {"DistributedIndex::remove: id 5 (" + rl + "'s entry 1) was already removed"});
  {
    // The same id from rank 0 and the last rank (at one rank: twice in rank 0's list).
    std::vector<std::int64_t> mine;
    if (g_rank == 0) mine.push_back(7);
    if (g_rank == last) mine.insert(mine.end(), {8, 7});
    const std::string again = g_ranks == 1 ? "rank 0's entry 2" : rl + "'s entry 1";
    expect_collective_error("an id on two ranks", [&] { dist.remove(mine.data(), mine.size()); },
                            {"DistributedIndex::remove: id 7 (rank 0's entry 0) appears twice (again as id 7 (" +
                             again + "))"});
  }
  expect_collective_error("removing every point",
                          [&] {
                            const std::vector<std::int64_t> mine = dist.shard_live_ids();
                            dist.remove(mine.data(), mine.size());
                          },
                          {"DistributedIndex::remove: removing all 999 live points would leave the index empty"});
  expect_collective_error("a null id array", [&] { dist.remove(nullptr, g_rank == last ? 2 : 0); },
                          {"DistributedIndex::remove: " + rl + ": ids is null with n = 2"});
  expect_collective_error("a remove of no ids", [&] { dist.remove(nullptr, 0); },
                          {"DistributedIndex::remove: no ids on any rank"});
  EXPECT(dist.size() == 999 && dist.removed_count() == 1 && dist.id_bound() == 1000,
         "refused removes changed the index: size %zu, removed %zu", dist.size(), dist.removed_count());
  const std::string why = differs_from_one_process(dist, *single, qs, 0.05f);
  EXPECT(why.empty(), "after the refused updates: %s", why.c_str());
}

// Fewer points than ranks (empty shards), then inserts everywhere: they go to the non-empty
// shards; and an id base past 2^32: the updated answers are base 0's plus the base.
void updates_with_empty_shards_and_a_wide_id_base() {
  const std::vector<float> pts = {0, 0, 0, 1, 0, 0, 0.5f, 0.5f, 0.5f};
  const bool last = g_rank == g_ranks - 1;
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), last ? pts.data() : nullptr, last ? 3 : 0);
  auto single = bhcl::make_index("kdtree", runtime(), pts.data(), 3);
  const std::vector<float> batch = bhcl::datasets::uniform(200, 43);
  auto [f, l] = slice(200, g_rank, g_ranks, 0);
  dist.insert(batch.data() + 3 * f, l);
  single->insert(batch.data(), 200);
  std::vector<float> all = pts;
  all.insert(all.end(), batch.begin(), batch.end());
  std::string why = differs_from_one_process(dist, *single, queries_for(all, 44, 20), 0.1f);
  EXPECT(why.empty(), "inserts with empty shards: %s", why.c_str());
  why = boxes_wrong(dist, all);
  EXPECT(why.empty(), "inserts with empty shards: %s", why.c_str());

  const std::int64_t base = (std::int64_t(1) << 33) + 3;
  const std::size_t N = 2000;
  const std::vector<float> p2 = bhcl::datasets::uniform(N, 45);
  auto [pf, pl] = slice(N, g_rank, g_ranks, 0);
  bhcl::DistributedBuildParams b0, bw;
  bw.id_base = base;
  bhcl::DistributedIndex d0(MPI_COMM_WORLD, runtime(), p2.data() + 3 * pf, pl, b0);
  bhcl::DistributedIndex dw(MPI_COMM_WORLD, runtime(), p2.data() + 3 * pf, pl, bw);
  const std::vector<float> more = bhcl::datasets::uniform(300, 46);
  auto [mf, ml] = slice(300, g_rank, g_ranks, 1);
  const std::int64_t first0 = d0.insert(more.data() + 3 * mf, ml), firstw = dw.insert(more.data() + 3 * mf, ml);
  EXPECT(firstw == first0 + base && dw.id_bound() == base + 2300, "wide base: first %lld, id_bound %lld",
         (long long)firstw, (long long)dw.id_bound());
  std::vector<std::int64_t> gone0, gonew;
  for (std::int64_t id = g_rank; id < 2300; id += 7 * g_ranks) gone0.push_back(id), gonew.push_back(id + base);
  d0.remove(gone0.data(), gone0.size());
  dw.remove(gonew.data(), gonew.size());
  const std::vector<float> qs = queries_for(p2, 47, 20);
  bhcl::SearchParams p;
  p.k = 8;
  bhcl::KnnResult64 r0, rw;
  d0.query(qs.data(), qs.size() / 3, p, r0);
  dw.query(qs.data(), qs.size() / 3, p, rw);
  bool same = r0.counts == rw.counts && r0.dist2 == rw.dist2;
  for (std::size_t i = 0; same && i < r0.ids.size(); ++i) same = rw.ids[i] == (r0.ids[i] < 0 ? -1 : r0.ids[i] + base);
  EXPECT(same, "wide base: the updated answers are not base 0's plus the base");
  bhcl::KnnResult r32;
  expect_collective_error("int32 kNN after updates past 2^31", [&] { dw.query(qs.data(), 0, p, r32); },
                          {"past int32: pass a KnnResult64"});
}

// Issue 22: `--hang-rank R` (a CTest case of its own, BHCL_MPI_DEADLINE_S set short): rank R stops
// answering before a query (it sleeps); the other ranks must not wait forever: the query's first
// step ends the job (MPI_Abort) with a message naming rank R. Returns only if nobody noticed.
int hang_one_rank(int hung) {
  const std::vector<float> pts = bhcl::datasets::uniform(2000, 24);
  bhcl::DistributedIndex dist(MPI_COMM_WORLD, runtime(), pts.data(), g_rank == 0 ? 2000 : 0);
  if (g_rank == 0) std::printf("built; rank %d now stops answering\n", hung), std::fflush(stdout);
  if (g_rank == hung) {
    for (int i = 0; i < 600; ++i) std::this_thread::sleep_for(std::chrono::seconds(1));
  } else {
    bhcl::SearchParams p;
    p.k = 3;
    bhcl::KnnResult r;
    dist.query(pts.data(), 4, p, r);
  }
  std::fprintf(stderr, "rank %d: FAILED: the query returned although rank %d never called it\n", g_rank, hung);
  return 1;
}

template <typename F>
void run(const char* name, F f) {
  const int before = g_failures;
  std::string err;
  try {
    f();
  } catch (const std::exception& e) {
    // Only the library's collective errors reach here, thrown on every rank alike.
    err = e.what();
    ++g_failures;
  }
  int mine = g_failures - before, all = 0;
  MPI_Allreduce(&mine, &all, 1, MPI_INT, MPI_SUM, MPI_COMM_WORLD);
  if (!err.empty()) std::fprintf(stderr, "rank %d: %s: unexpected error: %s\n", g_rank, name, err.c_str());
  if (g_rank == 0) std::printf("[%s] %s (%d ranks)\n", all ? "FAIL" : " ok ", name, g_ranks);
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  MPI_Init(&argc, &argv);
  MPI_Comm_rank(MPI_COMM_WORLD, &g_rank);
  MPI_Comm_size(MPI_COMM_WORLD, &g_ranks);
  if (argc == 3 && std::strcmp(argv[1], "--hang-rank") == 0) {
    const int rc = hang_one_rank(std::atoi(argv[2]));
    MPI_Finalize();
    return rc;
  }
  run("exact methods equal one process bit for bit", exact_methods_match_single_process);
  run("fewer points than ranks", fewer_points_than_ranks);
  run("non-finite queries and statistics", nonfinite_queries_and_stats);
  run("radius search as one process", radius_search_as_one_process);
  run("block hashing recall as one process", blockhash_recall_as_one_process);
  run("a failing rank fails the call on every rank", failures_reach_every_rank);
  run("ranks passing different parameters are refused on every rank", parameters_must_agree);
  run("64-bit global ids past 2^31", ids_past_int32);
  run("inserts and removes equal one process's after the same updates", updates_match_single_process);
  run("update errors reach every rank and change nothing", update_errors_reach_every_rank);
  run("updates with empty shards and an id base past 2^32", updates_with_empty_shards_and_a_wide_id_base);
  int all = 0;
  MPI_Allreduce(&g_failures, &all, 1, MPI_INT, MPI_SUM, MPI_COMM_WORLD);
  if (g_rank == 0) std::printf("%s: %d failed check(s) over %d rank(s)\n", all ? "FAILED" : "passed", all, g_ranks);
  MPI_Finalize();
  return all ? 1 : 0;
}
