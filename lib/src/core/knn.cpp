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
#include "core/query_pipeline.hpp"

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
    // Room for as many points again (address space: a page is faulted in only when an insert
    // writes it): inserts append instead of moving every row (issue 39: a 25 % insert's move
    // faulted in fresh pages and cost 1.2-1.4x a fresh build of brute force).
    caller_points_.reserve(6 * n);
    caller_points_.assign(points, points + 3 * n);
  }
  scale_exp_ = scale_exponent_of(box, points, n);
  if (scale_exp_ == 0) return points;
  storage.resize(3 * n);
  ldexp_all(points, storage.data(), 3 * n, -scale_exp_);
  return storage.data();
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

std::size_t Index::default_local_size() const { return runtime_->quirks().default_local_size; }

std::size_t Index::local_size_for(const DispatchParams& p) const {
  return p.local_size ? p.local_size : default_local_size();
}

void Index::save(const std::string& path) const {
  throw Error("save " + path + ": method '" + method() + "' does not save its index (block hashing does)");
}

void Index::rebuild(const float*, std::size_t) {
  throw Error("rebuild: method '" + method() + "' has no rebuild in place (build a new index)");
}

std::size_t Index::queries_per_launch(std::size_t max_batch, std::size_t local) const {
  const std::size_t per = max_batch ? std::min(max_batch, max_dispatch_queries()) : max_dispatch_queries();
  return detail::items_per_launch(per, local, runtime_->quirks().max_launch_items);
}

cl::Event Index::enqueue_impl(const cl::CommandQueue& queue, const cl::Buffer& queries,
                              std::size_t n, const ResultBuffers& out, const SearchParams& params,
                              const std::vector<cl::Event>* wait, std::vector<cl::Event>* kernels,
                              double* compile_s) const {
  check_params(params);
  double c = warm_up(params);
  if (compile_s) *compile_s += c;
  std::size_t local = local_size_for(params);
  const std::size_t per = queries_per_launch(params.max_batch, local);
  // Every batch waits for the caller's list (an out-of-order queue would not order them after the
  // first), and more than one batch ends in a marker on all of them, so the event returned means
  // "every row written" on any queue.
  std::vector<cl::Event> batches;
  for (std::size_t first = 0; first < n; first += per) {
    std::size_t count = std::min(per, n - first);
    batches.push_back(enqueue_batch(queue, queries, first, count, out, params, local, wait));
    if (kernels) kernels->push_back(batches.back());
  }
  return detail::one_event(queue, batches, method());
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
    // Honest but blocking: read the queries, answer them as the host-array call does, write the rows back.
    std::vector<float> q(n * 3);
    check_cl(queue.enqueueReadBuffer(queries, CL_TRUE, 0, q.size() * sizeof(float), q.data(), wait),
             "clEnqueueReadBuffer", method() + " queries");
    KnnResult r;
    query(q.data(), n, params, r);
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
  const std::size_t limit = runtime_->quirks().max_launch_items;
  detail::KernelArgs(copy, "bhcl_scale_copy").add(queries).add(scaled_q).add(cl_ulong(n * 3)).add(cl_int(-scale_exp_));
  cl::Event e0 = detail::launch_1d_split(queue, copy, 4, n * 3, local, limit, wait, "bhcl_scale_copy");
  std::vector<cl::Event> w0{e0};
  cl::Event e1 = enqueue_impl(queue, scaled_q, n, out, sp, &w0, nullptr, nullptr);
  cl::Kernel back = runtime_->kernel("scale.cl", "bhcl_scale_in_place");
  detail::KernelArgs(back, "bhcl_scale_in_place").add(out.dist2).add(cl_ulong(nk)).add(cl_int(2 * scale_exp_));
  std::vector<cl::Event> w1{e1};
  return detail::launch_1d_split(queue, back, 3, nk, local, limit, &w1, "bhcl_scale_in_place");
}

