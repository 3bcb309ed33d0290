// An index distributed over the ranks of an MPI communicator (an optional component: the target
// blockhash_cl::distributed, built when CMake finds MPI and BHCL_WITH_MPI is on).
//
// Design (docs/DISTRIBUTED.md has the measurements):
//  - The points are sharded by Hilbert-key range, balanced by count: keys of 21 bits per axis over
//    the bounding box of ALL points (the block-hash build's quantiser), ranks cut the global order
//    by (key, global index) into R runs whose sizes differ by at most one. Each rank builds a local
//    index of any registered method (make_index) over its run, and every rank knows every rank's
//    first key and the bounding boxes of `boxes_per_rank` consecutive sub-runs of its shard (so a
//    flat or L-shaped shard prunes better than its one bounding box would).
//  - A query goes to the rank owning its key (phase 1); the k-th distance found there (or the
//    maximum radius, when fewer than k were found) bounds a ball, and the query then goes to every
//    other rank with a box meeting the ball (phase 2). The rows are merged by (distance, global
//    index) on the rank that asked.
//  - Exact methods: the result equals the single-process result of the same method bit for bit
//    (same ids, same float distances, same counts), whatever the number of ranks and however the
//    points and queries were spread over them. Why: a local row holds the k best of its shard by
//    (distance, index) with local indices increasing with global ones (a shard is stored in global
//    order), every point of the global k best lies in its shard's k best, and the ball test is
//    conservative (it admits every box whose float distance could round to the k-th distance).
//  - Block hashing's grid: every shard is built with the cell side one process would choose for
//    all the points (from the shards' own sides and sizes, index.cpp), not its own, so that a
//    budget A means the same on every shard (issue 25: recall@10 at A = 4, Cornell-like 30k:
//    0.9859 / 0.9769 at 2 / 4 ranks with the shards' own sides, 0.9897 / 0.9905 with the global
//    one, one process 0.9892). The default search (the grid's exact mode) is exact.
//  - Approximate methods (block hashing): each shard answers with its own approximate row, and a
//    query whose ball meets other ranks is answered a second time by its owner with a larger
//    budget (DistributedBuildParams::border_factor). The merged rows' recall@k is that of one
//    process within about half a point at 4 ranks (measured in docs/DISTRIBUTED.md).
//
// Input and output: every rank passes ITS part of the points (any split, including all on rank 0
// and none elsewhere); the global id of a point is DistributedBuildParams::id_base (0 by default)
// plus its position in the concatenation of the ranks' parts in rank order. Global ids are 64-bit:
// the points over all ranks may pass 2^31 (each shard holds at most 2^31 - 2, one local index's
// int32 range), and the results that carry them (KnnResult64, RadiusResult64) hold int64 ids;
// the KnnResult / RadiusResult calls (int32 ids) remain for an index whose ids all fit, and
// refuse one whose ids do not, before any work. Queries are likewise per rank: each rank passes its own (possibly
// none) and gets their rows, and per-query statistics, back in its order. The `bhcl knn
// --distributed` tool reads both files on rank 0 and writes the results there.
//
// Collective calls: the constructor and query() must be called by every rank of the communicator
// with the same parameters: every field of DistributedBuildParams (the method options included),
// SearchParams and RadiusParams is checked against rank 0's (one allreduce of a hash), and a
// difference makes the call throw on every rank naming the first differing rank, the parameter
// and both values. Every collective step has a deadline (DistributedBuildParams::deadline_s): a
// rank that stops answering ends the job with a message naming it, never a hang. A failure on any rank (bad points, an
// index that cannot be built, a query that throws) makes the call throw bhcl::Error on EVERY rank,
// with the first failing rank's message; no rank is left waiting in a collective. The index works
// on its own duplicate of the communicator, so its messages never meet the caller's.
//
// Updates (insert / remove, issue 39; docs/UPDATES.md): collective, each rank passing ITS part
// (as the constructor): the new points of all ranks take the global ids id_bound(),
// id_bound() + 1, ... in the order of the concatenation of the ranks' parts in rank order (the
// rule of Index::insert, the ranks' parts one batch); a removed id is never reused. A new point
// goes to the rank that owns its region (owner_of: its Hilbert key under the build's quantiser,
// clamped for points outside the build's box), appended to that rank's local index (Index::insert:
// its local ids follow the shard's, as its global ids do, so ties still fall to the lower global
// id), and that rank's shared boxes grow to hold it (the sub-run of its key); a remove goes to the
// rank holding each id, and the boxes of the sub-runs that lost points are recomputed over their
// live points, so the boxes every rank keeps for routing always bound the live points of each
// shard. A shard whose points are all removed leaves the routing (its key range falls to the
// previous non-empty shard). The partition is not re-cut: many updates in one region unbalance
// the shards (a fresh build balances them again).
#pragma once

