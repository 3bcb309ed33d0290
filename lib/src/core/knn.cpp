// The Index base: parameter checks, batching, warm-up launches and timing, shared by all methods.
#include "blockhash_cl/knn.hpp"

#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <sstream>

#include <unistd.h>

#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "core/kernel_defines.hpp"
#include "core/parallel.hpp"
#include "core/point_scan.hpp"
#include "core/query_order.hpp"

namespace bhcl {

int kmax_variant(int k) {
  if (k < 1 || k > kMaxK)
    throw Error("k = " + std::to_string(k) + " is out of range: must be in [1, " +
                std::to_string(kMaxK) + "]");
  for (int v : kKmaxVariants)
    if (v >= k) return v;
  return kMaxK;
}

template <class Id>
void KnnRows<Id>::resize(std::size_t n_queries, int k_) {
  n = n_queries;
  k = k_;
  ids.assign(n * static_cast<std::size_t>(k), -1);
  dist2.assign(n * static_cast<std::size_t>(k), std::numeric_limits<float>::infinity());
  counts.assign(n, 0);
  examined.clear();
}

template <class Id>
KnnRows<Id> KnnRows<Id>::leading_columns(int k_) const {
  if (k_ < 1 || k_ > k)
    throw Error("leading_columns: k = " + std::to_string(k_) + " outside [1, " + std::to_string(k) + "]");
  KnnRows r;
  r.resize(n, k_);
  for (std::size_t q = 0; q < n; ++q) {
    std::copy_n(&ids[q * k], k_, &r.ids[q * k_]);
    std::copy_n(&dist2[q * k], k_, &r.dist2[q * k_]);
    r.counts[q] = std::min(counts[q], k_);
  }
  return r;
}

template struct KnnRows<std::int32_t>;
template struct KnnRows<std::int64_t>;

void validate_points(const float* xyz, std::size_t n, const char* what) {
  for (std::size_t i = 0; i < n; ++i) {
    const float* p = xyz + 3 * i;
    if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) {
      std::ostringstream os;
      os << what << ": point " << i << " has a non-finite coordinate (" << p[0] << ", " << p[1]
         << ", " << p[2] << ")";
      throw Error(os.str());
    }
  }
}

namespace {

// dst[i] = src[i] * 2^e, exact unless the result leaves the float range (kernels/scale.cl does
// the same on the device). src and dst may be the same array.
void ldexp_all(const float* src, float* dst, std::size_t count, int e) {
  for (std::size_t i = 0; i < count; ++i) dst[i] = std::ldexp(src[i], e);
}

// The process that first used OpenCL through an index (0: none yet). OpenCL objects do not
// survive fork(): a forked child that inherits an index would hang in its first OpenCL call, so
// device methods refuse there with a clear error.
std::atomic<long> g_opencl_pid{0};

void refuse_in_forked_child(const std::string& method) {
  const long self = static_cast<long>(::getpid());
  long first = 0;
  if (g_opencl_pid.compare_exchange_strong(first, self) || first == self) return;
  throw Error(method + ": this index (its OpenCL runtime) was created in process " + std::to_string(first) +
              "; this is process " + std::to_string(self) +
              ", a forked child, where OpenCL cannot be used (its objects do not survive fork) and a call "
              "would hang: use the index in the process that built it, or start children with spawn "
              "(Python: multiprocessing.get_context('spawn')); a forked child can build its own index "
              "only when its parent has not used OpenCL");
}

}  // namespace

namespace {
// The exponent for points whose box (one scan_points pass) is known.
int scale_exponent_of(const detail::PointScan& box, const float* points, std::size_t n) {
  double extent = 0, maxabs = 0;
  for (int d = 0; d < 3 && n; ++d) {
    extent = std::max(extent, double(box.hi[d]) - double(box.lo[d]));
    // The largest magnitude is at one end of the box.
    maxabs = std::max({maxabs, std::fabs(double(box.lo[d])), std::fabs(double(box.hi[d]))});
  }
  // Squared distances stay normal floats with room to spare inside [2^-40, 2^40].
  auto in_range = [](double x) { return x >= std::ldexp(1.0, -40) && x <= std::ldexp(1.0, 40); };
  if (extent == 0 || in_range(extent)) return 0;
  // Outside: the scale of the bulk, so that a few far outliers (a point at 3e24 among points in
  // [0,1]^3) do not flush every other distance to zero. Per dimension the 1st to 99th percentile
  // of a strided sample of at most 2^20 points.
  const std::size_t step = std::max<std::size_t>(1, n / (std::size_t(1) << 20));
  std::vector<float> v;
  v.reserve(n / step + 1);
  double bulk = 0;
  for (int d = 0; d < 3; ++d) {
    v.clear();
    for (std::size_t i = 0; i < n; i += step) v.push_back(points[3 * i + d]);
    const std::size_t a = v.size() / 100, b = v.size() - 1 - v.size() / 100;
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(a), v.end());
    const double qa = v[a];
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(b), v.end());
    bulk = std::max(bulk, double(v[b]) - qa);
  }
  int e = (bulk == 0 || in_range(bulk)) ? 0 : std::ilogb(bulk);
  // Every scaled coordinate below 2^126, so that the difference of two is a finite float.
  if (maxabs > 0) e = std::max(e, std::ilogb(maxabs) - 125);
  return e;
}
}  // namespace

