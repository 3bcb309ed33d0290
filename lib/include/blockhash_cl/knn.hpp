// The result contract shared by every method, and the Index base class.
//
// Contract (nanoflann/FLANN/FAISS users expect this):
//  - Queries are n x 3 float, row-major (x y z), as a host array or a caller-owned cl::Buffer.
//  - Results are n x k int32 indices into the caller's original point order and n x k float
//    SQUARED distances, row-major, each row sorted ascending by (distance, index): ties go to
//    the lower index. counts[i] is the number of neighbours found for query i (<= k); the rest of
//    the row is id -1 and distance +inf (k > N, or fewer points within max_radius).
//  - A point is within the maximum radius r when its squared distance is <= r*r.
//  - Distances are sum((q - p)^2) in float, never |q|^2 + |p|^2 - 2 q.p.
//  - A query with a NaN or Inf coordinate gets an empty row (count 0); the host-array call
//    reports how many there were in QueryStats::nonfinite_queries. Points must be finite: an
//    index build throws naming the first bad point.
//  - Results do not depend on batch size, work-group size or thread count.
//  - fork(): OpenCL objects do not survive it. In a forked child of the process that built (or
//    first queried) an index, every device method's call throws bhcl::Error saying so instead of
//    hanging: use an index in the process that built it, or start children with spawn (Python's
//    multiprocessing.get_context("spawn")); a forked child can build its own index only when its
//    parent has not used OpenCL. FLANN answers on the host and works in a child.
//  - Exact methods (kd-tree, brute force, FLANN) return the true k nearest of the caller's float
//    points for every finite input, ties to the lower index, whatever the scales (e.g. points in
//    [0,1]^3 with one outlier at 3e24, or clusters at 1e-20 and 1 in one set). They compute in
//    float, in the caller's coordinates or in coordinates scaled by a power of two (an exact
//    scaling: points whose extent is outside [2^-40, 2^40] get the scale of the bulk of the points,
//    never one that a few far outliers set). A row the float search cannot vouch for (a distance
//    that overflowed, one below 2^-120 in the scaled coordinates, a zero distance to a point that
//    differs from the query, or a radius whose square leaves the normal float range) is answered
//    again on the host in double precision over the caller's points: the ids are then those of
//    the true distances, and each distance is the double one rounded to float. A squared
//    distance that does not fit a float (above FLT_MAX) is reported as +inf; its rank is still
//    the true distance's. Radius search the same (a point is within when its true squared
//    distance <= r*r). The host-array calls do this (query, radius_search); the buffer-level call
//    of a device method (enqueue_query) stays in float on the device without the check. Exact
//    methods keep a host copy of the caller's points for it (12 bytes per point).
#pragma once

#include <CL/opencl.hpp>

#include <chrono>
#include <cstddef>
#include <algorithm>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <shared_mutex>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "blockhash_cl/runtime.hpp"
#include "blockhash_cl/spatial_order.hpp"  // detail::OrderSink