#include <mpi.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/knn.hpp"

namespace bhcl {

// An axis-aligned box a rank shares: the bounds of a run of its shard.
struct ShardBox {
  float lo[3], hi[3];
};

struct DistributedBuildParams {
  std::string method = "kdtree";  // any name of method_names()
  MethodOptions options;          // the method's build options (load_index / save_index refused)
  // Boxes per rank shared with every rank: the bounding boxes of this many consecutive runs of the
  // shard in Hilbert order, [1, 1024]. More boxes prune better and cost 24 bytes each per rank.
  int boxes_per_rank = 16;
  // Approximate methods: a query whose ball meets other ranks (a border query) is answered a
  // second time by its owner with this many times the budget A (the A tuned for
  // SearchParams::recall_target, when one is set), in phase 2, and the rows are merged. Why: at a
  // shard's edge block hashing sees half a neighbourhood, and the owner's row alone loses recall
  // on exactly these queries (docs/DISTRIBUTED.md measures it); 1 turns the second answer off.
  // Exact methods ignore it. [1, 1024].
  float border_factor = 2;
  // The deadline of every collective step, in seconds: a rank that has not reached a step this
  // long after rank 0 (or rank 0, for the others) ends the job with MPI_Abort and a message on
  // stderr naming it, instead of a hang. It bounds the skew of local work between two steps (a
  // shard's build, a batch's local queries), so it must exceed the slowest rank's. 0: no
  // deadline; negative: the environment variable BHCL_MPI_DEADLINE_S, else 600 s.
  double deadline_s = -1;
  // The global id of the first point (rank 0's first): ids are id_base + the point's place over
  // all ranks. For points that are one part of a larger numbering (a tile of a survey, a batch
  // of a stream), and for checking ids past 2^31 at small scale. [0, 2^62].
  std::int64_t id_base = 0;
};

// What the sharding did, as seen from one rank (the *_all vectors are the same on every rank).
struct DistributedBuildStats {
  std::size_t n_global = 0;         // points over all ranks
  std::size_t n_input = 0;          // points this rank passed in
  std::size_t shard_points = 0;     // points in this rank's shard
  std::size_t points_sent = 0;      // of this rank's input, those sent to another rank's shard
  std::size_t points_received = 0;  // of this rank's shard, those that came from another rank
  std::vector<std::size_t> shard_points_all;  // shard sizes of every rank, in rank order
  double balance = 0;   // largest shard / mean shard (1 = perfect)
  double shard_s = 0;   // keys, splitters and the exchange of points (wall, this rank)
  double build_s = 0;   // the local index build (this rank)
  double wall_s = 0;    // the whole constructor (this rank)
};

// What one query call did, as seen from one rank. The library's QueryStats (returned by query())
// holds this rank's own queries (n_queries, nonfinite_queries, wall_s of the whole call) and the
// local index's work for every rank's queries it answered (batches, compile_s, upload_s, query_s,
// download_s: sums over both phases).
struct DistributedQueryStats {
  // Per query of this rank, in the caller's order: the ranks that answered it (the owner plus the
  // ranks whose boxes met its ball; 0 for a query with a NaN/Inf coordinate) and the owner (-1).
  std::vector<std::int32_t> ranks_visited;
  std::vector<std::int32_t> owner;
  std::size_t multi_rank_queries = 0;  // of this rank's queries, those answered by more than one rank
  // Queries moved between ranks (a query answered by its own rank is not moved).
  std::size_t owner_sent = 0, owner_received = 0;  // phase 1: to / from the owners
  std::size_t extra_sent = 0, extra_received = 0;  // phase 2: to / from the ranks met (and owners)
  std::size_t reanswered = 0;  // of this rank's queries, those its owner answered twice (border_factor)
  std::size_t answered = 0;  // queries this rank's local index answered (both phases, any origin)
  std::size_t bytes_sent = 0, bytes_received = 0;  // queries and rows, to / from other ranks
  double phase1_s = 0, phase2_s = 0;  // wall time of each phase on this rank (routing included)
};

// What one insert or remove did, as seen from one rank.
struct DistributedUpdateStats {
  std::size_t n_global = 0;        // points (insert) or ids (remove) over all ranks in this call
  std::size_t n_input = 0;         // those this rank passed in
  std::size_t applied = 0;         // points inserted into / removed from this rank's shard
  std::size_t sent = 0;            // of this rank's input, those that went to another rank
  std::size_t bytes_sent = 0, bytes_received = 0;  // points or ids, to / from other ranks
  double route_s = 0;   // checks, keys and the exchange (wall, this rank)
  double local_s = 0;   // the local index's insert / remove (this rank)
  double boxes_s = 0;   // the boxes' update and their sharing
  double wall_s = 0;    // the whole call (this rank)
};

class DistributedIndex final : public SearchIndex {
 public:
  // Collective over `comm`. `points`: this rank's part, n x 3 floats (n may be 0 on some ranks,
  // not on all). `runtime`: this rank's OpenCL device (each rank opens its own). Throws
  // bhcl::Error on every rank when any rank fails: a NaN/Inf point (named by its global index and
  // rank), a shard of more than 2^31 - 2 points (more points than 2^31 - 2 per rank: use more
  // ranks), an id_base outside [0, 2^62], an unknown method, bad build options. Nothing is
  // allocated for the points before the counts are checked.
  DistributedIndex(MPI_Comm comm, std::shared_ptr<Runtime> runtime, const float* points,
                   std::size_t n, const DistributedBuildParams& params = {});
  ~DistributedIndex();
  DistributedIndex(const DistributedIndex&) = delete;
  DistributedIndex& operator=(const DistributedIndex&) = delete;

