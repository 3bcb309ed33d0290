// The one host-array query pipeline: the steps every kind of query (kNN, radius) shares, done
// once here; the kinds (query_pipeline.hpp) supply their rows, passes and suspect-row test.
#include "core/query_pipeline.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <future>
#include <limits>
#include <memory>

#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "core/parallel.hpp"
#include "core/query_order.hpp"

namespace bhcl {

namespace detail {

float trusted_min_distance() { return std::ldexp(1.0f, -120); }

float to_float_or_inf(double d) {
  return d > double(std::numeric_limits<float>::max()) ? INFINITY : static_cast<float>(d);
}

cl::Buffer io_buffer(const Runtime& rt, bool host_visible, std::size_t bytes, const char* what) {
  if (!host_visible) return device_buffer(rt, bytes, what);
  cl_int err = CL_SUCCESS;
  cl::Buffer b(rt.context(), CL_MEM_READ_WRITE | CL_MEM_ALLOC_HOST_PTR, std::max<std::size_t>(bytes, 4), nullptr, &err);
  check_cl(err, "clCreateBuffer", std::string(what) + " (host memory), " + std::to_string(bytes) + " bytes");
  return b;
}

Mapped::Mapped(const cl::CommandQueue& q, const cl::Buffer& b, cl_map_flags flags, std::size_t bytes,
               const char* what, bool blocking)
    : q_(q), b_(b) {
  cl_int err = CL_SUCCESS;
  ptr_ = q.enqueueMapBuffer(b, blocking ? CL_TRUE : CL_FALSE, flags, 0, std::max<std::size_t>(bytes, 4), nullptr,
                            nullptr, &err);
  check_cl(err, "clEnqueueMapBuffer", what);
}

void Mapped::unmap(const char* what) {
  cl::Event e;
  check_cl(q_.enqueueUnmapMemObject(b_, ptr_, nullptr, &e), "clEnqueueUnmapMemObject", what);
  ptr_ = nullptr;
}

}  // namespace detail

namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

std::size_t count_nonfinite(const float* queries, std::size_t n) {
  std::size_t c = 0;
  for (std::size_t i = 0; i < n; ++i) c += !detail::finite_query(queries + 3 * i);
  return c;
}

// Queries [lo, hi) in dispatch order (order null: as given) into dst[0, hi - lo), scaled by
// 2^-e into the structure's coordinates (e = 0: copied); rows (when not null) gets each dispatch
// row's caller row, for the kernel's store. One thread.
void gather_range(const float* caller, std::size_t lo, std::size_t hi, const std::size_t* order, int e, float* dst,
                  std::uint32_t* rows) {
  // In Hilbert order the caller's rows are read at random: each one's line asked for 32 rows
  // ahead, so that the reads overlap (1M Cornell queries: 12.5 against 18 ms on 2 threads).
  constexpr std::size_t kAhead = 32;
  for (std::size_t i = lo; i < hi; ++i) {
    if (order && i + kAhead < hi) __builtin_prefetch(caller + 3 * order[i + kAhead]);
    const std::size_t row = order ? order[i] : i;
    const float* q = caller + 3 * row;
    float* d = dst + 3 * (i - lo);
    for (int c = 0; c < 3; ++c) d[c] = e ? std::ldexp(q[c], -e) : q[c];
    if (rows) rows[i - lo] = static_cast<std::uint32_t>(row);
  }
}

// Queries [first, first + m) in dispatch order into dst (rows: as gather_range), on the threads:
// the sort and the scale fused with the upload.
void gather_queries(const float* caller, std::size_t first, std::size_t m, const std::size_t* order, int e,
                    float* dst, std::uint32_t* rows = nullptr) {
  detail::parallel_for(m, [&](std::size_t lo, std::size_t hi) {
    gather_range(caller, first + lo, first + hi, order, e, dst + 3 * lo, rows ? rows + lo : nullptr);
  }, 0, 16384);
}

// The chunk's queries into b.q (and their caller rows into b.result_rows where the kernel writes
// the caller's rows): mapped in place on a CPU device, written from a staging copy on a GPU.
// result_rows: null where the rows are copied after the kernel.
// A CPU device's query buffer (and caller-row buffer, when not null) mapped for writing m
// dispatch rows: both maps enqueued, then one wait (each blocking map is a round trip to the
// device's threads); unmap() hands them back (the destructors do on an exception).
struct MappedQueries {
  detail::Mapped q;
  std::unique_ptr<detail::Mapped> rows;
  MappedQueries(const cl::CommandQueue& queue, const cl::Buffer& qb, const cl::Buffer* result_rows, std::size_t m)
      : q(queue, qb, CL_MAP_WRITE_INVALIDATE_REGION, m * 3 * sizeof(float), "queries", false) {
    if (result_rows)
      rows = std::make_unique<detail::Mapped>(queue, *result_rows, CL_MAP_WRITE_INVALIDATE_REGION, m * 4,
                                              "result rows", false);
    check_cl(queue.finish(), "clFinish", "queries mapped");
  }
  float* queries() const { return q.as<float>(); }
  std::uint32_t* caller_rows() const { return rows ? rows->as<std::uint32_t>() : nullptr; }
  void unmap() {
    if (rows) rows->unmap("result rows");
    q.unmap("queries");
  }
};

void upload_queries(const cl::CommandQueue& queue, const cl::Buffer& q, bool host, const cl::Buffer* result_rows,
                    const float* caller, std::size_t first, std::size_t m, const std::size_t* order, int e,
                    std::vector<float>& stage) {
  if (host) {
    MappedQueries map(queue, q, result_rows, m);
    gather_queries(caller, first, m, order, e, map.queries(), map.caller_rows());
    map.unmap();
    return;
  }
  stage.resize(3 * m);
  gather_queries(caller, first, m, order, e, stage.data());
  check_cl(queue.enqueueWriteBuffer(q, CL_FALSE, 0, m * 3 * sizeof(float), stage.data()), "clEnqueueWriteBuffer",
           "queries");
}

}  // namespace