namespace bhcl {

// The largest k any kernel is compiled for. Kernels exist in variants of a maximum k (a -D
// define); a query uses the smallest variant >= k.
inline constexpr int kMaxK = 256;
inline constexpr int kKmaxVariants[] = {8, 16, 32, 64, 128, 256};
// Batches at least this large are dispatched in Hilbert order by default (SearchParams::sort_queries).
inline constexpr std::size_t kAutoSortQueries = 8192;
// A sorted host-array query keeps the rows of its last batch (8 k bytes per query) for the calling
// thread's next one, up to this size: allocating them afresh costs a page fault per 4 KiB on
// every call (13 % of the renderer's gather-query time). Larger batches free theirs at once.
inline constexpr std::size_t kSortScratchBytes = std::size_t(256) << 20;
int kmax_variant(int k);  // smallest variant >= k; throws for k outside [1, kMaxK]

// What both kinds of query (kNN: SearchParams, radius: RadiusParams) take the same way: how a
// batch is dispatched, and block hashing's probes. Build parameters live in each method's own
// struct.
struct DispatchParams {
  // Block hashing's block layouts: probe the near-side neighbour cells as well (-1: the index
  // preset decides).
  int neighbour_probes = -1;
  // Dispatch: 0 picks the device default (Quirks::default_local_size; the grid: its kernel form's
  // where the form sets one, kernel_forms.hpp).
  std::size_t local_size = 0;
  // Host-array calls split the batch so that one dispatch has at most this many queries
  // (0: automatic, bounded by device memory). Results do not depend on it.
  std::size_t max_batch = 0;
  // Host-array calls: dispatch the queries in 3D Hilbert order of their positions (results still
  // come back in the caller's order). 1 always, 0 never, -1 (default) for batches of at least
  // kAutoSortQueries queries, where the coherence gained outweighs the host sort (which counts in
  // QueryStats::wall_s, not in query_s).
  int sort_queries = -1;
  // Kernel exploration (the benchmark's variants): extra "-DNAME=VALUE" defines appended to the
  // kernel's build options, e.g. "-DBHCL_GRID_VTOPK=0". Only the tuning and experiment defines of
  // the kernel being built are accepted, each in its range (lib/src/core/kernel_defines.cpp's
  // table); any other name, or a structural one, throws bhcl::Error. Results of an exact method
  // do not depend on them; the block-hash kernel's may (the defines are its knobs).
  std::string kernel_defines;
  // Per query, the points examined (block hashing's cost measure) into the result's examined
  // (host-array calls) or ResultBuffers::examined (the buffer-level call). Only methods whose
  // Index::counts_examined() is true accept it; the others throw.
  bool count_examined = false;
};

// Search parameters of a kNN batch: everything that can change from one batch to the next.
struct SearchParams : DispatchParams {
  int k = 10;
  float max_radius = std::numeric_limits<float>::infinity();  // Euclidean (not squared)
  // Approximate methods (block hashing): examine at most A*k points per query; +inf examines
  // what the search needs (block hashing's grid: exact). 0 (the default) is the index's own
  // default: exact for block hashing's auto (grid) layout, 8 for its block layouts.
  float A = 0.0f;
  // Approximate methods: a recall@k to reach instead of a budget (e.g. 0.95). When > 0 the index
  // picks A for this k from a sample of its own points (BlockHashIndex::tune_for_recall, done once
  // per (k, target) and cached) and A above is ignored. 0 = use A.
  double recall_target = 0.0;
};

// Host-side kNN results, rows of k: ids/dist2 are n*k, counts is n. Id is the id type: int32 for
// an Index (KnnResult), int64 for an index whose ids can pass 2^31 (KnnResult64: DistributedIndex,
// whose global ids are DistributedBuildParams::id_base plus a point's place over all ranks). Same
// layout and contract for both, id -1 for an empty entry.
template <class Id>
struct KnnRows {
  std::size_t n = 0;
  int k = 0;
  std::vector<Id> ids;
  std::vector<float> dist2;
  std::vector<std::int32_t> counts;
  // n entries when SearchParams::count_examined was set: the points query i examined. Else empty.
  std::vector<std::int32_t> examined;

  void resize(std::size_t n_queries, int k_);  // every entry empty: id -1, distance +inf, count 0
  // The first k_ columns of every row (k_ <= k): the exact answer for k_ when this one is exact,
  // since rows are sorted by (distance, index).
  KnnRows leading_columns(int k_) const;
  Id id(std::size_t q, int j) const { return ids[q * static_cast<std::size_t>(k) + j]; }
  float d2(std::size_t q, int j) const { return dist2[q * static_cast<std::size_t>(k) + j]; }
};
using KnnResult = KnnRows<std::int32_t>;
using KnnResult64 = KnnRows<std::int64_t>;

// Caller-owned memory for the rows of a kNN call of n queries (Index::query_into): ids and dist2
// n*k entries, counts n, examined n where SearchParams::count_examined (else null). Every entry is
// written (the KnnRows contract); nothing is read, so the memory may be fresh (untouched pages are
// first touched by the search's own threads on a CPU device, not by a fill before it).
struct KnnRowsView {
  std::int32_t* ids = nullptr;
  float* dist2 = nullptr;
  std::int32_t* counts = nullptr;
  std::int32_t* examined = nullptr;
};
extern template struct KnnRows<std::int32_t>;  // lib/src/core/knn.cpp
extern template struct KnnRows<std::int64_t>;

// Caller-owned device buffers for the buffer-level call: ids (n*k int32), dist2 (n*k float),
// counts (n int32), and examined (n int32) only with SearchParams::count_examined.
struct ResultBuffers {
  ResultBuffers() = default;
  // The three result buffers, and examined only where SearchParams::count_examined asks for it
  // (a constructor, so that {ids, dist2, counts} stays complete without it).
  ResultBuffers(cl::Buffer ids_, cl::Buffer dist2_, cl::Buffer counts_, cl::Buffer examined_ = {})
      : ids(std::move(ids_)), dist2(std::move(dist2_)), counts(std::move(counts_)),
        examined(std::move(examined_)) {}
  cl::Buffer ids, dist2, counts;
  cl::Buffer examined;
  // Optional: the result row of each query of the queries buffer (uint32, one per query): query
  // i's row, count and examined count go to row rows[i]. Empty: row i (the usual layout).
  cl::Buffer rows;
};

// Radius search (Index::radius_search): every point within a radius of each query, a variable
// count per query, as nanoflann's radiusSearch, FLANN's radiusSearch, Open3D's
// fixed_radius_search, scipy's query_ball_point and FAISS's range_search give.
struct RadiusParams : DispatchParams {
  // Approximate methods (block hashing): examine at most this many points per query, the blocks
  // of the cells nearest the query first; 0 = no budget (every block within r in the cells the
  // probes reach). Exact methods ignore it.
  std::uint32_t budget = 0;
  // At most this many results per query, the nearest by (distance, index); 0 = no cap. A query
  // with more points within r is truncated: RadiusResult::found keeps its full count. The cap
  // bounds the output, not the work: the device still counts and writes every point within r.
  std::size_t max_results = 0;
  // Each slice sorted by (distance, index) (the default). false: slices in the order the method
  // found the points (scipy's return_sorted=False, Open3D's sort=False), which spares the host's
  // sort of every slice; with a cap, a truncated slice still holds the nearest max_results.
  bool sorted = true;
  // Device memory: results (8 bytes each) written by one fill dispatch; a batch of queries is
  // split so that its results fit (0: automatic, 2^24 results or less where the device's largest
  // buffer is smaller). A single query with more results than this gets a dispatch of its own.
  std::size_t max_batch_results = 0;
};

// Radius search results in the compressed layout of FAISS's range_search: query i's results are
// ids[offsets[i] .. offsets[i+1]) and the same slice of dist2 (SQUARED distances), sorted by
// (distance, index) unless RadiusParams::sorted is false. offsets has n + 1 entries, offsets[0] = 0.
template <class Id>
struct RadiusRows {
  std::size_t n = 0;
  std::vector<std::int64_t> offsets;
  std::vector<Id> ids;
  std::vector<float> dist2;
  // n entries: the points found within r per query before RadiusParams::max_results applied
  // (equal to the slice's length unless truncated).
  std::vector<std::int64_t> found;
  std::size_t truncated_queries = 0;  // queries whose slice the cap shortened
  // n entries with RadiusParams::count_examined: the points query i examined. Else empty.
  std::vector<std::int32_t> examined;