// The kNN kind of query (query_pipeline.hpp): rows of k, one pass. On a device that uses host
// memory in place (a CPU) the kernel writes each row straight to the caller's row (the dispatch
// order travels with the queries, QueryBuffers::result_rows), so nothing moves rows after it;
// elsewhere (a GPU) each chunk's rows are copied to the caller's places as they come off it.
class Index::KnnKind final : public Index::QueryKind {
 public:
  // Into a KnnResult (resized in begin), or (res null) into the caller's memory `view`.
  KnnKind(const Index& ix, const SearchParams& p, KnnResult* res, const KnnRowsView& view = {})
      : QueryKind(ix), p_(p), sp_(ix.scaled(p)), res_(res), v_(view), k_(static_cast<std::size_t>(p.k)),
        r2s_(detail::squared_radius(sp_.max_radius)) {}
  const char* name() const override { return "query"; }
  const DispatchParams& dispatch() const override { return p_; }
  std::size_t row_k() const override { return k_; }
  int kernel_variant() const override { return kmax_variant(p_.k); }
  void check(std::size_t n, int copies) const override {
    ix_.check_params(p_);
    if (!res_ && n > 0 && (!v_.ids || !v_.dist2 || !v_.counts || (p_.count_examined && !v_.examined)))
      throw Error("query_into: a null output array in the view (ids, dist2, counts" +
                  std::string(p_.count_examined ? ", examined" : "") + ") for " + std::to_string(n) + " queries");
    check_result_memory(n, p_.k, p_.count_examined, res_ ? copies : copies - 1, ix_.method());
  }
  void begin(std::size_t n) override;
  std::size_t chunk_rows(std::size_t n) const override;
  void warm_launch(const QueryBuffers& b, std::size_t local) const override {
    // On the library's own queue: the caller's queue may hold commands gated by a user event.
    const ResultBuffers rb(b.ids, b.dist2, b.counts, b.examined_buf);
    cl::Event e = ix_.enqueue_batch(ix_.runtime_->warm_queue(), b.q, 0, 0, rb, p_, local, nullptr);
    check_cl(e.wait(), "clWaitForEvents", ix_.method() + " warm-up");
  }
  void search_chunk(QueryBuffers& b, std::size_t first, std::size_t m, const std::size_t* order, std::size_t per,
                    std::size_t local, const float* caller_queries, QueryStats& st,
                    std::vector<std::size_t>& suspects) override;
  void search_host(const float* queries, std::size_t n, const std::size_t* order, const float* caller_queries,
                   QueryStats& st, std::vector<std::size_t>& suspects) override;
  void finish(const std::size_t*, const float*, QueryStats&, std::vector<std::size_t>&) override;
  void answer_exactly(const float* caller_queries, const std::vector<std::size_t>& rows) override;

 private:
  // Rows [first, first + m) of the dispatch order (ids/dist2 m x k, the structure's distances)
  // to the caller's places, distances to the caller's scale, suspect rows noted: one parallel pass.
  void store_rows(std::size_t first, std::size_t m, const std::size_t* order, const std::int32_t* ids,
                  const float* dist2, const std::int32_t* counts, const std::int32_t* exam,
                  const float* caller_queries, std::vector<std::size_t>& suspects);
  // The caller's rows written in place by the kernel: to the caller's scale, suspect rows noted.
  void check_rows_in_place(const float* caller_queries, std::vector<std::size_t>& suspects);
  bool row_suspect(const float* q, const std::int32_t* ids, const float* d, int count) const;
  void wrap_caller_rows();
  void point_view_at_result();

  const SearchParams& p_;
  const SearchParams sp_;  // in the structure's coordinates
  KnnResult* res_;
  KnnRowsView v_;  // where the rows go: res_'s arrays once begin sized them, or the caller's
  const std::size_t k_;
  const float r2s_;
  std::size_t n_ = 0;
  ResultBuffers in_place_;  // the caller's rows as buffers (USE_HOST_PTR) while the kernels write them
};