bool Index::QueryKind::entry_suspect(const float* q, std::int32_t id, float d) const {
  if (std::isinf(d)) return true;  // overflowed: ranked by index, not by the true distance
  if (d == 0) {
    const float* p = ix_.caller_points_.data() + 3 * static_cast<std::size_t>(id);
    return !(p[0] == q[0] && p[1] == q[1] && p[2] == q[2]);  // flushed to zero
  }
  return d < detail::trusted_min_distance();
}

void Index::QueryKind::exact_candidates(const float* q, double r2, std::size_t k, std::vector<Candidate>& best) const {
  // Every id issued; a removed one is skipped by its mark (its row is left as it was).
  const std::size_t N = ix_.caller_points_.size() / 3;
  const float* pts = ix_.caller_points_.data();
  const double qx = q[0], qy = q[1], qz = q[2];
  best.clear();
  for (std::size_t i = 0; i < N; ++i) {
    const double dx = qx - pts[3 * i], dy = qy - pts[3 * i + 1], dz = qz - pts[3 * i + 2];
    const double d = dx * dx + dy * dy + dz * dz;
    if (!(d <= r2) || ix_.id_removed(static_cast<std::int32_t>(i))) continue;
    const Candidate c{d, static_cast<std::int32_t>(i)};
    if (k == 0) {
      best.push_back(c);
    } else if (best.size() < k || c < best.back()) {
      if (best.size() == k) best.pop_back();
      best.insert(std::upper_bound(best.begin(), best.end(), c), c);
    }
  }
  if (k == 0) std::sort(best.begin(), best.end());
}