  std::size_t count(std::size_t q) const { return static_cast<std::size_t>(offsets[q + 1] - offsets[q]); }
  std::size_t total() const { return offsets.empty() ? 0 : static_cast<std::size_t>(offsets.back()); }
  // The queries of `part` (a later slice of the same call) after these: offsets shifted, slices,
  // counts and examined appended. Starts from offsets = {0}.
  void append(const RadiusRows& part) {
    const std::int64_t base = offsets.back();
    for (std::size_t i = 1; i < part.offsets.size(); ++i) offsets.push_back(base + part.offsets[i]);
    ids.insert(ids.end(), part.ids.begin(), part.ids.end());
    dist2.insert(dist2.end(), part.dist2.begin(), part.dist2.end());
    found.insert(found.end(), part.found.begin(), part.found.end());
    examined.insert(examined.end(), part.examined.begin(), part.examined.end());
    truncated_queries += part.truncated_queries;
  }
};
using RadiusResult = RadiusRows<std::int32_t>;
using RadiusResult64 = RadiusRows<std::int64_t>;  // as KnnResult64

// The device buffers of one radius dispatch (Index::enqueue_radius_batch): counts and examined
// per query row, offsets (ulong) per query of the dispatch, ids/dist2 the fill pass's slices.
struct RadiusBuffers {
  cl::Buffer counts, offsets, ids, dist2, examined;
};

// What one query call cost. Times in seconds.
struct QueryStats {
  std::size_t n_queries = 0;
  std::size_t nonfinite_queries = 0;  // queries with NaN/Inf coordinates (empty rows)
  std::size_t batches = 0;            // kernel dispatches
  double compile_s = 0.0;  // program builds and first-launch compiles done during this call
  // The call's stages, in order (host clock unless said): the queries' Hilbert order, the upload
  // (the queries gathered in that order into the buffer the kernel reads: zero-copy on a CPU
  // device), the kernel (query_s), the download (results mapped, or copied from a GPU), the
  // unsort (on a CPU device the kernel wrote each row at the caller's row: only the exact check
  // over the rows and a rescale at extreme scales; on a GPU the rows' scatter to the caller's
  // order with that check), the rest in wall_s. The first call's program load (compile_s) runs
  // beside the sort, so the stages can sum to more than wall_s.
  double sort_s = 0.0;
  double upload_s = 0.0;
  double query_s = 0.0;    // kernel execution (event times), compile excluded
  double download_s = 0.0;
  double unsort_s = 0.0;
  double wall_s = 0.0;     // the whole call, host clock (host methods: their search time is query_s)
  double queries_per_s() const { return query_s > 0 ? n_queries / query_s : 0.0; }
  // Every field and queries_per_s as f(name, value): the one list the front ends' stats (bhcl's
  // stats files, the Python package's dicts) are written from.
  template <class F>
  void for_each_field(F&& f) const {
    f("n_queries", n_queries);
    f("nonfinite_queries", nonfinite_queries);
    f("batches", batches);
    f("compile_s", compile_s);
    f("sort_s", sort_s);
    f("upload_s", upload_s);
    f("query_s", query_s);
    f("download_s", download_s);
    f("unsort_s", unsort_s);
    f("wall_s", wall_s);
    f("queries_per_s", queries_per_s());
  }
  // A slice of the same call answered on its own (a band, a sub-batch): its counts and times
  // added; n_queries and wall_s stay the caller's.
  void add_slice(const QueryStats& s) {
    nonfinite_queries += s.nonfinite_queries;
    batches += s.batches;
    compile_s += s.compile_s;
    sort_s += s.sort_s;
    upload_s += s.upload_s;
    query_s += s.query_s;
    download_s += s.download_s;
    unsort_s += s.unsort_s;
  }
};

// Sizes before allocation: throws bhcl::Error ("the result needs 7.2 GB ...") when a kNN result of
// n x k (held `copies` times) cannot fit the memory this process can still allocate (the ulimit
// -v / -d limits, the cgroup's memory.max, the machine's available memory and free swap). The
// host-array query calls it before any search.
void check_result_memory(std::size_t n, int k, bool examined, int copies, const std::string& method);
// The same for a radius search (Index::radius_search calls it twice): before any search with
// entries = 0, for what n queries need whatever they find (offsets, found and examined counts,
// `copies` of them when the rows are reordered, and `device_bytes` of device buffers); then, once
// the count pass has counted the `entries` points within the radius and before any of them is
// fetched, for those too (8 bytes each, twice: the reordered or re-checked copy). Throws
// bhcl::Error "the radius result needs 7.2 GB (...)" naming what bounds the memory.
void check_radius_memory(std::size_t n, std::size_t entries, bool examined, int copies,
                         std::size_t device_bytes, const std::string& method);

// Validates a point array (n x 3 float): finite everywhere. Throws bhcl::Error naming the first
// bad point, its coordinates and `what` (e.g. "points").
void validate_points(const float* xyz, std::size_t n, const char* what);

// A recall target turned into a budget (BlockHashIndex::tune_for_recall): the A picked, the
// recall measured on the sample at that A, the sample's size, whether the target was reached.
struct RecallTuning {
  float A = 0;
  double recall = 0;       // measured on the sample at that A
  std::size_t sample = 0;  // queries in the sample
  bool reached = false;
  double seconds = 0;      // the tuning's own time (exact answers included)
};

// What SearchIndex::params_for_batch did for a batch.
struct BatchTuning {
  bool tuned = false;       // A was chosen for a target (false: params came back as given)
  bool cached = false;      // from the cache (no sample answered now)
  double target = 0;
  RecallTuning tuning;      // the A, the recall measured on the sample, its size and time
  std::string distribution; // the cache key's distribution part, for the stats
  double seconds = 0;       // this call's own cost (signature and, unless cached, the tuning),
                            // first-launch kernel compiles excluded (they are compile_s)
  double compile_s = 0;     // kernel compiles the tuning's first launches triggered
};

// What a build used (derived values filled in) or what a query resolves to (block hashing: the A
// tuned for a recall target): (name, value as JSON text) pairs that every front end's stats carry.
using UsedFields = std::vector<std::pair<std::string, std::string>>;

// The one interface a front end queries, whatever answers: an Index (one method on one device),
// a MultiDeviceIndex (copies on several devices, multi_device.hpp) or a DistributedIndex (shards
// over MPI ranks, distributed.hpp: its calls are collective). Front ends hold a SearchIndex and
// run kNN and radius batches through it (bhcl's query_in_slices / radius_in_slices), so a kind
// of index needs no runner of its own. Rows follow the result contract above (int32 ids): an
// index whose own ids are wider converts in its override, or offers its wider call beside it.
class SearchIndex {
 public:
  virtual ~SearchIndex() = default;
  virtual std::string method() const = 0;  // "bruteforce", "kdtree", "blockhash", ...
  virtual bool exact() const = 0;          // true for exact methods
  virtual std::size_t size() const = 0;    // the live points indexed (over every rank)
  // Host arrays: queries n x 3 floats; out gets n rows (resized). Returns the call's stats.
  virtual QueryStats query(const float* queries, std::size_t n, const SearchParams& params,
                           KnnResult& out) const = 0;
  // The same rows into caller-owned memory (KnnRowsView: nothing resized or filled first). This
  // default answers into a KnnResult and copies it; an Index writes the caller's memory in place.
  virtual QueryStats query_into(const float* queries, std::size_t n, const SearchParams& params,
                                const KnnRowsView& out) const;
  // Every point within `radius` of each query (Index::radius_search's contract and layout).
  virtual QueryStats radius_search(const float* queries, std::size_t n, float radius,
                                   const RadiusParams& params, RadiusResult& out) const = 0;
  // The search parameters a host-array batch of these queries should run with: params as given,
  // unless the method tunes them to the batch (block hashing: A for a recall target on a sample
  // of the batch, BlockHashIndex::params_for_batch). `info` (optional) says what was done.
  virtual SearchParams params_for_batch(const float* queries, std::size_t n, const SearchParams& params,
                                        BatchTuning* info = nullptr) const {
    (void)queries;
    (void)n;
    if (info) *info = BatchTuning{};
    return params;
  }
  // The recall tuning a query with params.recall_target > 0 runs at (computed on first use and
  // cached), nullopt for a method with no budget to tune.
  virtual std::optional<RecallTuning> recall_tuning(const SearchParams& params) const {
    (void)params;
    return std::nullopt;
  }
  // What the build used and what a query with `params` resolves to (UsedFields; empty: nothing
  // beyond the options given). The stats of bhcl and the Python package carry them.
  virtual UsedFields build_used() const { return {}; }
  virtual UsedFields search_used(const SearchParams& params) const {
    (void)params;
    return {};
  }