void Index::KnnKind::point_view_at_result() {
  v_ = {res_->ids.data(), res_->dist2.data(), res_->counts.data(),
        p_.count_examined ? res_->examined.data() : nullptr};
}

void Index::KnnKind::begin(std::size_t n) {
  n_ = n;
  if (!res_) return;  // the caller's memory, written entry by entry
  if (ix_.answers_on_host()) {
    res_->resize(n, p_.k);  // host methods fill rows they are given
    if (p_.count_examined) res_->examined.assign(n, 0);
    return point_view_at_result();
  }
  // Every row is written by the kernel or the scatter: sized, not filled (a filled result is a
  // pass of its own; a result reused from the caller's last call costs nothing here).
  res_->n = n;
  res_->k = p_.k;
  res_->ids.resize(n * k_);
  res_->dist2.resize(n * k_);
  res_->counts.resize(n);
  if (p_.count_examined) res_->examined.resize(n);
  else res_->examined.clear();
  point_view_at_result();
}

std::size_t Index::KnnKind::chunk_rows(std::size_t n) const {
  // Results are 8*k bytes per query: host chunks bound the device memory of one call.
  std::size_t chunk = std::max<std::size_t>(1, (std::size_t(256) << 20) / (8 * k_ + 12));
  const std::size_t max_alloc = ix_.runtime_->info().max_alloc_bytes;
  if (max_alloc) chunk = std::min<std::size_t>(chunk, std::max<std::size_t>(1, max_alloc / (4 * k_)));
  return std::min(chunk, n);
}

bool Index::KnnKind::row_suspect(const float* q, const std::int32_t* ids, const float* d, int count) const {
  if (!detail::finite_query(q)) return false;  // an empty row, as the contract says
  const int full = static_cast<int>(std::min<std::size_t>(k_, ix_.size()));
  static const float tiny = detail::trusted_min_distance();
  if ((r2s_ > 0 && r2s_ < tiny) || (std::isinf(r2s_) && count < full)) return true;
  // Almost every row: each distance in [tiny, inf), which no entry_suspect case holds (a
  // branch-free test over the row, then the cases only where it fails).
  bool plain = true;
  for (int j = 0; j < count; ++j) plain &= (d[j] >= tiny) & (d[j] < INFINITY);
  if (plain) return false;
  for (int j = 0; j < count; ++j)
    if (entry_suspect(q, ids[j], d[j])) return true;
  return false;
}

void Index::KnnKind::store_rows(std::size_t first, std::size_t m, const std::size_t* order, const std::int32_t* ids,
                                const float* dist2, const std::int32_t* counts, const std::int32_t* exam,
                                const float* caller_queries, std::vector<std::size_t>& suspects) {
  const bool check = checks_rows();
  const int e = scale_exponent();
  std::mutex suspects_mutex;
  detail::parallel_for(m, [&](std::size_t lo, std::size_t hi) {
    std::vector<std::size_t> mine;
    for (std::size_t i = lo; i < hi; ++i) {
      const std::size_t row = order ? order[first + i] : first + i;
      const std::int32_t* ri = ids + i * k_;
      const float* rd = dist2 + i * k_;
      if (check && row_suspect(caller_queries + 3 * row, ri, rd, counts[i])) mine.push_back(row);
      float* od = v_.dist2 + row * k_;
      if (ri != v_.ids + row * k_) std::copy_n(ri, k_, v_.ids + row * k_);  // in place: the host's rows
      if (e) {
        for (std::size_t j = 0; j < k_; ++j) od[j] = std::ldexp(rd[j], 2 * e);
      } else if (rd != od) {
        std::copy_n(rd, k_, od);
      }
      v_.counts[row] = counts[i];
      if (exam) v_.examined[row] = exam[i];
    }
    if (!mine.empty()) {
      std::lock_guard<std::mutex> lock(suspects_mutex);
      suspects.insert(suspects.end(), mine.begin(), mine.end());
    }
  }, 0, 8192);
}