int Index::choose_scale_exponent(const float* points, std::size_t n) {
  return scale_exponent_of(detail::scan_points(points, n), points, n);
}

const float* Index::prepare_points(const float* points, std::size_t n, std::vector<float>& storage) {
  if (n == 0) throw Error(method() + ": the point set is empty (N = 0)");
  if (n > 0x7ffffffeu)
    throw Error(method() + ": N = " + std::to_string(n) +
                " points exceeds one index's int32 id range (at most 2^31 - 2 points; a DistributedIndex "
                "over enough ranks holds more, with int64 ids)");
  // One parallel pass for the validation and the scale; the serial check only to name the
  // first non-finite point.
  const detail::PointScan box = detail::scan_points(points, n);
  if (!box.finite) validate_points(points, n, "points");
  if (!answers_on_host()) refuse_in_forked_child(method());
  if (exact()) {
    // Room for inserts of up to an eighth (1.5 B per point, untouched until used): the first
    // insert after a build appends instead of moving every row (issue 39).
    caller_points_.reserve(3 * (n + n / 8));
    caller_points_.assign(points, points + 3 * n);
  }
  scale_exp_ = scale_exponent_of(box, points, n);
  if (scale_exp_ == 0) return points;
  storage.resize(3 * n);
  ldexp_all(points, storage.data(), 3 * n, -scale_exp_);
  return storage.data();
}

namespace {
// Below this a squared distance in the structure's coordinates may have lost precision (its
// components' squares underflow); the float ranking is then not vouched for.
const float kTrustedMin = std::ldexp(1.0f, -120);
// A double squared distance as the contract reports it: rounded to float, +inf above FLT_MAX.
float to_float_or_inf(double d) {
  return d > double(std::numeric_limits<float>::max()) ? INFINITY : static_cast<float>(d);
}
}  // namespace

bool Index::entry_suspect(const float* q, std::int32_t id, float d) const {
  if (std::isinf(d)) return true;  // overflowed: ranked by index, not by the true distance
  if (d == 0) {
    const float* p = caller_points_.data() + 3 * static_cast<std::size_t>(id);
    return !(p[0] == q[0] && p[1] == q[1] && p[2] == q[2]);  // flushed to zero
  }
  return d < kTrustedMin;
}

void Index::collect_suspect_rows(const float* caller_queries, std::size_t first, std::size_t m,
                                 float r2s, const KnnResult& out, std::vector<std::size_t>& rows) const {
  if (!exact() || caller_points_.empty()) return;
  const std::size_t k = static_cast<std::size_t>(out.k);
  const int full = static_cast<int>(std::min<std::size_t>(k, size()));
  const bool tiny_radius = r2s > 0 && r2s < kTrustedMin;
  for (std::size_t i = first; i < first + m; ++i) {
    const float* q = caller_queries + 3 * i;
    if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) continue;
    const int c = out.counts[i];
    bool bad = tiny_radius || (std::isinf(r2s) && c < full);
    for (int j = 0; j < c && !bad; ++j) bad = entry_suspect(q, out.ids[i * k + j], out.dist2[i * k + j]);
    if (bad) rows.push_back(i);
  }
}

void Index::answer_rows_exactly(const float* caller_queries, const std::vector<std::size_t>& rows,
                                const SearchParams& params, KnnResult& out) const {
  if (rows.empty()) return;
  const std::size_t k = static_cast<std::size_t>(params.k);
  const double r = params.max_radius;
  const double r2 = std::isinf(r) ? INFINITY : r * r;
  // Every id issued: a removed one holds NaN, which `d <= r2` rejects.
  const std::size_t N = caller_points_.size() / 3;
  const float* pts = caller_points_.data();
  detail::parallel_for(rows.size(), [&](std::size_t b, std::size_t e) {
    std::vector<std::pair<double, std::int32_t>> best;
    for (std::size_t t = b; t < e; ++t) {
      const std::size_t row = rows[t];
      const double qx = caller_queries[3 * row], qy = caller_queries[3 * row + 1],
                   qz = caller_queries[3 * row + 2];
      best.clear();
      for (std::size_t i = 0; i < N; ++i) {
        const double dx = qx - pts[3 * i], dy = qy - pts[3 * i + 1], dz = qz - pts[3 * i + 2];
        const double d = dx * dx + dy * dy + dz * dz;
        if (!(d <= r2)) continue;
        const std::pair<double, std::int32_t> c{d, static_cast<std::int32_t>(i)};
        if (best.size() < k) {
          best.insert(std::upper_bound(best.begin(), best.end(), c), c);
        } else if (c < best.back()) {
          best.pop_back();
          best.insert(std::upper_bound(best.begin(), best.end(), c), c);
        }
      }
      for (std::size_t j = 0; j < k; ++j) {
        out.ids[row * k + j] = j < best.size() ? best[j].second : -1;
        out.dist2[row * k + j] = j < best.size() ? to_float_or_inf(best[j].first) : INFINITY;
      }
      out.counts[row] = static_cast<std::int32_t>(best.size());
    }
  }, 0, 1);
}