 protected:
  SearchIndex() = default;
  SearchIndex(const SearchIndex&) = default;
  SearchIndex& operator=(const SearchIndex&) = default;
};

// Base of every method. Subclasses build their structure on construction and implement
// enqueue_batch(); the base does validation, batching, warm-up and timing.
class Index : public SearchIndex {
 public:
  virtual ~Index() = default;
  Index(const Index&) = delete;
  Index& operator=(const Index&) = delete;

  std::string method() const override = 0;     // "bruteforce", "kdtree", "blockhash", ...
  bool exact() const override = 0;             // true for exact methods
  virtual std::size_t memory_bytes() const = 0;  // device structure size, points included
  // True when the method counts the points each query examines (SearchParams::count_examined).
  virtual bool counts_examined() const { return false; }
  std::size_t size() const override { return n_points_; }
  double build_seconds() const { return build_seconds_; }
  Runtime& runtime() const { return *runtime_; }
  const std::shared_ptr<Runtime>& runtime_ptr() const { return runtime_; }
  // The work-group size a call with `params` launches with: params.local_size, else
  // default_local_size().
  std::size_t local_size_for(const DispatchParams& params) const;
  // Where the caller sets none: the device's quirks' (Quirks::default_local_size); the grid
  // takes its kernel form's where the form sets one (kernel_forms.hpp).
  virtual std::size_t default_local_size() const;

