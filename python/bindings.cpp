// blockhash_cl._core: the thin C++ layer under the Python package (python/blockhash_cl/).
//
// Split of work: the Python layer (__init__.py) checks names, keyword arguments and array shapes
// and hands this layer C-contiguous float32 (N, 3) arrays; this layer calls the library with the
// GIL released, and returns results as numpy arrays that own the library's vectors (no copy).
// Every bhcl::Error reaches Python as blockhash_cl.Error (a ValueError) with the library's
// message; bhcl::ClError (a failed OpenCL call) as blockhash_cl.OpenCLError (also a
// RuntimeError). Nothing the library throws ends the interpreter.
//
// A search is one function here taking (Index, queries, its parameters) like knn_query and
// radius_query below, returning its arrays through to_numpy(), bound in the Index class at the
// bottom, plus a method in __init__.py's Index that reuses _queries_array().
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <memory>
#include <optional>
#include <cstddef>
#include <unordered_map>
#include <mutex>
#include <new>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/config.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/knn.hpp"
#include "blockhash_cl/multi_device.hpp"
#include "blockhash_cl/numbers.hpp"
#include "blockhash_cl/parallel.hpp"
#include "blockhash_cl/runtime.hpp"
#include "py_common.hpp"
#if BHCL_HAVE_FLANN
#include "blockhash_cl/flann_index.hpp"
#endif

namespace py = pybind11;
using bhcl_py::rows_of;
using bhcl_py::stats_dict;
using bhcl_py::to_numpy;

#if BHCL_PYTHON_DISTRIBUTED
// distributed_bindings.cpp: bhcl::DistributedIndex (the build found MPI).
void bind_distributed(py::module_& m);
#endif

namespace {

PyObject* g_error = nullptr;     // blockhash_cl.Error(ValueError)
PyObject* g_cl_error = nullptr;  // blockhash_cl.OpenCLError(Error, RuntimeError)

py::dict device_dict(const bhcl::DeviceInfo& d) {
  py::dict o;
  o["spec"] = std::to_string(d.platform_index) + ":" + std::to_string(d.device_index);
  o["platform_index"] = d.platform_index;
  o["device_index"] = d.device_index;
  o["platform"] = d.platform_name;
  o["platform_vendor"] = d.platform_vendor;
  o["platform_version"] = d.platform_version;
  o["device"] = d.device_name;
  o["vendor"] = d.device_vendor;
  o["version"] = d.device_version;
  o["driver_version"] = d.driver_version;
  o["type"] = d.type_name();
  o["compute_units"] = d.compute_units;
  o["global_mem_bytes"] = d.global_mem_bytes;
  o["max_alloc_bytes"] = d.max_alloc_bytes;
  o["max_work_group_size"] = d.max_work_group_size;
  o["is_pocl"] = d.is_pocl;
  o["is_nvidia"] = d.is_nvidia;
  o["summary"] = d.summary();
  o["quirks"] = bhcl::quirks_for(d).description;
  return o;
}

// Values of the method's MethodInfo::used_* (JSON text) into a dict.
void add_used(py::dict& o, const bhcl::MethodInfo::Used& used) {
  py::object loads = py::module_::import("json").attr("loads");
  for (const auto& [name, value] : used) o[py::str(name)] = loads(value);
}

// What the search actually used beyond the caller's parameters (as `bhcl knn --stats` writes it):
// SearchIndex::search_used.
void add_resolved(py::dict& o, const bhcl::SearchIndex& index, const bhcl::SearchParams& p) {
  bhcl::UsedFields used;
  {
    py::gil_scoped_release nogil;
    used = index.search_used(p);  // a recall tuning is cached by the query that just ran
  }
  add_used(o, used);
}

// Radius search: (offsets (n + 1,) int64, dist2 (total,) float32, ids (total,) int32,
// found (n,) int64, stats dict with truncated_queries).
template <typename IndexT>
py::tuple radius_query(const IndexT& index, const py::array_t<float, py::array::c_style>& queries,
                       float r, bool squared, const bhcl::RadiusParams& params) {
  const std::size_t n = rows_of(queries, "queries");
  bhcl::RadiusResult r_out;
  bhcl::QueryStats st;
  {
    py::gil_scoped_release nogil;
    if constexpr (std::is_same_v<IndexT, bhcl::Index>) {
      st = squared ? index.radius_search_squared(queries.data(), n, r, params, r_out)
                   : index.radius_search(queries.data(), n, r, params, r_out);
    } else {
      if (squared) throw bhcl::Error("radius_search: a multi-device index takes r, not squared=True");
      st = index.radius_search(queries.data(), n, r, params, r_out);
    }
  }
  const auto total = static_cast<py::ssize_t>(r_out.total()), rows = static_cast<py::ssize_t>(n);
  py::dict stats = stats_dict(st);
  stats["truncated_queries"] = r_out.truncated_queries;
  stats["results"] = r_out.total();
  py::object examined = py::none();
  if (params.count_examined) examined = to_numpy(std::move(r_out.examined), {rows});
  stats["examined"] = examined;
  return py::make_tuple(to_numpy(std::move(r_out.offsets), {rows + 1}), to_numpy(std::move(r_out.dist2), {total}),
                        to_numpy(std::move(r_out.ids), {total}), to_numpy(std::move(r_out.found), {rows}), stats);
}

// float64 refinement (python/blockhash_cl/_refine.py): distances in double from the caller's points,
// rows re-sorted by (distance, id). Rows are split over a few threads (GIL released).
// The library's parallel_for, over at most 8 of the CPUs this process may use, once the work
// (distances to compute) pays for threads.
template <typename F>
void over_rows(std::size_t n, std::size_t work, F&& f) {
  const unsigned t = work < 200000 ? 1u : std::min(8u, bhcl::detail::default_threads());
  bhcl::detail::parallel_for(n, f, t, 1);
}

// The refinement's output buffers, kept for reuse once numpy frees them. Why: a refined k = 50
// call over 200k queries writes 120 MB of fresh results, and glibc maps and unmaps each such
// buffer (above its mmap threshold), so every call faulted in 30k fresh pages: perf put 47 % of
// the refinement's samples in the kernel (faults, zeroing, the page lists, unmapping). A freed
// buffer is kept while the pool holds at most kPoolBuffers of them and kPoolBytes in all, and a
// request takes the smallest kept buffer that fits it without wasting more than half; the next
// call's pages are then already mapped. BHCL_REFINE_POOL=0 turns the pool off (every buffer
// freed at once). Huge pages (MADV_HUGEPAGE) were tried instead and dropped: on this shared
// machine their compaction made the k = 50 refinement 1.7-2.2x slower
// (bench/results/issue40/refine_hugepages_tried.md).
class BufferPool {
 public:
  static BufferPool& instance() {
    static BufferPool* pool = new BufferPool();  // never destroyed: buffers may outlive exit's order
    return *pool;
  }
  void* take(std::size_t bytes) {
    if (enabled()) {
      std::lock_guard<std::mutex> lock(mu_);
      std::size_t best = kept_.size();
      for (std::size_t i = 0; i < kept_.size(); ++i)
        if (kept_[i].bytes >= bytes && kept_[i].bytes <= 2 * bytes &&
            (best == kept_.size() || kept_[i].bytes < kept_[best].bytes))
          best = i;
      if (best != kept_.size()) {
        Block b = kept_[best];
        kept_.erase(kept_.begin() + static_cast<std::ptrdiff_t>(best));
        total_ -= b.bytes;
        sizes_[b.p] = b.bytes;
        return b.p;
      }
    }
    void* p = std::malloc(bytes);
    if (!p) throw std::bad_alloc();
    std::lock_guard<std::mutex> lock(mu_);
    sizes_[p] = bytes;
    return p;
  }
  void give(void* p) {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = sizes_.find(p);
    const std::size_t bytes = it == sizes_.end() ? 0 : it->second;
    if (it != sizes_.end()) sizes_.erase(it);
    if (bytes >= kMinBytes && enabled()) {
      while (!kept_.empty() && (kept_.size() >= kPoolBuffers || total_ + bytes > kPoolBytes)) {
        std::free(kept_.front().p);  // the oldest first
        total_ -= kept_.front().bytes;
        kept_.erase(kept_.begin());
      }
      if (bytes <= kPoolBytes) {
        kept_.push_back({p, bytes});
        total_ += bytes;
        return;
      }
    }
    std::free(p);
  }