SearchParams Index::scaled(const SearchParams& p) const {
  SearchParams s = p;
  if (scale_exp_ != 0 && std::isfinite(p.max_radius)) s.max_radius = std::ldexp(p.max_radius, -scale_exp_);
  return s;
}

const float* Index::to_structure(const float* queries, std::size_t n, std::vector<float>& storage) const {
  if (scale_exp_ == 0) return queries;
  storage.resize(3 * n);
  ldexp_all(queries, storage.data(), 3 * n, -scale_exp_);
  return storage.data();
}

void Index::distances_to_caller(float* dist2, std::size_t count) const {
  if (scale_exp_ != 0) ldexp_all(dist2, dist2, count, 2 * scale_exp_);
}

cl::Event Index::enqueue_batch(const cl::CommandQueue&, const cl::Buffer&, std::size_t, std::size_t,
                               const ResultBuffers&, const SearchParams&, std::size_t,
                               const std::vector<cl::Event>*) const {
  throw Error(method() + ": no device kernel (a host method)");
}

double Index::host_search(const float*, std::size_t, const SearchParams&, KnnResult&) const {
  throw Error(method() + ": host_search is not implemented by this method");
}

void Index::check_params(const SearchParams& p) const {
  if (!answers_on_host()) refuse_in_forked_child(method());
  kmax_variant(p.k);  // throws for k outside [1, kMaxK]
  if (p.count_examined && !counts_examined())
    throw Error("count_examined: method " + method() + " does not count the points it examines");
  if (std::isnan(p.max_radius) || p.max_radius < 0)
    throw Error("max_radius must be >= 0 (or +inf), got " + std::to_string(p.max_radius));
  detail::parse_kernel_defines(p.kernel_defines);  // names the kernels read, values in range
  if (p.local_size > runtime_->info().max_work_group_size && runtime_->info().max_work_group_size)
    throw Error("local_size " + std::to_string(p.local_size) + " exceeds the device maximum " +
                std::to_string(runtime_->info().max_work_group_size));
}

std::size_t Index::local_size_for(const SearchParams& p) const {
  return p.local_size ? p.local_size : runtime_->quirks().default_local_size;
}

void Index::save(const std::string& path) const {
  throw Error("save " + path + ": method '" + method() + "' does not save its index (block hashing does)");
}

void Index::rebuild(const float*, std::size_t) {
  throw Error("rebuild: method '" + method() + "' has no rebuild in place (build a new index)");
}