  // Collective. `queries`: this rank's queries, n x 3 floats (n may be 0). Fills `out` with n rows
  // under the library's contract (knn.hpp): global ids, squared distances, counts, and per query
  // the points examined summed over the ranks visited when params.count_examined is set. Returns
  // this rank's QueryStats (see DistributedQueryStats); `stats`, when given, gets the rest.
  QueryStats query(const float* queries, std::size_t n, const SearchParams& params, KnnResult64& out,
                   DistributedQueryStats* stats = nullptr) const;
  // The same with int32 ids: throws bhcl::Error on every rank, before any work, when the ids do
  // not all fit (!ids_fit_int32(); the KnnResult64 call answers there).
  QueryStats query(const float* queries, std::size_t n, const SearchParams& params, KnnResult& out,
                   DistributedQueryStats* stats) const;
  QueryStats query(const float* queries, std::size_t n, const SearchParams& params,
                   KnnResult& out) const override {
    return query(queries, n, params, out, nullptr);
  }

  // Collective radius search (knn.hpp's Index::radius_search, same contract and layout): each
  // finite query goes to its owner and to every rank whose boxes meet the ball of radius r (the
  // ball is known up front: one round trip), each answers over its shard, and the slices are
  // merged by (distance, global index) and capped at params.max_results. Exact methods give the
  // single-process answer bit for bit; block hashing the union of its shards' subsets. Every rank
  // must pass the same r and max_results. `stats` gets ranks_visited, owner, the moved counts
  // (in owner_sent/received) and bytes.
  QueryStats radius_search(const float* queries, std::size_t n, float r, const RadiusParams& params,
                           RadiusResult64& out, DistributedQueryStats* stats = nullptr) const;
  // The same with int32 ids (refused as query()'s when the ids do not fit).
  QueryStats radius_search(const float* queries, std::size_t n, float r, const RadiusParams& params,
                           RadiusResult& out, DistributedQueryStats* stats) const;
  QueryStats radius_search(const float* queries, std::size_t n, float r, const RadiusParams& params,
                           RadiusResult& out) const override {
    return radius_search(queries, n, r, params, out, nullptr);
  }