 private:
  struct Block {
    void* p;
    std::size_t bytes;
  };
  static constexpr std::size_t kPoolBuffers = 8;
  static constexpr std::size_t kPoolBytes = std::size_t(1) << 30;
  static constexpr std::size_t kMinBytes = std::size_t(1) << 20;  // smaller ones come from malloc's heap
  static bool enabled() {
    const char* v = std::getenv("BHCL_REFINE_POOL");
    return !(v && v[0] == '0');
  }
  std::mutex mu_;
  std::vector<Block> kept_;
  std::size_t total_ = 0;
  std::unordered_map<void*, std::size_t> sizes_;  // every buffer handed out, by address
};

// An output array the refinement writes every entry of: from the pool above, without
// std::vector's value initialisation (a pass over up to 2 GB of results before the real writes),
// handed to numpy without a copy (back to the pool when numpy frees it).
template <typename T>
class Uninit {
 public:
  explicit Uninit(std::size_t n)
      : p_(static_cast<T*>(BufferPool::instance().take(std::max<std::size_t>(1, n) * sizeof(T)))) {}
  ~Uninit() {
    if (p_) BufferPool::instance().give(p_);
  }
  Uninit(const Uninit&) = delete;
  Uninit& operator=(const Uninit&) = delete;
  T& operator[](std::size_t i) { return p_[i]; }
  py::array_t<T> to_numpy(std::vector<py::ssize_t> shape) && {
    T* raw = p_;
    py::capsule owner(raw, [](void* x) { BufferPool::instance().give(x); });
    p_ = nullptr;
    return py::array_t<T>(std::move(shape), raw, owner);
  }