QueryStats Index::run_query(const float* queries, std::size_t n, QueryKind& kind) const {
  const auto t0 = std::chrono::steady_clock::now();
  ReadLock lock(*this);  // queries share the index; insert/remove wait (see insert)
  if (n > 0 && !queries) throw Error(std::string(kind.name()) + ": queries is null with n = " + std::to_string(n));
  const DispatchParams& dp = kind.dispatch();
  const bool sort = n > 1 && (dp.sort_queries > 0 || (dp.sort_queries < 0 && n >= kAutoSortQueries));
  // Sizes before allocation: a result that cannot fit is refused with what it needs, before any
  // search (the Hilbert-ordered path holds the rows twice).
  kind.check(n, sort ? 2 : 1);
  QueryStats st;
  st.n_queries = n;
  if (!sort) st.nonfinite_queries = count_nonfinite(queries, n);  // else counted by the sort's box pass
  std::unique_ptr<std::size_t[]> order;  // dispatch in Hilbert order: neighbouring work-items walk the same cells
  // A first call's program load (the binary cache's, or a compile) on its own thread while this
  // one sorts: they share nothing, and the load is as long as the sort of 10^5 queries.
  std::future<double> warm;
  if (sort && !answers_on_host()) {
    const std::size_t local = local_size_for(dp);
    bool warmed = false;
    {
      std::lock_guard<std::mutex> lock(warm_mutex_);
      warmed = warmed_.count(std::make_tuple(kind.kernel_variant(), local, dp.kernel_defines)) > 0;
    }
    if (!warmed) warm = std::async(std::launch::async, [this, &kind, local] { return warm_up_kind(kind, local); });
  }
  // The sort: on a device, where search_on_device calls it once the query buffer is mapped (a
  // sink set: the sort's last pass also gathers the queries there, no pass of their own after it).
  const SortStep sort_step = [&](const detail::OrderSink* sink) -> const std::size_t* {
    const auto ts = std::chrono::steady_clock::now();
    order = detail::hilbert_query_order_fresh(queries, n, &st.nonfinite_queries, sink);
    st.sort_s = seconds_since(ts);
    if (warm.valid()) st.compile_s += warm.get();
    return order.get();
  };
  if (sort && answers_on_host()) sort_step(nullptr);
  kind.begin(n);
  std::vector<std::size_t> suspects;
  if (n > 0 && answers_on_host()) search_on_host(queries, n, order.get(), kind, st, suspects);
  else if (n > 0) search_on_device(queries, n, nullptr, kind, st, suspects, sort ? &sort_step : nullptr);
  const std::size_t* ord = order.get();
  kind.finish(ord, queries, st, suspects);
  // The rows in ascending order: the answers do not depend on the thread count.
  std::sort(suspects.begin(), suspects.end());
  if (!suspects.empty()) kind.answer_exactly(queries, suspects);
  st.wall_s = seconds_since(t0);
  return st;
}

void Index::search_on_host(const float* queries, std::size_t n, const std::size_t* order, QueryKind& kind,
                           QueryStats& st, std::vector<std::size_t>& suspects) const {
  if (!order && scale_exp_ == 0) return kind.search_host(queries, n, nullptr, queries, st, suspects);
  // The queries in dispatch order and the structure's coordinates, in one pass.
  std::vector<float> q(3 * n);
  gather_queries(queries, 0, n, order, scale_exp_, q.data());
  kind.search_host(q.data(), n, order, queries, st, suspects);
}

void Index::search_on_device(const float* queries, std::size_t n, const std::size_t* order, QueryKind& kind,
                             QueryStats& st, std::vector<std::size_t>& suspects, const SortStep* sort) const {
  const cl::CommandQueue& queue = runtime_->queue();
  const DispatchParams& dp = kind.dispatch();
  const std::size_t local = local_size_for(dp);
  const std::size_t per = queries_per_launch(dp.max_batch, local);
  const std::size_t chunk = std::min(kind.chunk_rows(n), n);
  QueryBuffers b;
  take_query_buffers(chunk, kind.row_k(), dp.count_examined, b);
  // One chunk in host memory (a CPU device): the sort's last pass gathers each finished part of
  // the order into the mapped buffers (no gather pass of its own after the sort, no second read
  // of the order); else the sort, then each chunk's upload.
  bool uploaded = false;
  if (sort && b.host && chunk == n) {
    const auto tu = std::chrono::steady_clock::now();
    MappedQueries map(queue, b.q, b.writes_caller_rows(n) ? &b.result_rows : nullptr, n);
    st.upload_s += seconds_since(tu);
    float* dst = map.queries();
    std::uint32_t* rdst = map.caller_rows();
    const int e = scale_exp_;
    const detail::OrderSink sink = [&](std::size_t lo, std::size_t hi, const std::size_t* ord) {
      gather_range(queries, lo, hi, ord, e, dst + 3 * lo, rdst ? rdst + lo : nullptr);
    };
    order = (*sort)(&sink);
    const auto tm = std::chrono::steady_clock::now();
    map.unmap();
    st.upload_s += seconds_since(tm);
    uploaded = true;
  } else if (sort) {
    order = (*sort)(nullptr);
  }
  st.compile_s += warm_up_kind(kind, local);
  std::vector<float> stage;  // device memory only: the gathered queries before their copy
  for (std::size_t first = 0; first < n; first += chunk) {
    const std::size_t m = std::min(chunk, n - first);
    if (!uploaded) {
      const auto tu = std::chrono::steady_clock::now();
      upload_queries(queue, b.q, b.host, b.writes_caller_rows(n) ? &b.result_rows : nullptr, queries, first, m,
                     order, scale_exp_, stage);
      st.upload_s += seconds_since(tu);
    }
    uploaded = false;
    kind.search_chunk(b, first, m, order, per, local, queries, st, suspects);
  }
  // The last chunk's unmaps done before its buffers serve another call.
  check_cl(queue.finish(), "clFinish", method() + " query");
  give_back_query_buffers(std::move(b));
}