double Index::warm_up(const SearchParams& params) const {
  ReadLock read_lock(*this);  // the launch reads the structure's buffers (see insert)
  check_params(params);
  if (answers_on_host()) return 0.0;
  std::size_t local = local_size_for(params);
  auto key = std::make_tuple(kmax_variant(params.k), local, params.kernel_defines);
  std::lock_guard<std::mutex> lock(warm_mutex_);
  if (warmed_.count(key)) return 0.0;
  auto t0 = std::chrono::steady_clock::now();
  // A zero-count launch compiles the program (clBuildProgram) and, on PoCL, the machine code for
  // this local size; kernels return at once for count 0.
  cl_int err = CL_SUCCESS;
  cl::Buffer q(runtime_->context(), CL_MEM_READ_WRITE, 16, nullptr, &err);
  check_cl(err, "clCreateBuffer", "warm-up");
  ResultBuffers rb;
  rb.ids = cl::Buffer(runtime_->context(), CL_MEM_READ_WRITE, 16, nullptr, &err);
  check_cl(err, "clCreateBuffer", "warm-up");
  rb.dist2 = cl::Buffer(runtime_->context(), CL_MEM_READ_WRITE, 16, nullptr, &err);
  check_cl(err, "clCreateBuffer", "warm-up");
  rb.counts = cl::Buffer(runtime_->context(), CL_MEM_READ_WRITE, 16, nullptr, &err);
  check_cl(err, "clCreateBuffer", "warm-up");
  rb.examined = cl::Buffer(runtime_->context(), CL_MEM_READ_WRITE, 16, nullptr, &err);
  check_cl(err, "clCreateBuffer", "warm-up");
  // On the library's own queue: the caller's queue may hold commands gated by a user event.
  cl::Event e = enqueue_batch(runtime_->warm_queue(), q, 0, 0, rb, params, local, nullptr);
  check_cl(e.wait(), "clWaitForEvents", method() + " warm-up");
  runtime_->keep_program_binaries();  // the launch compiled this local size: kept for later processes
  warmed_.insert(key);
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

cl::Event Index::enqueue_impl(const cl::CommandQueue& queue, const cl::Buffer& queries,
                              std::size_t n, const ResultBuffers& out, const SearchParams& params,
                              const std::vector<cl::Event>* wait, std::vector<cl::Event>* kernels,
                              double* compile_s) const {
  check_params(params);
  double c = warm_up(params);
  if (compile_s) *compile_s += c;
  std::size_t local = local_size_for(params);
  std::size_t per = params.max_batch ? params.max_batch : max_dispatch_queries();
  if (per > max_dispatch_queries()) per = max_dispatch_queries();
  per = std::max<std::size_t>(per, 1);
  // Every batch waits for the caller's list (an out-of-order queue would not order them after the
  // first), and more than one batch ends in a marker on all of them, so the event returned means
  // "every row written" on any queue.
  std::vector<cl::Event> batches;
  for (std::size_t first = 0; first < n; first += per) {
    std::size_t count = std::min(per, n - first);
    batches.push_back(enqueue_batch(queue, queries, first, count, out, params, local, wait));
    if (kernels) kernels->push_back(batches.back());
  }
  if (batches.size() == 1) return batches.front();
  cl::Event all;
  check_cl(queue.enqueueMarkerWithWaitList(&batches, &all), "clEnqueueMarkerWithWaitList", method());
  return all;
}

cl::Event Index::enqueue_query(const cl::CommandQueue& queue, const cl::Buffer& queries,
                               std::size_t n, const ResultBuffers& out,
                               const SearchParams& params,
                               const std::vector<cl::Event>* wait) const {
  ReadLock lock(*this);  // kernels enqueued with the structure's buffers (see insert)
  check_params(params);
  // Buffers too small for n queries would be written out of bounds: refuse.
  auto need = [&](const cl::Buffer& b, std::size_t bytes, const char* what) {
    std::size_t have = 0;
    check_cl(b.getInfo(CL_MEM_SIZE, &have), "clGetMemObjectInfo", what);
    if (have < bytes)
      throw Error(std::string(what) + " buffer holds " + std::to_string(have) + " bytes, " +
                  std::to_string(bytes) + " needed for " + std::to_string(n) + " queries, k = " +
                  std::to_string(params.k));
  };
  if (n == 0) throw Error("enqueue_query: no queries (n = 0)");
  const std::size_t nk = n * static_cast<std::size_t>(params.k);
  const std::size_t top = std::numeric_limits<std::size_t>::max();
  if (n > top / 12 || nk / static_cast<std::size_t>(params.k) != n || nk > top / 4)
    throw Error("enqueue_query: n = " + std::to_string(n) + " queries x k = " +
                std::to_string(params.k) + " overflows the size type (refused, not wrapped)");
  need(queries, n * 3 * sizeof(float), "queries");
  need(out.ids, nk * sizeof(std::int32_t), "ids");
  need(out.dist2, nk * sizeof(float), "dist2");
  need(out.counts, n * sizeof(std::int32_t), "counts");
  if (params.count_examined) need(out.examined, n * sizeof(std::int32_t), "examined");
  const SearchParams sp = scaled(params);
  const cl::Context ctx = queue.getInfo<CL_QUEUE_CONTEXT>();
  cl_int err = CL_SUCCESS;
  if (answers_on_host()) {
    // Honest but blocking: read the queries, answer on the host, write the rows back.
    std::vector<float> q(n * 3);
    check_cl(queue.enqueueReadBuffer(queries, CL_TRUE, 0, q.size() * sizeof(float), q.data(), wait),
             "clEnqueueReadBuffer", method() + " queries");
    KnnResult r;
    r.resize(n, params.k);
    const std::vector<float> caller_q = scale_exp_ ? q : std::vector<float>();
    if (scale_exp_)
      ldexp_all(q.data(), q.data(), q.size(), -scale_exp_);
    host_search(q.data(), n, sp, r);
    const float* cq = scale_exp_ ? caller_q.data() : q.data();
    std::vector<std::size_t> suspects;
    collect_suspect_rows(cq, 0, n, detail::squared_radius(sp.max_radius), r, suspects);
    if (scale_exp_)
      ldexp_all(r.dist2.data(), r.dist2.data(), r.dist2.size(), 2 * scale_exp_);
    answer_rows_exactly(cq, suspects, params, r);
    cl::Event e;
    check_cl(queue.enqueueWriteBuffer(out.ids, CL_TRUE, 0, nk * 4, r.ids.data()), "clEnqueueWriteBuffer", "ids");
    check_cl(queue.enqueueWriteBuffer(out.dist2, CL_TRUE, 0, nk * 4, r.dist2.data()), "clEnqueueWriteBuffer", "dist2");
    check_cl(queue.enqueueWriteBuffer(out.counts, CL_TRUE, 0, n * 4, r.counts.data(), nullptr, &e),
             "clEnqueueWriteBuffer", "counts");
    return e;
  }
  if (scale_exp_ == 0) return enqueue_impl(queue, queries, n, out, sp, wait, nullptr, nullptr);
  // Extreme scales: scale a copy of the queries, answer, scale the distances back.
  cl::Buffer scaled_q(ctx, CL_MEM_READ_WRITE, n * 3 * sizeof(float), nullptr, &err);
  check_cl(err, "clCreateBuffer", "scaled queries");
  const std::size_t local = local_size_for(params);
  cl::Kernel copy = runtime_->kernel("scale.cl", "bhcl_scale_copy");
  detail::KernelArgs(copy, "bhcl_scale_copy").add(queries).add(scaled_q).add(cl_ulong(n * 3)).add(cl_int(-scale_exp_));
  cl::Event e0 = detail::launch_1d(queue, copy, n * 3, local, wait, "bhcl_scale_copy");
  std::vector<cl::Event> w0{e0};
  cl::Event e1 = enqueue_impl(queue, scaled_q, n, out, sp, &w0, nullptr, nullptr);
  cl::Kernel back = runtime_->kernel("scale.cl", "bhcl_scale_in_place");
  detail::KernelArgs(back, "bhcl_scale_in_place").add(out.dist2).add(cl_ulong(nk)).add(cl_int(2 * scale_exp_));
  std::vector<cl::Event> w1{e1};
  return detail::launch_1d(queue, back, nk, local, &w1, "bhcl_scale_in_place");
}

namespace {
double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}
}  // namespace