 private:
  T* p_ = nullptr;
};

// kNN: (dist2 (n, k) float32, ids (n, k) int32, counts (n,) int32, stats dict).
template <typename IndexT>
py::tuple knn_query(const IndexT& index, const py::array_t<float, py::array::c_style>& queries,
                    const bhcl::SearchParams& params) {
  const std::size_t n = rows_of(queries, "queries");
  const auto rows = static_cast<py::ssize_t>(n), k = static_cast<py::ssize_t>(params.k);
  const std::size_t nk = n * static_cast<std::size_t>(std::max(params.k, 0));
  // An Index writes straight into the arrays numpy gets (from the pool: a buffer reused from an
  // earlier call's freed result has its pages mapped already; a fresh one is first touched by the
  // search's threads, not by a fill before it); another index kind fills a KnnResult.
  constexpr bool into = std::is_same_v<IndexT, bhcl::Index>;
  std::optional<Uninit<float>> d2;
  std::optional<Uninit<std::int32_t>> ids, counts;
  if constexpr (into) {
    // The result's memory checked before it is taken (the call checks it again, with its scratch).
    if (params.k >= 1) bhcl::check_result_memory(n, params.k, false, 1, index.method());
    d2.emplace(nk);
    ids.emplace(nk);
    counts.emplace(n);
  }
  bhcl::KnnResult r;
  bhcl::QueryStats st;
  // The batch's own parameters (SearchIndex::params_for_batch; block hashing: a recall asked for,
  // or the default one on a layout where a budget applies, tuned on a sample of this batch, not on
  // the index's points).
  bhcl::BatchTuning bt;
  bhcl::SearchParams run = params;
  double wall = 0;
  {
    py::gil_scoped_release nogil;
    const auto t0 = std::chrono::steady_clock::now();
    run = index.params_for_batch(queries.data(), n, params, &bt);
    if constexpr (into) {
      std::optional<Uninit<std::int32_t>> examined;  // asked for, not returned: written and dropped
      if (run.count_examined) examined.emplace(n);
      st = index.query_into(queries.data(), n, run,
                            {&(*ids)[0], &(*d2)[0], &(*counts)[0], examined ? &(*examined)[0] : nullptr});
    }
    else st = index.query(queries.data(), n, run, r);
    wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
  py::dict stats = stats_dict(st);
  add_resolved(stats, index, run);
  if (bt.tuned) {
    // What the tuning chose and measured, and its cost within this call (wall_s covers the
    // query only; tuning_share is the tuning's part of both, compiles excluded).
    stats["recall_target"] = bt.target;
    stats["A"] = bt.tuning.A;
    stats["tuned_on"] = "queries";
    stats["tuned_sample_recall"] = bt.tuning.recall;
    stats["tuned_reached"] = bt.tuning.reached;
    stats["tuning_sample"] = bt.tuning.sample;
    stats["tuning_cached"] = bt.cached;
    stats["tuning_distribution"] = bt.distribution;
    stats["tuning_s"] = bt.seconds;
    stats["tuning_compile_s"] = bt.compile_s;
    // Of the call's time without first-launch compiles (they happen once per process).
    const double warm = wall - bt.compile_s - st.compile_s;
    stats["tuning_share"] = warm > 0 ? std::min(1.0, bt.seconds / warm) : 0.0;
  }
  if constexpr (into)
    return py::make_tuple(std::move(*d2).to_numpy({rows, k}), std::move(*ids).to_numpy({rows, k}),
                          std::move(*counts).to_numpy({rows}), stats);
  else
    return py::make_tuple(to_numpy(std::move(r.dist2), {rows, k}), to_numpy(std::move(r.ids), {rows, k}),
                          to_numpy(std::move(r.counts), {rows}), stats);
}

inline double dist2_64(const double* q, const double* p) {
  const double dx = q[0] - p[0], dy = q[1] - p[1], dz = q[2] - p[2];
  return (dx * dx + dy * dy) + dz * dz;
}

// _refine.query_delta in one pass (numpy's took a third of the refinement at k = 10: an (n, 3)
// abs, a reduction along the short axis, np.spacing): per query, sqrt3 (eq + ep) (1 + rel) +
// 1e-30 with eq half the float32 spacing at the query's largest |stored coordinate| (0 where that
// is not finite: a NaN/Inf query, answered with an empty row).
py::array_t<double> query_delta(const py::array_t<float, py::array::c_style>& q32, double point_rounding,
                                double sqrt3, double rel) {
  const std::size_t n = rows_of(q32, "queries");
  Uninit<double> out(n);
  const float* q = q32.data();
  {
    py::gil_scoped_release nogil;
    for (std::size_t i = 0; i < n; ++i) {
      const float a = std::fabs(q[3 * i]), b = std::fabs(q[3 * i + 1]), c = std::fabs(q[3 * i + 2]);
      double eq = 0;
      if (std::isfinite(a) && std::isfinite(b) && std::isfinite(c)) {
        const float m = std::max(a, std::max(b, c));
        const float spacing = std::nextafter(m, std::numeric_limits<float>::infinity()) - m;
        if (std::isfinite(spacing)) eq = 0.5 * static_cast<double>(spacing);
      }
      out[i] = sqrt3 * (eq + point_rounding) * (1 + rel) + 1e-30;
    }
  }
  return std::move(out).to_numpy({static_cast<py::ssize_t>(n)});
}

// How many rows ahead refine_knn prefetches the candidates' points: BHCL_REFINE_PREFETCH (0 turns
// it off, for measuring it; at most 8), else kPrefetchRows.
constexpr std::size_t kPrefetchRows = 2;
std::size_t prefetch_rows() {
  const char* v = std::getenv("BHCL_REFINE_PREFETCH");
  if (!v || v[0] < '0' || v[0] > '8' || v[1] != 0) return kPrefetchRows;
  return static_cast<std::size_t>(v[0] - '0');
}

// ids (n, kc) int32 (-1: missing) -> the first k of each row by float64 (distance, id): (d2 (n, k)
// float64, ids (n, k) int32, found (n,) int32: the ids >= 0 of each row); missing are inf and -1.
py::tuple refine_knn(const py::array_t<double, py::array::c_style>& q, const py::array_t<double, py::array::c_style>& pts,
                     const py::array_t<std::int32_t, py::array::c_style>& ids, int k) {
  if (q.ndim() != 2 || q.shape(1) != 3 || pts.ndim() != 2 || pts.shape(1) != 3 || ids.ndim() != 2 ||
      ids.shape(0) != q.shape(0) || k < 1 || k > ids.shape(1))
    throw py::value_error("refine_knn: q (n, 3), points (N, 3), ids (n, kc) with 1 <= k <= kc");
  const std::size_t n = static_cast<std::size_t>(q.shape(0)), kc = static_cast<std::size_t>(ids.shape(1)),
                    np = static_cast<std::size_t>(pts.shape(0)), kk = static_cast<std::size_t>(k);
  // The memory before allocating: 12 bytes per entry, within two copies of a kNN result's 8.
  bhcl::check_result_memory(n, k, false, 2, "refine_knn");
  // Every entry is written below: no zeroing pass over the (up to n * 256) outputs.
  Uninit<double> od(n * kk);
  Uninit<std::int32_t> oi(n * kk);
  Uninit<std::int32_t> found(n);
  const double* qd = q.data();
  const double* pd = pts.data();
  const std::int32_t* id = ids.data();
  std::atomic<bool> bad{false};
  {
    py::gil_scoped_release nogil;
    // Rows in their own order: the candidates' ids and the outputs stream. (Visiting them in
    // Hilbert order of the queries, so that neighbouring rows gather the same float64 points,
    // was measured 2x slower on the UTM case: the gathers hit the cache anyway, and the rows'
    // reads and writes scatter.)
    const std::size_t ahead = prefetch_rows();
    over_rows(n, n * kc, [&](std::size_t a, std::size_t b) {
      std::vector<std::pair<double, std::int32_t>> row(kc);
      for (std::size_t r = a; r < b; ++r) {
        const double* qr = qd + 3 * r;
        const std::int32_t* ir = id + r * kc;
        // The candidates of the row `ahead` rows on requested now, so that their cache misses
        // overlap this row's work: perf put 3/4 of the refinement's samples on the gathers' loads
        // (a row's points lie anywhere in the float64 copy, and the search has just been through
        // the cache). A point's 24 bytes may straddle two cache lines: both are asked for.
        if (ahead && r + ahead < b)
          for (std::size_t j = 0; j < kc; ++j) {
            const std::int32_t i = ir[ahead * kc + j];
            if (i >= 0 && static_cast<std::size_t>(i) < np) {
              __builtin_prefetch(pd + 3 * static_cast<std::size_t>(i));
              __builtin_prefetch(pd + 3 * static_cast<std::size_t>(i) + 2);
            }
          }
        for (std::size_t j = 0; j < kc; ++j) {
          const std::int32_t i = ir[j];
          const bool in = i >= 0 && static_cast<std::size_t>(i) < np;
          if (i >= 0 && !in) bad = true;
          row[j] = {in ? dist2_64(qr, pd + 3 * static_cast<std::size_t>(i)) : HUGE_VAL, i >= 0 ? i : INT32_MAX};
        }
        // Insertion sort: the float32 order is nearly always the float64 one already.
        for (std::size_t j = 1; j < kc; ++j)
          for (std::size_t m = j; m > 0 && row[m] < row[m - 1]; --m) std::swap(row[m], row[m - 1]);
        std::int32_t live = 0;
        for (std::size_t j = 0; j < kk; ++j) {
          const bool missing = row[j].second == INT32_MAX;
          od[r * kk + j] = row[j].first;
          oi[r * kk + j] = missing ? -1 : row[j].second;
          live += missing ? 0 : 1;
        }
        found[r] = live;
      }
    });
  }
  if (bad) throw py::value_error("refine_knn: an id past the points");
  const auto rows = static_cast<py::ssize_t>(n), cols = static_cast<py::ssize_t>(kk);
  return py::make_tuple(std::move(od).to_numpy({rows, cols}), std::move(oi).to_numpy({rows, cols}),
                        std::move(found).to_numpy({rows}));
}

// Squared float64 distances of pairs (q[owner[j]], points[ids[j]]); id -1 gives inf.
py::array_t<double> pair_dist2(const py::array_t<double, py::array::c_style>& q,
                               const py::array_t<std::int64_t, py::array::c_style>& owner,
                               const py::array_t<double, py::array::c_style>& pts,
                               const py::array_t<std::int32_t, py::array::c_style>& ids) {
  if (q.ndim() != 2 || q.shape(1) != 3 || pts.ndim() != 2 || pts.shape(1) != 3 || owner.ndim() != 1 ||
      ids.ndim() != 1 || owner.shape(0) != ids.shape(0))
    throw py::value_error("pair_dist2: q (n, 3), owner (m,), points (N, 3), ids (m,)");
  const std::size_t m = static_cast<std::size_t>(ids.shape(0)), n = static_cast<std::size_t>(q.shape(0)),
                    np = static_cast<std::size_t>(pts.shape(0));
  Uninit<double> out(m);  // every entry written below
  const double* qd = q.data();
  const double* pd = pts.data();
  const std::int64_t* ow = owner.data();
  const std::int32_t* id = ids.data();
  std::atomic<bool> bad{false};
  {
    py::gil_scoped_release nogil;
    over_rows(m, m, [&](std::size_t a, std::size_t b) {
      for (std::size_t j = a; j < b; ++j) {
        const std::int32_t i = id[j];
        const std::int64_t o = ow[j];
        if (o < 0 || static_cast<std::size_t>(o) >= n || (i >= 0 && static_cast<std::size_t>(i) >= np)) {
          bad = true;
          out[j] = HUGE_VAL;
          continue;
        }
        out[j] = i < 0 ? HUGE_VAL : dist2_64(qd + 3 * o, pd + 3 * static_cast<std::size_t>(i));
      }
    });
  }
  if (bad) throw py::value_error("pair_dist2: an index out of range");
  return std::move(out).to_numpy({static_cast<py::ssize_t>(m)});
}

// A radius search's slices (offsets (n + 1,), ids) refined: each query's points within r2[i]
// (squared, float64 distances <= r2), sorted by (distance, id) when `sorted`, else in the given
// order: (offsets, d2 float64, ids int32).
py::tuple refine_radius(const py::array_t<double, py::array::c_style>& q, const py::array_t<double, py::array::c_style>& pts,
                        const py::array_t<std::int64_t, py::array::c_style>& offsets,
                        const py::array_t<std::int32_t, py::array::c_style>& ids,
                        const py::array_t<double, py::array::c_style>& r2, bool sorted) {
  const std::size_t n = static_cast<std::size_t>(q.shape(0));
  if (q.ndim() != 2 || q.shape(1) != 3 || pts.ndim() != 2 || pts.shape(1) != 3 || offsets.ndim() != 1 ||
      static_cast<std::size_t>(offsets.shape(0)) != n + 1 || ids.ndim() != 1 || r2.ndim() != 1 ||
      static_cast<std::size_t>(r2.shape(0)) != n || offsets.data()[n] != ids.shape(0))
    throw py::value_error("refine_radius: q (n, 3), points (N, 3), offsets (n + 1,), ids (offsets[n],), r2 (n,)");
  const std::size_t total = static_cast<std::size_t>(ids.shape(0)), np = static_cast<std::size_t>(pts.shape(0));
  bhcl::check_radius_memory(n, total, false, 2, 0, "refine_radius");
  Uninit<double> d2(total);  // each slice's kept entries written, the rest never read
  Uninit<std::int32_t> out_ids(total);
  std::vector<std::int64_t> kept(n + 1, 0);
  const double* qd = q.data();
  const double* pd = pts.data();
  const double* rr = r2.data();
  const std::int64_t* off = offsets.data();
  const std::int32_t* id = ids.data();
  std::atomic<bool> bad{false};
  {
    py::gil_scoped_release nogil;
    // Each slice compacted in place (its kept points at its start), then the slices packed.
    const std::size_t ahead = prefetch_rows();
    over_rows(n, total, [&](std::size_t a, std::size_t b) {
      std::vector<std::pair<double, std::int32_t>> row;
      for (std::size_t r = a; r < b; ++r) {
        // As refine_knn: the points of the slice `ahead` rows on requested now.
        if (ahead && r + ahead < b)
          for (std::int64_t j = off[r + ahead]; j < off[r + ahead + 1]; ++j) {
            const std::int32_t i = id[j];
            if (i >= 0 && static_cast<std::size_t>(i) < np) {
              __builtin_prefetch(pd + 3 * static_cast<std::size_t>(i));
              __builtin_prefetch(pd + 3 * static_cast<std::size_t>(i) + 2);
            }
          }
        row.clear();
        for (std::int64_t j = off[r]; j < off[r + 1]; ++j) {
          const std::int32_t i = id[j];
          if (i < 0 || static_cast<std::size_t>(i) >= np) {
            bad = true;
            continue;
          }
          const double d = dist2_64(qd + 3 * r, pd + 3 * static_cast<std::size_t>(i));
          if (d <= rr[r]) row.emplace_back(d, i);
        }
        if (sorted) std::sort(row.begin(), row.end());
        for (std::size_t j = 0; j < row.size(); ++j) {
          d2[static_cast<std::size_t>(off[r]) + j] = row[j].first;
          out_ids[static_cast<std::size_t>(off[r]) + j] = row[j].second;
        }
        kept[r + 1] = static_cast<std::int64_t>(row.size());
      }
    });
    std::size_t at = 0;
    for (std::size_t r = 0; r < n; ++r) {
      const std::size_t from = static_cast<std::size_t>(off[r]), m = static_cast<std::size_t>(kept[r + 1]);
      if (from != at) {
        std::copy(&d2[from], &d2[from] + m, &d2[at]);
        std::copy(&out_ids[from], &out_ids[from] + m, &out_ids[at]);
      }
      at += m;
      kept[r + 1] += kept[r];
    }
  }
  if (bad) throw py::value_error("refine_radius: an id past the points");
  // The first kept[n] entries (the rest of the allocation, what the radius dropped, stays unused).
  const auto m = static_cast<py::ssize_t>(kept[n]);
  return py::make_tuple(to_numpy(std::move(kept), {static_cast<py::ssize_t>(n + 1)}), std::move(d2).to_numpy({m}),
                        std::move(out_ids).to_numpy({m}));
}

std::unique_ptr<bhcl::Index> make_index(const std::string& method,
                                        const std::shared_ptr<bhcl::Runtime>& runtime,
                                        const py::array_t<float, py::array::c_style>& points,
                                        const bhcl::MethodOptions& options) {
  if (!runtime) throw py::value_error("make_index: runtime is None");
  const std::size_t n = rows_of(points, "points");
  py::gil_scoped_release nogil;
  return bhcl::make_index(method, runtime, points.data(), n, options);
}

py::dict build_info(const bhcl::Index& index) {
  py::dict o;
  add_used(o, index.build_used());
  return o;
}

// The method registry (factory.hpp) as Python data, so that the package's keyword arguments come
// from the same entries as bhcl's options: per method its flags, build options (name as the
// command line spells it, kind, range or choices, default, help) and search options.
py::list method_table() {
  py::list out;
  for (const bhcl::MethodInfo& m : bhcl::methods()) {
    py::dict d;
    d["name"] = m.name;
    d["summary"] = m.summary;
    d["exact"] = m.exact;
    d["on_device"] = m.on_device;
    d["saves"] = m.saves;
    py::list opts;
    for (const bhcl::OptionInfo& o : m.options) {
      py::dict od;
      od["name"] = o.name;
      od["keyword"] = o.keyword_name();
      od["help"] = o.help;
      od["default"] = o.def;
      od["kind"] = o.kind == bhcl::OptionInfo::Kind::Integer  ? "integer"
                   : o.kind == bhcl::OptionInfo::Kind::Number ? "number"
                   : o.kind == bhcl::OptionInfo::Kind::Choice ? "choice"
                                                              : "file";
      od["range"] = o.range_text();
      od["lo"] = o.kind == bhcl::OptionInfo::Kind::Number ? py::object(py::float_(o.xlo)) : py::object(py::int_(o.lo));
      od["hi"] = o.kind == bhcl::OptionInfo::Kind::Number ? py::object(py::float_(o.xhi)) : py::object(py::int_(o.hi));
      od["choices"] = o.choices;
      od["build"] = bool(o.scope & bhcl::OptionInfo::Build);
      od["search"] = bool(o.scope & bhcl::OptionInfo::Search);
      od["radius"] = bool(o.scope & bhcl::OptionInfo::Radius);
      od["field"] = o.field;
      opts.append(od);
    }
    d["options"] = opts;
    out.append(d);
  }
  return out;
}

// One option of `method`'s table by name, parsed and range-checked by its entry (bhcl::Error,
// a ValueError, naming it otherwise).
const bhcl::OptionInfo& table_entry(const std::string& method, const std::string& name, unsigned scope) {
  for (const bhcl::OptionInfo& o : bhcl::method_info(method).options)
    if (o.name == name && (o.scope & scope)) return o;
  throw bhcl::Error("option '" + name + "' does not apply to method " + method);
}

// A keyword's value as the option table's parser reads it: a Python int or float crosses as a
// number and is written here locale-free (numbers.hpp: the shortest text that reads back to the
// same double), never through Python's or C's locale-dependent text (issue 38: after
// setlocale(LC_ALL, "de_DE.UTF-8") "8.0" was refused); a str passes as given (a choice).
std::string option_text(const py::handle& value) {
  if (py::isinstance<py::str>(value)) return value.cast<std::string>();
  if (py::isinstance<py::bool_>(value)) return value.cast<bool>() ? "1" : "0";
  if (py::isinstance<py::int_>(value)) return py::str(value).cast<std::string>();  // digits only
  if (py::isinstance<py::float_>(value)) return bhcl::detail::format_double(value.cast<double>());
  throw py::type_error("an option value must be a str, an int or a float");
}

void set_build_option(bhcl::MethodOptions& opts, const std::string& method, const std::string& name,
                      const py::object& value) {
  const std::string text = option_text(value);
  const bhcl::OptionInfo& o = table_entry(method, name, bhcl::OptionInfo::Build);
  o.parse(text, o.keyword_name());
  opts.set(name, text);
}

void set_search_option(bhcl::SearchParams& p, const std::string& method, const std::string& name,
                       const py::object& value) {
  const std::string text = option_text(value);
  const bhcl::OptionInfo& o = table_entry(method, name, bhcl::OptionInfo::Search);
  o.set_search(&p, o.parse(text, o.keyword_name()));
}

void set_radius_option(bhcl::RadiusParams& p, const std::string& method, const std::string& name,
                       const py::object& value) {
  const std::string text = option_text(value);
  const bhcl::OptionInfo& o = table_entry(method, name, bhcl::OptionInfo::Radius);
  o.set_radius(&p, o.parse(text, o.keyword_name()));
}

void save(const bhcl::Index& index, const std::string& path) {
  py::gil_scoped_release nogil;
  index.save(path);  // a method that does not save throws, naming itself
}

}  // namespace

namespace {

// Updates of an Index or a MultiDeviceIndex (Index::insert/remove): the new ids (first ..
// first + n - 1), the GIL released while the index changes.
template <class T>
py::array insert_points(T& index, const py::array_t<float, py::array::c_style>& points) {
  const std::size_t n = rows_of(points, "points");
  std::int32_t first = 0;
  {
    py::gil_scoped_release nogil;
    first = index.insert(points.data(), n);
  }
  std::vector<std::int32_t> ids(n);
  for (std::size_t i = 0; i < n; ++i) ids[i] = first + static_cast<std::int32_t>(i);
  return to_numpy(std::move(ids), {static_cast<py::ssize_t>(n)});
}
template <class T>
void remove_ids(T& index, const py::array_t<std::int32_t, py::array::c_style>& ids) {
  if (ids.ndim() != 1)
    throw bhcl::Error("remove: ids must be a 1-D array, got " + std::to_string(ids.ndim()) + " dimensions");
  const std::size_t n = static_cast<std::size_t>(ids.shape(0));
  py::gil_scoped_release nogil;
  index.remove(ids.data(), n);
}

// blockhash_cl.Error (a ValueError) and OpenCLError, and the translation of the library's exceptions.
void bind_errors(py::module_& m) {
  g_error = PyErr_NewExceptionWithDoc(
      "blockhash_cl.Error",
      "An error of the blockhash_cl library: bad input or parameters, an unreadable file. A ValueError.",
      PyExc_ValueError, nullptr);
  py::object bases = py::make_tuple(py::handle(g_error), py::handle(PyExc_RuntimeError));
  g_cl_error = PyErr_NewExceptionWithDoc(
      "blockhash_cl.OpenCLError",
      "An OpenCL call failed (or a kernel did not build): a blockhash_cl.Error and a RuntimeError.",
      bases.ptr(), nullptr);
  if (!g_error || !g_cl_error) throw py::error_already_set();
  m.add_object("Error", py::handle(g_error));
  m.add_object("OpenCLError", py::handle(g_cl_error));
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const bhcl::ClError& e) {
      PyErr_SetString(g_cl_error, e.what());
    } catch (const bhcl::Error& e) {
      PyErr_SetString(g_error, e.what());
    }
  });
}