void Index::KnnKind::check_rows_in_place(const float* caller_queries, std::vector<std::size_t>& suspects) {
  const bool check = checks_rows();
  const int e = scale_exponent();
  if (!check && !e) return;  // nothing to read: the rows are final as the kernel wrote them
  std::mutex suspects_mutex;
  detail::parallel_for(n_, [&](std::size_t lo, std::size_t hi) {
    std::vector<std::size_t> mine;
    for (std::size_t row = lo; row < hi; ++row) {
      float* rd = v_.dist2 + row * k_;
      if (check && row_suspect(caller_queries + 3 * row, v_.ids + row * k_, rd, v_.counts[row])) mine.push_back(row);
      if (e)
        for (std::size_t j = 0; j < k_; ++j) rd[j] = std::ldexp(rd[j], 2 * e);
    }
    if (!mine.empty()) {
      std::lock_guard<std::mutex> lock(suspects_mutex);
      suspects.insert(suspects.end(), mine.begin(), mine.end());
    }
  }, 0, 8192);
}

namespace {
// A chunk's rows off the device: mapped in place on a CPU device (no copy), read on a GPU.
struct DownloadedRows {
  std::unique_ptr<detail::Mapped> mids, mdist2, mcounts, mexam;
  std::vector<std::int32_t> ids_stage, counts_stage, exam_stage;
  std::vector<float> dist2_stage;
  const std::int32_t *ids = nullptr, *counts = nullptr, *exam = nullptr;
  const float* dist2 = nullptr;

  // The maps enqueued without a wait each: valid after the next wait on the queue (`wait`: here).
  void map(const cl::CommandQueue& q, const ResultBuffers& rb, std::size_t m, std::size_t k, bool examined,
           cl_map_flags flags = CL_MAP_READ, bool wait = true) {
    mids = std::make_unique<detail::Mapped>(q, rb.ids, flags, m * k * 4, "ids", false);
    mdist2 = std::make_unique<detail::Mapped>(q, rb.dist2, flags, m * k * 4, "dist2", false);
    mcounts = std::make_unique<detail::Mapped>(q, rb.counts, flags, m * 4, "counts", false);
    if (examined) mexam = std::make_unique<detail::Mapped>(q, rb.examined, flags, m * 4, "examined", false);
    if (wait) check_cl(q.finish(), "clFinish", "kNN rows mapped");
    ids = mids->as<std::int32_t>();
    dist2 = mdist2->as<float>();
    counts = mcounts->as<std::int32_t>();
    if (mexam) exam = mexam->as<std::int32_t>();
  }
  void read(const cl::CommandQueue& q, const ResultBuffers& rb, std::size_t m, std::size_t k, bool examined) {
    ids_stage.resize(m * k);
    dist2_stage.resize(m * k);
    counts_stage.resize(m);
    check_cl(q.enqueueReadBuffer(rb.ids, CL_FALSE, 0, m * k * 4, ids_stage.data()), "clEnqueueReadBuffer", "ids");
    check_cl(q.enqueueReadBuffer(rb.dist2, CL_FALSE, 0, m * k * 4, dist2_stage.data()), "clEnqueueReadBuffer", "dist2");
    check_cl(q.enqueueReadBuffer(rb.counts, CL_FALSE, 0, m * 4, counts_stage.data()), "clEnqueueReadBuffer", "counts");
    if (examined) {
      exam_stage.resize(m);
      check_cl(q.enqueueReadBuffer(rb.examined, CL_FALSE, 0, m * 4, exam_stage.data()), "clEnqueueReadBuffer", "examined");
      exam = exam_stage.data();
    }
    check_cl(q.finish(), "clFinish", "kNN results");
    ids = ids_stage.data();
    dist2 = dist2_stage.data();
    counts = counts_stage.data();
  }
};

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Caller memory as a buffer the device uses in place (CL_MEM_USE_HOST_PTR on a host-memory device).
cl::Buffer caller_buffer(const cl::Context& ctx, void* p, std::size_t bytes, const char* what) {
  cl_int err = CL_SUCCESS;
  cl::Buffer b(ctx, CL_MEM_READ_WRITE | CL_MEM_USE_HOST_PTR, bytes, p, &err);
  check_cl(err, "clCreateBuffer", std::string(what) + " (the caller's rows), " + std::to_string(bytes) + " bytes");
  return b;
}
}  // namespace