  // Collective updates (see the top of this file). insert: this rank's new points, n x 3 floats
  // (n may be 0 on some ranks, not on all); returns the global id of this rank's first point
  // (its i-th point has that + i; the call's first id over all ranks is id_bound() before it).
  // remove: this rank's list of global ids to remove (any live ids, held by any rank; n may be 0
  // on some ranks, not on all). Throws bhcl::Error on EVERY rank, with the same message, for the
  // errors of Index::insert / remove over the concatenated batch: no points (ids) on any rank, a
  // null array with n > 0, a non-finite point (named by the global id it would take, its rank and
  // its place there), more than 2^40 - 1 ids issued in all or 2^31 - 2 on one rank, an id outside
  // [id_base(), id_bound()), already removed, given twice (anywhere in the batch: both places are
  // named), or removing every live point. The index is unchanged when a check fails. A failure
  // inside a local index after the checks (a device error) undoes the insert on the ranks that
  // made it and spends its ids (never issued to later points); a remove cannot be undone there
  // and the message says the index must be rebuilt.
  std::int64_t insert(const float* points, std::size_t n, DistributedUpdateStats* stats = nullptr);
  void remove(const std::int64_t* ids, std::size_t n, DistributedUpdateStats* stats = nullptr);
  std::size_t removed_count() const { return removed_n_; }  // ids removed so far, over all ranks

  std::string method() const override { return method_; }
  bool exact() const override { return exact_; }
  std::size_t size() const override { return n_global_; }  // live points over all ranks
  std::int64_t id_base() const { return id_base_; }
  // One past the largest global id issued: id_base() + size() + removed_count() (+ the ids a
  // failed insert spent); the next insert's first id.
  std::int64_t id_bound() const { return id_bound_; }
  // True when every global id fits an int32, the largest (id_bound() - 1) <= 2^31 - 1: the
  // KnnResult / RadiusResult calls answer.
  bool ids_fit_int32() const { return id_bound() <= (std::int64_t(1) << 31); }
  int rank() const { return rank_; }
  int ranks() const { return ranks_; }
  std::size_t shard_size() const { return shard_live_; }  // live points in this rank's shard
  // The global ids of this rank's shard, ascending: local index i is global id shard_ids()[i].
  // After removes it still holds the removed ones (local ids are never reused): shard_live_ids()
  // holds the live ones alone.
  const std::vector<std::int64_t>& shard_ids() const { return shard_ids_; }
  std::vector<std::int64_t> shard_live_ids() const;
  // Host bytes this rank holds beside its local index: the shard's global ids, its copy of the
  // points (for the boxes after a remove), their sub-runs and removed marks.
  std::size_t host_bytes() const;
  // This rank's local index (nullptr when its shard is empty: fewer points than ranks).
  const Index* local_index() const { return local_.get(); }
  const DistributedBuildStats& build_stats() const { return build_stats_; }
  // The rank that owns a query position (phase 1's destination). Same answer on every rank.
  int owner_of(const float xyz[3]) const;

  // The boxes rank r shares: one per sub-run of its shard holding a live point, at most
  // min(boxes_per_rank, its shard size at the build); the same on every rank.
  const std::vector<ShardBox>& boxes(int r) const { return boxes_.at(static_cast<std::size_t>(r)); }

 private:
  // The constructor's steps (index.cpp), collective in this order on every rank.
  struct Shard;  // this rank's points after the exchange, with their places over all ranks
  std::uint64_t number_points(const float* points, std::size_t n);
  Shard shard_points(const float* points, std::size_t n, std::uint64_t offset);
  void share_boxes(Shard& shard, int boxes_per_rank);
  // Every rank's boxes and live shard size from this rank's own (my_boxes_, shard_live_):
  // one allgather of each; sets boxes_, rank_box_, shard_sizes_ and nonempty_.
  void publish_boxes();
  std::vector<float> global_order(Shard shard);
  void build_local(const std::shared_ptr<Runtime>& runtime, const std::vector<float>& xyz,
                   const MethodOptions& options);
  void agree_global_cell_side(const std::shared_ptr<Runtime>& runtime, const std::vector<float>& xyz,
                              const MethodOptions& options);