// The method registry, the option setters and the devices.
void bind_registry(py::module_& m) {
  m.def("method_names", &bhcl::method_names, "Names make_index accepts, in display order.");
  m.def("method_table", &method_table, "The method registry: flags, build and search options.");
  m.def("set_build_option", &set_build_option, py::arg("options"), py::arg("method"),
        py::arg("name"), py::arg("value"));
  m.def("set_search_option", &set_search_option, py::arg("params"), py::arg("method"),
        py::arg("name"), py::arg("value"));
  m.def("set_radius_option", &set_radius_option, py::arg("params"), py::arg("method"),
        py::arg("name"), py::arg("value"));
  m.def("list_devices", [] {
    std::vector<py::dict> out;
    for (const auto& d : bhcl::list_devices()) out.push_back(device_dict(d));
    return out;
  }, "Every OpenCL device of every platform (empty when there is none).");
  m.def("select_device", [](const std::string& spec) { return device_dict(bhcl::select_device(spec)); },
        py::arg("spec"), "The device a spec picks (empty: BHCL_DEVICE, then the default).");

  py::class_<bhcl::Runtime, std::shared_ptr<bhcl::Runtime>>(m, "Runtime")
      .def(py::init([](const std::string& spec) {
             py::gil_scoped_release nogil;
             return std::make_shared<bhcl::Runtime>(spec);
           }),
           py::arg("spec") = "")
      .def_property_readonly("device", [](const bhcl::Runtime& r) { return device_dict(r.info()); })
      .def_property_readonly("build_seconds", &bhcl::Runtime::build_seconds);
  m.def("default_runtime", [] {
    py::gil_scoped_release nogil;
    return bhcl::default_runtime();
  }, "The process-wide runtime (BHCL_DEVICE, read once, else PoCL, else the first device).");
}