double Index::warm_up_kind(const QueryKind& kind, std::size_t local) const {
  const auto key = std::make_tuple(kind.kernel_variant(), local, kind.dispatch().kernel_defines);
  std::lock_guard<std::mutex> lock(warm_mutex_);
  if (warmed_.count(key)) return 0.0;
  const auto t0 = std::chrono::steady_clock::now();
  // Zero-count launches compile the program (clBuildProgram) and, on PoCL, the machine code for
  // this local size; kernels return at once for count 0. Buffers of 16 bytes stand in for the rows.
  QueryBuffers b;
  for (cl::Buffer* buf : {&b.q, &b.ids, &b.dist2, &b.counts, &b.examined_buf, &b.offsets})
    *buf = detail::device_buffer(*runtime_, 16, "warm-up");
  kind.warm_launch(b, local);
  runtime_->keep_program_binaries();  // the launches compiled this local size: kept for later processes
  warmed_.insert(key);
  return seconds_since(t0);
}

void Index::take_query_buffers(std::size_t rows, std::size_t k, bool examined, QueryBuffers& b) const {
  QueryBuffers& cache = io_cache_[k ? 0 : 1];
  {
    std::lock_guard<std::mutex> lock(io_mutex_);
    if (cache.rows >= rows && cache.k == k && (cache.examined() || !examined)) {
      b = std::move(cache);
      cache = QueryBuffers{};
      return;
    }
  }
  const Runtime& rt = *runtime_;
  b.host = (rt.info().type & CL_DEVICE_TYPE_CPU) != 0;
  b.rows = rows;
  b.k = k;
  b.q = detail::io_buffer(rt, b.host, rows * 3 * sizeof(float), "queries");
  b.counts = detail::io_buffer(rt, b.host, rows * sizeof(std::int32_t), "counts");
  if (examined) b.examined_buf = detail::io_buffer(rt, b.host, rows * sizeof(std::int32_t), "examined");
  if (k && b.host) b.result_rows = detail::io_buffer(rt, true, rows * sizeof(std::uint32_t), "result rows");
  if (k) {
    b.ids = detail::io_buffer(rt, b.host, rows * k * sizeof(std::int32_t), "ids");
    b.dist2 = detail::io_buffer(rt, b.host, rows * k * sizeof(float), "dist2");
  } else {
    // Radius: the fill pass's slices grow with what the count pass finds (RadiusKind).
    b.offsets = detail::io_buffer(rt, b.host, rows * sizeof(cl_ulong), "radius offsets");
    b.ids = b.dist2 = detail::io_buffer(rt, b.host, 4, "radius fill");
  }
}

void Index::give_back_query_buffers(QueryBuffers&& b) const {
  // Kept for the next call (its pages are mapped already: fresh ones fault on every 4 KiB),
  // up to the bound on scratch memory.
  if (b.bytes() > kSortScratchBytes) return;
  std::lock_guard<std::mutex> lock(io_mutex_);
  QueryBuffers& cache = io_cache_[b.k ? 0 : 1];
  if (b.rows >= cache.rows) cache = std::move(b);
}

}  // namespace bhcl