  // Host arrays. queries: n x 3 floats. Fills out (resized to n x k). Returns the call's stats.
  QueryStats query(const float* queries, std::size_t n, const SearchParams& params,
                   KnnResult& out) const override;
  // Convenience overload (std::vector of n*3 floats).
  KnnResult query(const std::vector<float>& queries, const SearchParams& params,
                  QueryStats* stats = nullptr) const;
  // The same rows into caller-owned memory (KnnRowsView): no resize, no value-initialisation of
  // the result (a pass of its own over up to gigabytes); on a CPU device the kernel writes them.
  QueryStats query_into(const float* queries, std::size_t n, const SearchParams& params,
                        const KnnRowsView& out) const override;

  // Buffer level: queries is a caller-owned buffer of at least n*3 floats, the results go to the
  // caller's buffers. Enqueued on the caller's queue (same context as the index; in order or out
  // of order), every command after `wait`; returns an event that completes when every row is
  // written. Nothing is read back. When it blocks the calling thread:
  //  - device methods never wait for `wait` or for the caller's queue. The first call per kernel
  //    variant compiles it and runs a zero-size launch on the library's own queue
  //    (Runtime::warm_queue), which blocks for the compile only; call warm_up() first to keep
  //    that off the critical path.
  //  - host methods (FLANN, answers on the host) block until `wait` completes, then answer: a
  //    user event in `wait` must be completed by another thread.
  cl::Event enqueue_query(const cl::CommandQueue& queue, const cl::Buffer& queries, std::size_t n,
                          const ResultBuffers& out, const SearchParams& params,
                          const std::vector<cl::Event>* wait = nullptr) const;

  // Radius search on host arrays: every point p with sum((q - p)^2) <= r*r (r Euclidean, in
  // float, the kNN contract's distance), per query in the caller's order, into `out` (see
  // RadiusResult: offsets, ids, squared distances, each slice sorted by (distance, index)). Exact
  // methods return exactly those points; block hashing those among the points it examines (its
  // budget and probes), a subset. A query with a NaN/Inf coordinate gets an empty slice. r must be
  // >= 0 and not NaN (bhcl::Error otherwise); r = +inf takes every point at a finite distance
  // (scipy's query_ball_point accepts it too). Sizes are found by a count pass, then a fill pass
  // writes them; batches are split to bound device memory (RadiusParams::max_batch_results).
  QueryStats radius_search(const float* queries, std::size_t n, float radius,
                           const RadiusParams& params, RadiusResult& out) const override;
  // The same with the squared radius r2 (nanoflann's and FLANN's convention): p is within when
  // its squared distance <= r2.
  QueryStats radius_search_squared(const float* queries, std::size_t n, float r2,
                                   const RadiusParams& params, RadiusResult& out) const;