QueryStats Index::query(const float* queries, std::size_t n, const SearchParams& params,
                        KnnResult& out) const {
  auto t0 = std::chrono::steady_clock::now();
  ReadLock lock(*this);  // queries share the index; insert/remove wait (see insert)
  check_params(params);
  const bool sort = params.sort_queries > 0 || (params.sort_queries < 0 && n >= kAutoSortQueries);
  // Sizes before allocation: a result that cannot fit is refused with what it needs, before any
  // search (the Hilbert-ordered path holds the rows twice: the caller's and the device's).
  check_result_memory(n, params.k, params.count_examined, sort && n > 1 ? 2 : 1, method());
  if (answers_on_host()) return query_host_method(queries, n, params, out, sort, t0);
  QueryStats st;
  st.n_queries = n;
  // Dispatch in Hilbert order (neighbouring work-items walk the same cells), rows written in the
  // caller's order as they come off the device: no second pass over the result.
  std::vector<std::size_t> order;
  if (sort && n > 1) {
    const auto ts = std::chrono::steady_clock::now();
    order = detail::hilbert_query_order(queries, n);
    st.sort_s = seconds_since(ts);
  }
  for (std::size_t i = 0; i < n; ++i) {
    const float* q = queries + 3 * i;
    if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) ++st.nonfinite_queries;
  }
  // Every row is written by the scatter below: sized, not filled (a filled result is a pass of
  // its own; a result reused from the caller's last call costs nothing here).
  const std::size_t k = static_cast<std::size_t>(params.k);
  out.n = n;
  out.k = params.k;
  out.ids.resize(n * k);
  out.dist2.resize(n * k);
  out.counts.resize(n);
  if (params.count_examined) out.examined.resize(n);
  else out.examined.clear();
  if (n > 0) query_on_device(queries, n, order.empty() ? nullptr : order.data(), params, out, st);
  st.wall_s = seconds_since(t0);
  return st;
}