// SearchParams, RadiusParams (both a DispatchParams, as in knn.hpp: its fields bound once, on the
// base) and MethodOptions.
void bind_params(py::module_& m) {
  py::class_<bhcl::DispatchParams>(m, "DispatchParams")
      .def_readwrite("local_size", &bhcl::DispatchParams::local_size)
      .def_readwrite("max_batch", &bhcl::DispatchParams::max_batch)
      .def_readwrite("sort_queries", &bhcl::DispatchParams::sort_queries)
      .def_readwrite("count_examined", &bhcl::DispatchParams::count_examined);

  py::class_<bhcl::SearchParams, bhcl::DispatchParams>(m, "SearchParams")
      .def(py::init<>())
      .def_readwrite("k", &bhcl::SearchParams::k)
      .def_readwrite("max_radius", &bhcl::SearchParams::max_radius)
      .def_readwrite("A", &bhcl::SearchParams::A)
      .def_readwrite("recall_target", &bhcl::SearchParams::recall_target);

  py::class_<bhcl::RadiusParams, bhcl::DispatchParams>(m, "RadiusParams")
      .def(py::init<>())
      .def_readwrite("budget", &bhcl::RadiusParams::budget)
      .def_readwrite("max_results", &bhcl::RadiusParams::max_results)
      .def_readwrite("sorted", &bhcl::RadiusParams::sorted)
      .def_readwrite("max_batch_results", &bhcl::RadiusParams::max_batch_results);

  py::class_<bhcl::MethodOptions>(m, "MethodOptions")
      .def(py::init<>())
      .def_readwrite("values", &bhcl::MethodOptions::values)
      .def("set", [](bhcl::MethodOptions& o, const std::string& name, const std::string& text) { o.set(name, text); },
           py::arg("name"), py::arg("text"));
}