  // Capabilities a method may have, virtual so that callers need no cast to a method's class.
  // Host memory the index keeps besides its device arrays (host copies of its structure or of the
  // caller's points); on PoCL both are the process's memory.
  virtual std::size_t host_bytes() const { return 0; }
  // One line on what the build did (block hashing: BlockHashBuildInfo::summary), "" when nothing.
  virtual std::string build_summary() const { return {}; }
  // save (a file the method's loader reads back; MethodInfo::saves says which methods do): the
  // default throws bhcl::Error naming the method.
  virtual bool saves() const { return false; }
  virtual void save(const std::string& path) const;
  // rebuild: the next frame's points with this build's parameters, the arrays reused (the same
  // answers as a fresh build). The default throws bhcl::Error; rebuilds_in_place() says whether
  // a method has it. Not safe concurrently with queries on this index.
  virtual bool rebuilds_in_place() const { return false; }
  virtual void rebuild(const float* points, std::size_t n_points);

  // Compiles the kernel variant for params (k, local size) and does the first launch, so that
  // later query timings exclude compilation. Returns the seconds it took (0 if already done).
  double warm_up(const SearchParams& params) const;

  // Points added and removed without a fresh build (every method; lib/src/core/update.cpp).
  // Ids are stable: the points of an insert take the ids id_bound(), id_bound() + 1, ... in order
  // (insert returns the first); a removed id is never returned again and never reused; size()
  // counts the live points. Results answer as an index over the live points would, their ids
  // the stable ones (exact methods: equal to a fresh build over the live points, ids mapped).
  // Thread safety: queries (query, radius_search, enqueue_query, warm_up) may run concurrently
  // with each other; insert and remove are exclusive: they wait for the queries in progress and
  // queries wait for them (a std::shared_mutex). A buffer-level call's kernels are enqueued under
  // the lock, and insert/remove finish the library's queue before changing device buffers, but a
  // caller's queue is the caller's: finish it before an update.
  // Throws bhcl::Error for non-finite points (naming the first), an empty batch, ids outside
  // [0, id_bound()), already removed, duplicated within a call, removing every live point, or
  // more than 2^31 - 2 ids in all; the index is unchanged when it throws.
  std::int32_t insert(const float* points, std::size_t n);
  void remove(const std::int32_t* ids, std::size_t n);
  std::int32_t id_bound() const { return id_bound_; }     // one past the largest id issued
  bool contains(std::int32_t id) const;                     // live (issued, not removed)
  std::size_t removed_count() const { return removed_n_; }  // ids removed so far

 protected:
  Index(std::shared_ptr<Runtime> runtime, std::size_t n_points)
      : runtime_(std::move(runtime)), n_points_(n_points),
        id_bound_(static_cast<std::int32_t>(std::min<std::size_t>(n_points, 0x7ffffffe))) {}

  // For the constructors of subclasses: validates the points (N in [1, 2^31 - 2], every
  // coordinate finite: bhcl::Error naming the method or the first bad point) and picks the coordinate
  // scale (see the contract above). Returns the points the structure must be built from: `points`
  // itself, or a copy scaled by 2^-scale_exponent() kept in `storage`.
  const float* prepare_points(const float* points, std::size_t n, std::vector<float>& storage);
  // Device (and host-method) coordinates are the caller's times 2^-e. Set by prepare_points, or
  // by a subclass that loads a saved structure.
  int scale_exponent() const { return scale_exp_; }
  void set_scale_exponent(int e) { scale_exp_ = e; }
  // The exponent prepare_points picks for a point set: 0 when its extent is within [2^-40, 2^40],
  // else that of the bulk's extent (per dimension, the 1st to 99th percentile), raised where
  // needed so that every scaled coordinate stays below 2^126 (differences stay finite).
  static int choose_scale_exponent(const float* points, std::size_t n);

  // Host methods (FLANN) answer on the host: they return true and implement host_search, which
  // gets queries and max_radius already in scaled coordinates and fills out's rows (distances in
  // scaled coordinates too). Returns the search's own seconds.
  virtual bool answers_on_host() const { return false; }
  virtual double host_search(const float* queries, std::size_t n, const SearchParams& params,
                             KnnResult& out) const;

  // Enqueue one dispatch answering queries [first, first+count) of the buffer, writing the same
  // rows of the result buffers. count may be 0 (a warm-up launch). Must not block.
  // Host methods (answers_on_host()) have no kernel and keep the default, which throws.
  virtual cl::Event enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                  std::size_t first, std::size_t count, const ResultBuffers& out,
                                  const SearchParams& params, std::size_t local_size,
                                  const std::vector<cl::Event>* wait) const;