  // The queries' steps (index.cpp, radius.cpp). The checks fail every rank alike (mpi_agree) and
  // agree the parameters with rank 0's; check_knn_params returns the budget of a border query's
  // second answer (approximate methods; 0: none).
  float check_knn_params(const float* queries, std::size_t n, const SearchParams& params) const;
  void check_radius_params(const float* queries, std::size_t n, float r, const RadiusParams& params) const;
  void require_int32_ids(const char* call) const;
  std::uint64_t key_of(const float xyz[3]) const;
  int owner_of_key(std::uint64_t key) const;
  // Sets ds.owner and ds.ranks_visited for n queries: each finite query's owner and 1 rank; -1
  // and 0 ranks for a query with a NaN/Inf coordinate, counted in st.nonfinite_queries.
  void route_to_owners(const float* queries, std::size_t n, QueryStats& st, DistributedQueryStats& ds) const;
  // The ranks other than `skip` with a box within squared distance `bound` of q (conservative).
  void ranks_meeting(const float q[3], double bound, int skip, std::vector<int>& out) const;
  // The updates' steps (update.cpp).
  struct Incoming;  // the new points that came to this rank, in global-id order
  std::uint64_t check_insert(const float* points, std::size_t n, std::uint64_t& total);
  Incoming route_new_points(const float* points, std::size_t n, std::uint64_t offset,
                            DistributedUpdateStats& us);
  void insert_locally(const Incoming& in);
  void grow_boxes(const Incoming& in);
  std::vector<std::int64_t> gather_ids(const std::int64_t* ids, std::size_t n,
                                       std::vector<std::uint64_t>& entry_first);
  std::vector<std::int32_t> check_remove(const std::vector<std::int64_t>& all,
                                         const std::vector<std::uint64_t>& entry_first);
  void remove_locally(const std::vector<std::int32_t>& local_ids);
  void shrink_boxes(const std::vector<std::int32_t>& local_ids);

  MPI_Comm comm_ = MPI_COMM_NULL;
  int rank_ = 0, ranks_ = 1;
  std::string method_;
  bool exact_ = false;
  float border_factor_ = 2;
  std::size_t n_global_ = 0;
  // The global quantiser (block hashing's: origin, one scale for all axes, 21 bits).
  double origin_[3] = {0, 0, 0};
  double scale_ = 0;
  std::int64_t id_base_ = 0;
  std::vector<std::int64_t> shard_ids_;
  std::unique_ptr<Index> local_;
  // Updates: the ids issued (id_base_ + every point ever numbered) and removed, over all ranks;
  // per local id of this shard its point, its sub-run (the box it counts in) and whether it was
  // removed; the live points of the shard; per sub-run its first key (where a new point's key
  // falls decides its sub-run) and its box over its live points (empty: lo > hi).
  std::int64_t id_bound_ = 0;
  std::size_t removed_n_ = 0;
  std::vector<float> shard_xyz_;
  std::vector<std::uint16_t> shard_run_;
  std::vector<bool> shard_removed_;
  std::size_t shard_live_ = 0;
  std::vector<std::uint64_t> run_first_keys_;
  std::vector<ShardBox> my_boxes_;
  int boxes_per_rank_ = 16;
  // Per rank: shard size, first key, the union box and the boxes of its sub-runs.
  std::vector<std::uint64_t> shard_sizes_, first_keys_;
  std::vector<ShardBox> rank_box_;
  std::vector<std::vector<ShardBox>> boxes_;
  std::vector<int> nonempty_;  // ranks with a non-empty shard, ascending
  DistributedBuildStats build_stats_;
};

// Collective over `comm`: returns when no rank passed an error; otherwise throws bhcl::Error on
// every rank, "<what>: rank R: <message>" with the first failing rank's message (and how many
// others failed). For callers that do their own per-rank work between collective steps (the bhcl
// tool reads the files on rank 0 and shares the outcome with it).
// Every rank first checks in within comm's deadline (the job ends naming a rank that does not).
void mpi_agree(MPI_Comm comm, const std::string& local_error, const std::string& what);

}  // namespace bhcl