// bhcl::SearchIndex, the base of Index, MultiDeviceIndex and DistributedIndex: what every one
// has, bound once (the three derive from it in Python as in C++).
void bind_search_index(py::module_& m) {
  py::class_<bhcl::SearchIndex>(m, "SearchIndex")
      .def_property_readonly("method", &bhcl::SearchIndex::method)
      .def_property_readonly("exact", &bhcl::SearchIndex::exact)
      .def_property_readonly("size", &bhcl::SearchIndex::size);
}

// bhcl::Index: the calls the package's Index wraps.
void bind_index(py::module_& m) {
  py::class_<bhcl::Index, bhcl::SearchIndex, std::unique_ptr<bhcl::Index>>(m, "Index")
      .def_property_readonly("memory_bytes", &bhcl::Index::memory_bytes)
      .def_property_readonly("host_bytes", &bhcl::Index::host_bytes)
      .def_property_readonly("saves", &bhcl::Index::saves)
      .def_property_readonly("build_seconds", &bhcl::Index::build_seconds)
      .def_property_readonly("runtime", &bhcl::Index::runtime_ptr)
      .def_property_readonly("build_info", &build_info)
      .def("query", &knn_query<bhcl::Index>, py::arg("queries").noconvert(), py::arg("params"))
      .def("radius_search", &radius_query<bhcl::Index>, py::arg("queries").noconvert(), py::arg("r"),
           py::arg("squared"), py::arg("params"))
      .def("save", &save, py::arg("path"))
      // Updates (Index::insert/remove): the new ids (first .. first + n - 1), GIL released.
      .def("insert", &insert_points<bhcl::Index>, py::arg("points").noconvert())
      .def("remove", &remove_ids<bhcl::Index>, py::arg("ids").noconvert())
      .def_property_readonly("id_bound", &bhcl::Index::id_bound)
      .def("contains", &bhcl::Index::contains, py::arg("id"))
      .def_property_readonly("removed_count", &bhcl::Index::removed_count)
      .def("removed_ids", [](const bhcl::Index& index) {  // ascending (a loaded index's, for its copy)
             std::vector<std::int32_t> ids;
             ids.reserve(index.removed_count());
             for (std::int32_t id = 0; id < index.id_bound() && ids.size() < index.removed_count(); ++id)
               if (!index.contains(id)) ids.push_back(id);
             const auto n = static_cast<py::ssize_t>(ids.size());
             return to_numpy(std::move(ids), {n});
           })
      .def("warm_up", [](const bhcl::Index& i, const bhcl::SearchParams& p) {
        py::gil_scoped_release nogil;
        return i.warm_up(p);
      }, py::arg("params"));
}