void Index::KnnKind::wrap_caller_rows() {
  const cl::Context& ctx = ix_.runtime_->context();
  in_place_.ids = caller_buffer(ctx, v_.ids, n_ * k_ * 4, "ids");
  in_place_.dist2 = caller_buffer(ctx, v_.dist2, n_ * k_ * 4, "dist2");
  in_place_.counts = caller_buffer(ctx, v_.counts, n_ * 4, "counts");
  if (p_.count_examined) in_place_.examined = caller_buffer(ctx, v_.examined, n_ * 4, "examined");
}

void Index::KnnKind::search_chunk(QueryBuffers& b, std::size_t first, std::size_t m, const std::size_t* order,
                                  std::size_t per, std::size_t local, const float* caller_queries, QueryStats& st,
                                  std::vector<std::size_t>& suspects) {
  const cl::CommandQueue& queue = ix_.runtime_->queue();
  const bool in_place = b.writes_caller_rows(n_);
  ResultBuffers rb{b.ids, b.dist2, b.counts};
  if (p_.count_examined) rb.examined = b.examined_buf;
  if (in_place) {
    if (!in_place_.ids()) wrap_caller_rows();
    rb = in_place_;
    rb.rows = b.result_rows;
  }
  std::vector<cl::Event> kernels;
  for (std::size_t f = 0; f < m; f += per)
    kernels.push_back(ix_.enqueue_batch(queue, b.q, f, std::min(per, m - f), rb, sp_, local, nullptr));
  // The last chunk written in place: the caller's rows mapped behind the kernels, one wait for both.
  const bool last = first + m == n_;
  DownloadedRows rows;
  if (in_place && last) rows.map(queue, in_place_, n_, k_, p_.count_examined, CL_MAP_READ | CL_MAP_WRITE, false);
  check_cl(queue.finish(), "clFinish", ix_.method() + " query");
  for (const auto& e : kernels) st.query_s += event_seconds(e);
  st.batches += kernels.size();
  if (in_place) {
    if (!last) return;
    // Every chunk's rows are the caller's already: checked where they lie, then unmapped (the
    // pipeline's closing wait covers the unmaps) and the buffers let go.
    const auto tw = std::chrono::steady_clock::now();
    check_rows_in_place(caller_queries, suspects);
    st.unsort_s += seconds_since(tw);
    return;
  }
  const auto td = std::chrono::steady_clock::now();
  if (b.host) rows.map(queue, rb, m, k_, p_.count_examined);
  else rows.read(queue, rb, m, k_, p_.count_examined);
  st.download_s += seconds_since(td);
  const auto tw = std::chrono::steady_clock::now();
  store_rows(first, m, order, rows.ids, rows.dist2, rows.counts, rows.exam, caller_queries, suspects);
  st.unsort_s += seconds_since(tw);
}

void Index::KnnKind::finish(const std::size_t*, const float*, QueryStats&, std::vector<std::size_t>&) {
  // The caller's memory is the caller's alone again (its unmaps ran before the pipeline's wait).
  in_place_ = ResultBuffers{};
}

