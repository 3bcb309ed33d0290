// The Index base: parameter checks, batching, warm-up launches and timing, shared by all methods.
#include "blockhash_cl/knn.hpp"

#include <chrono>
#include <cmath>
#include <sstream>

#include "blockhash_cl/error.hpp"

namespace bhcl {

int kmax_variant(int k) {
  if (k < 1 || k > kMaxK)
    throw Error("k = " + std::to_string(k) + " is out of range: must be in [1, " +
                std::to_string(kMaxK) + "]");
  for (int v : kKmaxVariants)
    if (v >= k) return v;
  return kMaxK;
}

void KnnResult::resize(std::size_t n_queries, int k_) {
  n = n_queries;
  k = k_;
  ids.assign(n * static_cast<std::size_t>(k), -1);
  dist2.assign(n * static_cast<std::size_t>(k), std::numeric_limits<float>::infinity());
  counts.assign(n, 0);
}

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

void Index::check_params(const SearchParams& p) const {
  kmax_variant(p.k);  // throws for k outside [1, kMaxK]
  if (std::isnan(p.max_radius) || p.max_radius < 0)
    throw Error("max_radius must be >= 0 (or +inf), got " + std::to_string(p.max_radius));
  if (p.local_size > runtime_->info().max_work_group_size && runtime_->info().max_work_group_size)
    throw Error("local_size " + std::to_string(p.local_size) + " exceeds the device maximum " +
                std::to_string(runtime_->info().max_work_group_size));
}

std::size_t Index::local_size_for(const SearchParams& p) const {
  return p.local_size ? p.local_size : runtime_->quirks().default_local_size;
}

double Index::warm_up(const SearchParams& params) const {
  check_params(params);
  std::size_t local = local_size_for(params);
  auto key = std::make_pair(kmax_variant(params.k), local);
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
  cl::Event e = enqueue_batch(runtime_->queue(), q, 0, 0, rb, params, local, nullptr);
  check_cl(e.wait(), "clWaitForEvents", method() + " warm-up");
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
  cl::Event last;
  std::vector<cl::Event> prev;
  const std::vector<cl::Event>* w = wait;
  for (std::size_t first = 0; first < n; first += per) {
    std::size_t count = std::min(per, n - first);
    last = enqueue_batch(queue, queries, first, count, out, params, local, w);
    if (kernels) kernels->push_back(last);
    // An in-order queue orders the batches; the caller's wait list applies to the first only.
    w = nullptr;
  }
  return last;
}

cl::Event Index::enqueue_query(const cl::CommandQueue& queue, const cl::Buffer& queries,
                               std::size_t n, const ResultBuffers& out,
                               const SearchParams& params,
                               const std::vector<cl::Event>* wait) const {
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
  std::size_t nk = n * static_cast<std::size_t>(params.k);
  if (nk / static_cast<std::size_t>(params.k) != n) throw Error("n * k overflows");
  need(queries, n * 3 * sizeof(float), "queries");
  need(out.ids, nk * sizeof(std::int32_t), "ids");
  need(out.dist2, nk * sizeof(float), "dist2");
  need(out.counts, n * sizeof(std::int32_t), "counts");
  return enqueue_impl(queue, queries, n, out, params, wait, nullptr, nullptr);
}

QueryStats Index::query(const float* queries, std::size_t n, const SearchParams& params,
                        KnnResult& out) const {
  auto t0 = std::chrono::steady_clock::now();
  check_params(params);
  QueryStats st;
  st.n_queries = n;
  out.resize(n, params.k);
  if (n == 0) return st;
  for (std::size_t i = 0; i < n; ++i) {
    const float* q = queries + 3 * i;
    if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) ++st.nonfinite_queries;
  }
  const Runtime& rt = *runtime_;
  const cl::CommandQueue& queue = rt.queue();
  const std::size_t k = static_cast<std::size_t>(params.k);
  // Host chunks bound the device memory of one call: results are 8*k bytes per query.
  std::size_t chunk = std::max<std::size_t>(1, (std::size_t(256) << 20) / (8 * k + 12));
  if (rt.info().max_alloc_bytes)
    chunk = std::min<std::size_t>(chunk, std::max<std::size_t>(1, rt.info().max_alloc_bytes / (4 * k)));
  chunk = std::min(chunk, n);
  cl_int err = CL_SUCCESS;
  auto make = [&](std::size_t bytes, const char* what) {
    cl::Buffer b(rt.context(), CL_MEM_READ_WRITE, bytes, nullptr, &err);
    check_cl(err, "clCreateBuffer", std::string(what) + ", " + std::to_string(bytes) + " bytes");
    return b;
  };
  cl::Buffer qbuf = make(chunk * 3 * sizeof(float), "queries");
  ResultBuffers rb{make(chunk * k * sizeof(std::int32_t), "ids"), make(chunk * k * sizeof(float), "dist2"),
                   make(chunk * sizeof(std::int32_t), "counts")};
  for (std::size_t first = 0; first < n; first += chunk) {
    std::size_t m = std::min(chunk, n - first);
    cl::Event up, d1, d2, d3;
    check_cl(queue.enqueueWriteBuffer(qbuf, CL_FALSE, 0, m * 3 * sizeof(float), queries + 3 * first,
                                      nullptr, &up),
             "clEnqueueWriteBuffer", "queries");
    std::vector<cl::Event> kernels;
    enqueue_impl(queue, qbuf, m, rb, params, nullptr, &kernels, &st.compile_s);
    check_cl(queue.enqueueReadBuffer(rb.ids, CL_FALSE, 0, m * k * sizeof(std::int32_t),
                                     out.ids.data() + first * k, nullptr, &d1),
             "clEnqueueReadBuffer", "ids");
    check_cl(queue.enqueueReadBuffer(rb.dist2, CL_FALSE, 0, m * k * sizeof(float),
                                     out.dist2.data() + first * k, nullptr, &d2),
             "clEnqueueReadBuffer", "dist2");
    check_cl(queue.enqueueReadBuffer(rb.counts, CL_FALSE, 0, m * sizeof(std::int32_t),
                                     out.counts.data() + first, nullptr, &d3),
             "clEnqueueReadBuffer", "counts");
    check_cl(queue.finish(), "clFinish", method() + " query");
    st.upload_s += event_seconds(up);
    for (const auto& e : kernels) st.query_s += event_seconds(e);
    st.download_s += event_seconds(d1) + event_seconds(d2) + event_seconds(d3);
    st.batches += kernels.size();
  }
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