namespace {
// Host buffers a CPU device reads and writes in place (zero-copy: PoCL's kernels use the host
// memory itself); a GPU gets device memory and copies.
cl::Buffer io_buffer(const Runtime& rt, bool host_visible, std::size_t bytes, const char* what) {
  if (!host_visible) return detail::device_buffer(rt, bytes, what);
  cl_int err = CL_SUCCESS;
  cl::Buffer b(rt.context(), CL_MEM_READ_WRITE | CL_MEM_ALLOC_HOST_PTR, std::max<std::size_t>(bytes, 4), nullptr, &err);
  check_cl(err, "clCreateBuffer", std::string(what) + " (host memory), " + std::to_string(bytes) + " bytes");
  return b;
}

// A mapped region of a buffer, unmapped when done (also on an exception).
class Mapped {
 public:
  Mapped(const cl::CommandQueue& q, const cl::Buffer& b, cl_map_flags flags, std::size_t bytes, const char* what)
      : q_(q), b_(b) {
    cl_int err = CL_SUCCESS;
    ptr_ = q.enqueueMapBuffer(b, CL_TRUE, flags, 0, std::max<std::size_t>(bytes, 4), nullptr, nullptr, &err);
    check_cl(err, "clEnqueueMapBuffer", what);
  }
  ~Mapped() {
    if (ptr_) q_.enqueueUnmapMemObject(b_, ptr_);
  }
  Mapped(const Mapped&) = delete;
  Mapped& operator=(const Mapped&) = delete;
  void unmap(const char* what) {
    cl::Event e;
    check_cl(q_.enqueueUnmapMemObject(b_, ptr_, nullptr, &e), "clEnqueueUnmapMemObject", what);
    ptr_ = nullptr;
  }
  template <typename T>
  T* as() const { return static_cast<T*>(ptr_); }

 private:
  const cl::CommandQueue& q_;
  const cl::Buffer& b_;
  void* ptr_ = nullptr;
};
}  // namespace

void Index::take_query_buffers(std::size_t rows, std::size_t k, bool examined, QueryBuffers& b) const {
  {
    std::lock_guard<std::mutex> lock(io_mutex_);
    if (io_cache_.rows >= rows && io_cache_.k == k && (io_cache_.examined() || !examined)) {
      b = std::move(io_cache_);
      io_cache_ = QueryBuffers{};
      return;
    }
  }
  const Runtime& rt = *runtime_;
  b.host = (rt.info().type & CL_DEVICE_TYPE_CPU) != 0;
  b.rows = rows;
  b.k = k;
  b.q = io_buffer(rt, b.host, rows * 3 * sizeof(float), "queries");
  b.ids = io_buffer(rt, b.host, rows * k * sizeof(std::int32_t), "ids");
  b.dist2 = io_buffer(rt, b.host, rows * k * sizeof(float), "dist2");
  b.counts = io_buffer(rt, b.host, rows * sizeof(std::int32_t), "counts");
  if (examined) b.examined_buf = io_buffer(rt, b.host, rows * sizeof(std::int32_t), "examined");
}

void Index::give_back_query_buffers(QueryBuffers&& b) const {
  // Kept for the next call (its pages are mapped already: fresh ones fault on every 4 KiB),
  // up to the bound on scratch memory.
  if (b.rows * (8 * b.k + 20) > kSortScratchBytes) return;
  std::lock_guard<std::mutex> lock(io_mutex_);
  if (b.rows >= io_cache_.rows) io_cache_ = std::move(b);
}