void Index::KnnKind::search_host(const float* queries, std::size_t n, const std::size_t* order,
                                 const float* caller_queries, QueryStats& st, std::vector<std::size_t>& suspects) {
  if (!order && res_) {  // the rows searched in place; the scan notes suspects and rescales
    st.query_s = ix_.host_search(queries, n, sp_, *res_);
    point_view_at_result();
    store_rows(0, n, nullptr, v_.ids, v_.dist2, v_.counts, nullptr, caller_queries, suspects);
    return;
  }
  // The rows in dispatch order, in arrays this thread keeps from call to call: fresh ones cost
  // a page fault per 4 KiB (8 k bytes per query) on every call, more than the copy itself.
  // (A reference: the copy below runs on other threads, where the name would mean their own.)
  thread_local KnnResult scratch;
  KnnResult& tmp = scratch;
  tmp.resize(n, p_.k);
  st.query_s = ix_.host_search(queries, n, sp_, tmp);
  const auto tu = std::chrono::steady_clock::now();
  const std::int32_t* exam = p_.count_examined && !tmp.examined.empty() ? tmp.examined.data() : nullptr;
  if (p_.count_examined && !exam) std::fill_n(v_.examined, n, 0);
  store_rows(0, n, order, tmp.ids.data(), tmp.dist2.data(), tmp.counts.data(), exam, caller_queries, suspects);
  if (tmp.ids.capacity() * 8 > kSortScratchBytes) tmp = KnnResult{};  // kept only up to the bound
  st.unsort_s = seconds_since(tu);
}

void Index::KnnKind::answer_exactly(const float* caller_queries, const std::vector<std::size_t>& rows) {
  const double r = p_.max_radius;
  const double r2 = std::isinf(r) ? INFINITY : r * r;
  detail::parallel_for(rows.size(), [&](std::size_t b, std::size_t e) {
    std::vector<Candidate> best;
    for (std::size_t t = b; t < e; ++t) {
      const std::size_t row = rows[t];
      exact_candidates(caller_queries + 3 * row, r2, k_, best);
      for (std::size_t j = 0; j < k_; ++j) {
        v_.ids[row * k_ + j] = j < best.size() ? best[j].second : -1;
        v_.dist2[row * k_ + j] = j < best.size() ? detail::to_float_or_inf(best[j].first) : INFINITY;
      }
      v_.counts[row] = static_cast<std::int32_t>(best.size());
    }
  }, 0, 1);
}

QueryStats Index::query(const float* queries, std::size_t n, const SearchParams& params,
                        KnnResult& out) const {
  KnnKind kind(*this, params, &out);
  return run_query(queries, n, kind);
}

QueryStats SearchIndex::query_into(const float* queries, std::size_t n, const SearchParams& params,
                                   const KnnRowsView& out) const {
  if (n > 0 && (!out.ids || !out.dist2 || !out.counts || (params.count_examined && !out.examined)))
    throw Error("query_into: a null output array in the view for " + std::to_string(n) + " queries");
  KnnResult r;
  const QueryStats st = query(queries, n, params, r);
  const std::size_t nk = n * static_cast<std::size_t>(params.k);
  std::copy_n(r.ids.data(), nk, out.ids);
  std::copy_n(r.dist2.data(), nk, out.dist2);
  std::copy_n(r.counts.data(), n, out.counts);
  if (params.count_examined) std::copy_n(r.examined.data(), n, out.examined);
  return st;
}

QueryStats Index::query_into(const float* queries, std::size_t n, const SearchParams& params,
                             const KnnRowsView& out) const {
  KnnKind kind(*this, params, nullptr, out);
  return run_query(queries, n, kind);
}

double Index::warm_up(const SearchParams& params) const {
  ReadLock read_lock(*this);  // the launch reads the structure's buffers (see insert)
  check_params(params);
  if (answers_on_host()) return 0.0;
  KnnResult unused;
  KnnKind kind(*this, params, &unused);
  return warm_up_kind(kind, local_size_for(params));
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