// The float64 refinement helpers and make_index.
void bind_refine(py::module_& m) {
  m.def("refine_knn", &refine_knn, py::arg("q").noconvert(), py::arg("points").noconvert(),
        py::arg("ids").noconvert(), py::arg("k"), "float64 refinement of kNN rows (blockhash_cl/_refine.py).");
  m.def("query_delta", &query_delta, py::arg("q32").noconvert(), py::arg("point_rounding"), py::arg("sqrt3"),
        py::arg("rel"), "_refine.query_delta: the widening per query.");
  m.def("pair_dist2", &pair_dist2, py::arg("q").noconvert(), py::arg("owner").noconvert(),
        py::arg("points").noconvert(), py::arg("ids").noconvert(), "float64 squared distances of pairs.");
  m.def("refine_radius", &refine_radius, py::arg("q").noconvert(), py::arg("points").noconvert(),
        py::arg("offsets").noconvert(), py::arg("ids").noconvert(), py::arg("r2").noconvert(), py::arg("sorted"),
        "float64 refinement of radius slices.");
  m.def("make_index", &make_index, py::arg("method"), py::arg("runtime"),
        py::arg("points").noconvert(), py::arg("options"));
}

// bhcl::MultiDeviceIndex.
void bind_multi_device(py::module_& m) {
  // bhcl::MultiDeviceIndex with the attributes and calls of Index above that the package's Index
  // uses (it wraps either): one copy per runtime, a batch split among them by their throughput.
  using Multi = bhcl::MultiDeviceIndex;
  py::class_<Multi, bhcl::SearchIndex, std::unique_ptr<Multi>>(m, "MultiDeviceIndex")
      .def(py::init([](std::vector<std::shared_ptr<bhcl::Runtime>> runtimes, const std::string& method,
                       const py::array_t<float, py::array::c_style>& points, const bhcl::MethodOptions& options) {
             const std::size_t n = rows_of(points, "points");
             py::gil_scoped_release nogil;
             return std::make_unique<Multi>(std::move(runtimes), method, points.data(), n, options);
           }),
           py::arg("runtimes"), py::arg("method"), py::arg("points").noconvert(), py::arg("options"))
      .def_property_readonly("devices", &Multi::devices)
      .def_property_readonly("memory_bytes", [](const Multi& x) {
        std::size_t b = 0;
        for (std::size_t d = 0; d < x.devices(); ++d) b += x.index(d).memory_bytes();
        return b;
      })
      .def_property_readonly("host_bytes", [](const Multi& x) {
        std::size_t b = 0;
        for (std::size_t d = 0; d < x.devices(); ++d) b += x.index(d).host_bytes();
        return b;
      })
      .def_property_readonly("saves", [](const Multi&) { return false; })
      .def_property_readonly("build_seconds", [](const Multi& x) {
        double s = 0;
        for (std::size_t d = 0; d < x.devices(); ++d) s = std::max(s, x.index(d).build_seconds());
        return s;
      })
      .def_property_readonly("runtime", [](const Multi& x) { return x.index(0).runtime_ptr(); })
      .def_property_readonly("runtimes", [](const Multi& x) {
        std::vector<std::shared_ptr<bhcl::Runtime>> r;
        for (std::size_t d = 0; d < x.devices(); ++d) r.push_back(x.index(d).runtime_ptr());
        return r;
      })
      .def_property_readonly("build_info", [](const Multi& x) {
        py::dict o;
        add_used(o, x.build_used());
        return o;
      })
      .def_property_readonly("weights", &Multi::weights)
      .def("set_weights", &Multi::set_weights, py::arg("weights"))
      .def("query", &knn_query<Multi>, py::arg("queries").noconvert(), py::arg("params"))
      .def("radius_search", &radius_query<Multi>, py::arg("queries").noconvert(), py::arg("r"),
           py::arg("squared"), py::arg("params"))
      .def("save", [](const Multi&, const std::string&) {
        throw bhcl::Error("save: a multi-device index saves through the package (its points), not a structure file");
      }, py::arg("path"))
      .def("insert", &insert_points<Multi>, py::arg("points").noconvert())
      .def("remove", &remove_ids<Multi>, py::arg("ids").noconvert())
      .def_property_readonly("id_bound", &Multi::id_bound)
      .def("contains", [](const Multi& x, std::int32_t id) { return x.index(0).contains(id); }, py::arg("id"))
      .def_property_readonly("removed_count", [](const Multi& x) { return x.index(0).removed_count(); })
      .def("warm_up", [](const Multi& x, const bhcl::SearchParams& p) {
        py::gil_scoped_release nogil;
        double s = 0;
        for (std::size_t d = 0; d < x.devices(); ++d) s += x.index(d).warm_up(p);
        return s;
      }, py::arg("params"));
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "blockhash_cl's C++ layer; use the package blockhash_cl, not this module.";
  m.attr("__version__") = BHCL_VERSION_STRING;
  m.attr("HAVE_FLANN") = bool(BHCL_HAVE_FLANN);
  m.attr("MAX_K") = bhcl::kMaxK;

  bind_errors(m);
  bind_registry(m);
  bind_params(m);
  bind_search_index(m);
  bind_index(m);
  bind_refine(m);
  bind_multi_device(m);
#if BHCL_PYTHON_DISTRIBUTED
  m.attr("HAVE_MPI") = true;
  bind_distributed(m);
#else
  m.attr("HAVE_MPI") = false;
#endif
}