void Index::query_on_device(const float* caller_queries, std::size_t n, const std::size_t* order,
                            const SearchParams& params, KnnResult& out, QueryStats& st) const {
  const Runtime& rt = *runtime_;
  const cl::CommandQueue& queue = rt.queue();
  const std::size_t k = static_cast<std::size_t>(params.k);
  const SearchParams sp = scaled(params);
  const float r2s = detail::squared_radius(sp.max_radius);
  const bool check = exact() && !caller_points_.empty();
  const bool tiny_radius = r2s > 0 && r2s < kTrustedMin;
  const int full = static_cast<int>(std::min<std::size_t>(k, size()));
  // Host chunks bound the device memory of one call: results are 8*k bytes per query.
  std::size_t chunk = std::max<std::size_t>(1, (std::size_t(256) << 20) / (8 * k + 12));
  if (rt.info().max_alloc_bytes)
    chunk = std::min<std::size_t>(chunk, std::max<std::size_t>(1, rt.info().max_alloc_bytes / (4 * k)));
  chunk = std::min(chunk, n);
  QueryBuffers b;
  take_query_buffers(chunk, k, params.count_examined, b);
  ResultBuffers rb{b.ids, b.dist2, b.counts};
  if (params.count_examined) rb.examined = b.examined_buf;
  std::vector<float> qstage;  // device memory only: the gathered queries before their copy
  std::vector<std::int32_t> ids_stage, counts_stage, examined_stage;
  std::vector<float> dist2_stage;
  std::vector<std::size_t> suspects;
  std::mutex suspects_mutex;
  for (std::size_t first = 0; first < n; first += chunk) {
    const std::size_t m = std::min(chunk, n - first);
    const auto src = [&](std::size_t i) { return order ? order[first + i] : first + i; };
    // Upload, fused with the sort: each query gathered from the caller's array in dispatch order
    // (and scaled, at extreme scales) straight into the buffer the kernel reads.
    auto tu = std::chrono::steady_clock::now();
    {
      std::unique_ptr<Mapped> map;
      float* dst;
      if (b.host) {
        map = std::make_unique<Mapped>(queue, b.q, CL_MAP_WRITE_INVALIDATE_REGION, m * 3 * sizeof(float), "queries");
        dst = map->as<float>();
      } else {
        qstage.resize(3 * m);
        dst = qstage.data();
      }
      detail::parallel_for(m, [&](std::size_t lo, std::size_t hi) {
        for (std::size_t i = lo; i < hi; ++i) {
          const float* q = caller_queries + 3 * src(i);
          for (int d = 0; d < 3; ++d) dst[3 * i + d] = scale_exp_ ? std::ldexp(q[d], -scale_exp_) : q[d];
        }
      }, 0, 16384);
      if (map) map->unmap("queries");
      else check_cl(queue.enqueueWriteBuffer(b.q, CL_FALSE, 0, m * 3 * sizeof(float), dst), "clEnqueueWriteBuffer", "queries");
    }
    st.upload_s += seconds_since(tu);
    std::vector<cl::Event> kernels;
    enqueue_impl(queue, b.q, m, rb, sp, nullptr, &kernels, &st.compile_s);
    check_cl(queue.finish(), "clFinish", method() + " query");
    for (const auto& e : kernels) st.query_s += event_seconds(e);
    st.batches += kernels.size();
    // Download: mapped in place on a CPU device (no copy), read on a GPU.
    auto td = std::chrono::steady_clock::now();
    std::unique_ptr<Mapped> mids, mdist2, mcounts, mexam;
    const std::int32_t *ids, *counts, *exam = nullptr;
    const float* dist2;
    if (b.host) {
      mids = std::make_unique<Mapped>(queue, b.ids, CL_MAP_READ, m * k * 4, "ids");
      mdist2 = std::make_unique<Mapped>(queue, b.dist2, CL_MAP_READ, m * k * 4, "dist2");
      mcounts = std::make_unique<Mapped>(queue, b.counts, CL_MAP_READ, m * 4, "counts");
      if (params.count_examined) mexam = std::make_unique<Mapped>(queue, b.examined_buf, CL_MAP_READ, m * 4, "examined");
      ids = mids->as<std::int32_t>();
      dist2 = mdist2->as<float>();
      counts = mcounts->as<std::int32_t>();
      if (mexam) exam = mexam->as<std::int32_t>();
    } else {
      ids_stage.resize(m * k);
      dist2_stage.resize(m * k);
      counts_stage.resize(m);
      check_cl(queue.enqueueReadBuffer(b.ids, CL_FALSE, 0, m * k * 4, ids_stage.data()), "clEnqueueReadBuffer", "ids");
      check_cl(queue.enqueueReadBuffer(b.dist2, CL_FALSE, 0, m * k * 4, dist2_stage.data()), "clEnqueueReadBuffer", "dist2");
      check_cl(queue.enqueueReadBuffer(b.counts, CL_FALSE, 0, m * 4, counts_stage.data()), "clEnqueueReadBuffer", "counts");
      if (params.count_examined) {
        examined_stage.resize(m);
        check_cl(queue.enqueueReadBuffer(b.examined_buf, CL_FALSE, 0, m * 4, examined_stage.data()),
                 "clEnqueueReadBuffer", "examined");
        exam = examined_stage.data();
      }
      check_cl(queue.finish(), "clFinish", method() + " results");
      ids = ids_stage.data();
      dist2 = dist2_stage.data();
      counts = counts_stage.data();
    }
    st.download_s += seconds_since(td);
    // Unsort: each row to the caller's place, its distances back to the caller's scale, and the
    // rows the float search cannot vouch for noted, in one parallel pass.
    auto tw = std::chrono::steady_clock::now();
    detail::parallel_for(m, [&](std::size_t lo, std::size_t hi) {
      std::vector<std::size_t> mine;
      for (std::size_t i = lo; i < hi; ++i) {
        const std::size_t row = src(i);
        const std::int32_t* ri = ids + i * k;
        const float* rd = dist2 + i * k;
        const int c = counts[i];
        if (check) {
          const float* q = caller_queries + 3 * row;
          if (std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2])) {
            bool bad = tiny_radius || (std::isinf(r2s) && c < full);
            for (int j = 0; j < c && !bad; ++j) bad = entry_suspect(q, ri[j], rd[j]);
            if (bad) mine.push_back(row);
          }
        }
        std::copy_n(ri, k, &out.ids[row * k]);
        if (scale_exp_) {
          for (std::size_t j = 0; j < k; ++j) out.dist2[row * k + j] = std::ldexp(rd[j], 2 * scale_exp_);
        } else {
          std::copy_n(rd, k, &out.dist2[row * k]);
        }
        out.counts[row] = c;
        if (exam) out.examined[row] = exam[i];
      }
      if (!mine.empty()) {
        std::lock_guard<std::mutex> lock(suspects_mutex);
        suspects.insert(suspects.end(), mine.begin(), mine.end());
      }
    }, 0, 8192);
    st.unsort_s += seconds_since(tw);
  }
  // The last chunk's unmaps done before its buffers serve another call.
  check_cl(queue.finish(), "clFinish", method() + " query");
  give_back_query_buffers(std::move(b));
  // The threads' lists in row order: the answers do not depend on the thread count.
  std::sort(suspects.begin(), suspects.end());
  answer_rows_exactly(caller_queries, suspects, params, out);
}