  // Radius search, device methods: one dispatch for queries [first, first + count) of the query
  // buffer, kernel arguments as kernels/radius_common.h's BHCL_RADIUS_PARAMS. pass 0 writes
  // counts[row] (and examined[row] when asked); pass 1 writes query `row`'s points, unsorted, at
  // ids/dist2[offsets[row - first] ...] (at most counts[row] of them). Both passes must visit the
  // same points. r2 is in the structure's coordinates. The default throws (no radius kernel).
  virtual cl::Event enqueue_radius_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                         std::size_t first, std::size_t count, float r2, int pass,
                                         const RadiusBuffers& out, const RadiusParams& params,
                                         std::size_t local_size,
                                         const std::vector<cl::Event>* wait) const;
  // Radius search, host methods: fills out.offsets/ids/dist2 (slices in any order; the base sorts
  // them) for queries and r2 in the structure's coordinates. Returns the search's own seconds.
  virtual double host_radius_search(const float* queries, std::size_t n, float r2,
                                    const RadiusParams& params, RadiusResult& out) const;
  // Throws bhcl::Error for radius parameters this method cannot serve. The base checks the
  // common ones.
  virtual void check_radius_params(const RadiusParams& params) const;

  // Throws bhcl::Error for parameters this method cannot serve. The base checks k and radius.
  virtual void check_params(const SearchParams& params) const;

  // Updates (see insert/remove): called under the exclusive lock with validated input. points:
  // the caller's coordinates; scaled: the same in the structure's (2^-scale_exponent()); the new
  // ids are first .. first + n - 1. ids: distinct live ids, ascending. The defaults throw (no
  // update support). After insert_points/remove_points the base updates size() and id_bound().
  virtual void insert_points(const float* points, const float* scaled, std::size_t n, std::int32_t first);
  virtual void remove_points(const std::int32_t* ids, std::size_t n);
  // Exact methods: the caller's point of every id issued (the host copy the double-precision
  // fallback reads; a removed id's row is left as it was: id_removed says which). Empty for
  // approximate methods.
  const std::vector<float>& caller_points() const { return caller_points_; }
  // The removed ids, a bit per id issued (bit id % 32 of word id / 32), set before remove_points
  // is called: the methods' removes and the kernels that skip removed points read them (brute
  // force's, as a device buffer). removed_words() is null and removed_word_count() 0 while no id
  // was removed; words past the count hold no removed id.
  bool id_removed(std::int32_t id) const {
    return std::size_t(id >> 5) < removed_bits_.size() && ((removed_bits_[std::size_t(id) >> 5] >> (id & 31)) & 1u);
  }
  const std::uint32_t* removed_words() const { return removed_bits_.empty() ? nullptr : removed_bits_.data(); }
  std::size_t removed_word_count() const { return removed_bits_.size(); }
  // The id range after a load (ids of a saved index after updates): id_bound = bound, and every
  // id below it that is not in live[] counts as removed. live: ascending ids.
  void set_id_state(std::int32_t bound, const std::vector<std::int32_t>& live);
  // The lock a query holds shared (recursion-safe per thread: a query that queries its own index,
  // e.g. the recall tuning, does not lock twice).
  class ReadLock {
   public:
    explicit ReadLock(const Index& ix);
    ~ReadLock();
    ReadLock(const ReadLock&) = delete;
    ReadLock& operator=(const ReadLock&) = delete;
   private:
    const Index* ix_;
    bool held_ = false;
  };

  // The most queries per dispatch this method allows (e.g. to bound scratch memory).
  virtual std::size_t max_dispatch_queries() const { return std::size_t(1) << 20; }
  // Queries per launch: the caller's max_batch (0: no wish), max_dispatch_queries() and the
  // driver's launch limit (Quirks::max_launch_items, whole groups of `local` below it); >= 1.
  std::size_t queries_per_launch(std::size_t max_batch, std::size_t local) const;


  void set_build_seconds(double s) { build_seconds_ = s; }
  // A rebuild over another point set: n points with ids 0 .. n - 1 (the update state reset).
  void set_size(std::size_t n);

  // The coordinate scaling every entry point applies (see the contract): queries and max_radius
  // into the structure's coordinates, squared distances back. to_structure returns `queries`
  // itself when no scaling applies, else a scaled copy kept in `storage`.
  SearchParams scaled(const SearchParams& params) const;
  const float* to_structure(const float* queries, std::size_t n, std::vector<float>& storage) const;
  void distances_to_caller(float* dist2, std::size_t count) const;

 private:
  // The one host-array query pipeline (lib/src/core/query_pipeline.cpp): run_query does what
  // every kind of query shares once (the lock, the checks, the Hilbert order, the chunks that bound
  // memory, the upload, the warm-up, the batches, the exact re-answer of suspect rows, the stats);
  // a QueryKind supplies what differs (the rows' shape, its passes, its suspect-row test): KnnKind
  // (knn.cpp) and RadiusKind (radius.cpp), as nanoflann's findNeighbors takes a result set.
  class QueryKind;
  class KnnKind;
  class RadiusKind;
  QueryStats run_query(const float* queries, std::size_t n, QueryKind& kind) const;
  // A remove's ids checked and marked in removed_bits_ (update.cpp), and the marks undone.
  void mark_removed(const std::int32_t* ids, std::size_t n);
  void unmark_removed(const std::int32_t* ids, std::size_t n);
  // sort (when set): makes the dispatch order and returns it, handed a sink that gathers each
  // part of the order's queries as the sort's last pass finishes it (null where the queries are
  // uploaded after the sort): called once the query buffers are mapped.
  using SortStep = std::function<const std::size_t*(const detail::OrderSink* sink)>;
  void search_on_device(const float* queries, std::size_t n, const std::size_t* order, QueryKind& kind,
                        QueryStats& st, std::vector<std::size_t>& suspects, const SortStep* sort = nullptr) const;
  void search_on_host(const float* queries, std::size_t n, const std::size_t* order, QueryKind& kind,
                      QueryStats& st, std::vector<std::size_t>& suspects) const;
  // The kind's first launches, once per (kernel variant, local size, defines); the seconds (0
  // when already done).
  double warm_up_kind(const QueryKind& kind, std::size_t local) const;
  cl::Event enqueue_impl(const cl::CommandQueue& queue, const cl::Buffer& queries, std::size_t n,
                         const ResultBuffers& out, const SearchParams& params,
                         const std::vector<cl::Event>* wait, std::vector<cl::Event>* kernels,
                         double* compile_s) const;

  std::shared_ptr<Runtime> runtime_;
  std::size_t n_points_;
  // Exact methods: the caller's points as given (the double-precision fallback's input).
  std::vector<float> caller_points_;
  int scale_exp_ = 0;
  double build_seconds_ = 0.0;
  // Updates: the lock (see insert), the ids issued and those removed (a bit per id issued).
  mutable std::shared_mutex update_mutex_;
  std::int32_t id_bound_ = 0;
  std::vector<std::uint32_t> removed_bits_;  // a bit per id issued (see id_removed); empty while none was
  std::size_t removed_n_ = 0;
  // A host-array query's device buffers, kept from call to call per kind (kNN rows of k; radius,
  // k = 0: counts, offsets and the fill pass's `fill` entries).
  struct QueryBuffers {
    cl::Buffer q, ids, dist2, counts, examined_buf, offsets;
    cl::Buffer result_rows;  // kNN on a host-memory device: each dispatch row's caller row (uint32)
    std::size_t rows = 0, k = 0, fill = 0;
    bool host = false;  // host memory the device uses in place (a CPU device)
    bool examined() const { return examined_buf() != nullptr; }
    // kNN on a host-memory device, at most 2^32 queries: the kernel writes each row at the
    // caller's row, which travels with the queries (result_rows, uint32).
    bool writes_caller_rows(std::size_t n) const { return result_rows() != nullptr && n <= 0xffffffffull; }
    std::size_t bytes() const {
      return rows * (12 + 8 * k + 4 + (examined() ? 4 : 0) + (k ? 0 : 8) + (result_rows() ? 4 : 0)) + 8 * fill;
    }
  };
  void take_query_buffers(std::size_t rows, std::size_t k, bool examined, QueryBuffers& b) const;
  void give_back_query_buffers(QueryBuffers&& b) const;
  mutable std::mutex io_mutex_;
  mutable QueryBuffers io_cache_[2];  // [0]: kNN, [1]: radius
  mutable std::mutex warm_mutex_;
  // (kmax, local size, defines); kmax 0: the radius kernels.
  mutable std::set<std::tuple<int, std::size_t, std::string>> warmed_;
};

// What a method's class declares of the Index hooks above, in one line each (under protected:):
// a device method's kNN and radius dispatch, and any method's insert/remove.
#define BHCL_INDEX_DEVICE_HOOKS                                                                     \
  cl::Event enqueue_radius_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,          \
                                 std::size_t first, std::size_t count, float r2, int pass,          \
                                 const RadiusBuffers& out, const RadiusParams& params,              \
                                 std::size_t local_size,                                            \
                                 const std::vector<cl::Event>* wait) const override;                \
  cl::Event enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,                 \
                          std::size_t first, std::size_t count, const ResultBuffers& out,           \
                          const SearchParams& params, std::size_t local_size,                       \
                          const std::vector<cl::Event>* wait) const override;
#define BHCL_INDEX_UPDATE_HOOKS                                                                     \
  void insert_points(const float* points, const float* scaled, std::size_t n, std::int32_t first) \
      override;                                                                                     \
  void remove_points(const std::int32_t* ids, std::size_t n) override;

}  // namespace bhcl