QueryStats Index::query_host_method(const float* queries, std::size_t n, const SearchParams& params,
                                    KnnResult& out, bool sort,
                                    std::chrono::steady_clock::time_point t0) const {
  if (sort && n > 1) {
    // Dispatch in Hilbert order, return rows in the caller's order.
    const auto ts = std::chrono::steady_clock::now();
    std::vector<std::size_t> order = detail::hilbert_query_order(queries, n);
    const double sort_s = seconds_since(ts);
    const std::vector<float> sorted = detail::queries_in_order(queries, order);
    SearchParams p = params;
    p.sort_queries = 0;
    // The rows in dispatch order, in arrays this thread keeps from call to call: fresh ones cost
    // a page fault per 4 KiB (8 k bytes per query) on every call, more than the copy itself.
    // (A reference: the copy below runs on other threads, where the name would mean their own.)
    thread_local KnnResult rows;
    KnnResult& tmp = rows;
    out.resize(n, params.k);  // before the search: a result that cannot be held fails first
    QueryStats st = query(sorted.data(), n, p, tmp);
    st.sort_s = sort_s;
    const auto tu = std::chrono::steady_clock::now();
    const std::size_t k = static_cast<std::size_t>(params.k);
    detail::parallel_for(n, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) {
        std::copy_n(&tmp.ids[i * k], k, &out.ids[order[i] * k]);
        std::copy_n(&tmp.dist2[i * k], k, &out.dist2[order[i] * k]);
        out.counts[order[i]] = tmp.counts[i];
      }
    });
    if (params.count_examined) {
      out.examined.resize(n);
      for (std::size_t i = 0; i < n; ++i) out.examined[order[i]] = tmp.examined[i];
    }
    if (tmp.ids.capacity() * 8 > kSortScratchBytes) tmp = KnnResult{};  // kept only up to the bound
    st.unsort_s = seconds_since(tu);
    st.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return st;
  }
  QueryStats st;
  st.n_queries = n;
  out.resize(n, params.k);
  if (params.count_examined) out.examined.assign(n, 0);
  if (n == 0) return st;
  for (std::size_t i = 0; i < n; ++i) {
    const float* q = queries + 3 * i;
    if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) ++st.nonfinite_queries;
  }
  const SearchParams sp = scaled(params);
  // Exact methods: rows the float search cannot vouch for, answered again in double at the end.
  const float* caller_queries = queries;
  const float r2s = detail::squared_radius(sp.max_radius);
  std::vector<std::size_t> suspects;
  // Queries in the structure's coordinates: the caller's, or a scaled copy (extreme scales).
  std::vector<float> scaled_queries;
  if (scale_exp_ != 0) {
    scaled_queries.resize(3 * n);
    ldexp_all(queries, scaled_queries.data(), 3 * n, -scale_exp_);
    queries = scaled_queries.data();
  }
  auto unscale = [&](float* d2, std::size_t count) {
    if (scale_exp_ != 0)
      ldexp_all(d2, d2, count, 2 * scale_exp_);
  };
  st.query_s = host_search(queries, n, sp, out);
  collect_suspect_rows(caller_queries, 0, n, r2s, out, suspects);
  unscale(out.dist2.data(), out.dist2.size());
  answer_rows_exactly(caller_queries, suspects, params, out);
  st.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return st;
}

KnnResult Index::query(const std::vector<float>& queries, const SearchParams& params,
                       QueryStats* stats) const {
  if (queries.size() % 3 != 0)
    throw Error("queries: array of " + std::to_string(queries.size()) +
                " floats is not a multiple of 3 (x y z per query)");
  KnnResult r;
  QueryStats st = query(queries.data(), queries.size() / 3, params, r);
  if (stats) *stats = st;
  return r;
}

}  // namespace bhcl
