// The density estimate inside the query (density_query.hpp): chunks of queries answered by the
// method's buffer-level call into reused device buffers, reduced on the device by
// kernels/density_estimate.cl; only the estimates come back.
#include "blockhash_cl/density_query.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>

#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "core/query_order.hpp"

namespace bhcl {
namespace {

void check_finite(const float* v, std::size_t n, const char* what, const char* item) {
  for (std::size_t i = 0; i < 3 * n; ++i)
    if (!std::isfinite(v[i])) {
      std::ostringstream os;
      os << "density_estimate: " << what << " of " << item << " " << i / 3 << " is not finite (component "
         << i % 3 << " = " << v[i] << ")";
      throw Error(os.str());
    }
}

cl::Buffer upload(const Runtime& rt, const float* data, std::size_t floats, const char* what) {
  cl_int err = CL_SUCCESS;
  cl::Buffer b(rt.context(), CL_MEM_READ_ONLY, std::max<std::size_t>(floats * sizeof(float), 4), nullptr, &err);
  check_cl(err, "clCreateBuffer", std::string("density weights: ") + what);
  if (floats)
    check_cl(rt.queue().enqueueWriteBuffer(b, CL_TRUE, 0, floats * sizeof(float), data), "clEnqueueWriteBuffer",
             std::string("density weights: ") + what);
  return b;
}

}  // namespace

DensityWeights::DensityWeights(const Index& index, const float* power, const float* direction, std::size_t n)
    : n_(n) {
  if (n != index.size())
    throw Error("density weights: " + std::to_string(n) + " points given, the " + index.method() + " index has " +
                std::to_string(index.size()));
  if (n > 0 && (!power || !direction)) throw Error("density weights: power or direction is null");
  check_finite(power, n, "the power", "point");
  check_finite(direction, n, "the direction", "point");
  power_ = upload(index.runtime(), power, 3 * n, "power");
  direction_ = upload(index.runtime(), direction, 3 * n, "direction");
}

QueryStats density_estimate(const Index& index, const DensityWeights& weights, const float* queries,
                            const float* normals, std::size_t n, const DensityParams& params, DensityResult& out) {
  const auto t0 = std::chrono::steady_clock::now();
  if (weights.size() != index.size())
    throw Error("density_estimate: the weights hold " + std::to_string(weights.size()) + " points, the " +
                index.method() + " index " + std::to_string(index.size()) + " (weights of another point set?)");
  if (n > 0 && (!queries || !normals)) throw Error("density_estimate: queries or normals is null");
  if (!(params.radius_scale2 > 0 && params.radius_scale2 <= 1))
    throw Error("density_estimate: radius_scale2 must be in (0, 1], got " + std::to_string(params.radius_scale2));
  if (!(params.cone >= 1) || !std::isfinite(params.cone))
    throw Error("density_estimate: the cone filter's constant must be finite and >= 1, got " +
                std::to_string(params.cone));
  const int rk = static_cast<int>(params.radius), fk = static_cast<int>(params.filter);
  if (rk < 0 || rk > 2 || fk < 0 || fk > 2) throw Error("density_estimate: unknown radius estimator or filter");
  check_finite(normals, n, "the normal", "query");
  QueryStats st;
  st.n_queries = n;
  out.n = n;
  out.estimate.assign(3 * n, 0.0f);
  out.radius2.assign(n, 0.0f);
  out.bytes_read_back = 0;
  if (n == 0) return st;
  for (std::size_t i = 0; i < n; ++i)
    if (!std::isfinite(queries[3 * i]) || !std::isfinite(queries[3 * i + 1]) || !std::isfinite(queries[3 * i + 2]))
      ++st.nonfinite_queries;

  // Hilbert order, as Index::query dispatches large batches: neighbouring queries then share
  // cells and photons in the cache (the estimates come back in the caller's order).
  const SearchParams& sp = params.search;
  const bool sort = sp.sort_queries > 0 || (sp.sort_queries < 0 && n >= kAutoSortQueries);
  std::vector<std::size_t> order;
  std::vector<float> sq, sn;
  const float* q = queries;
  const float* nm = normals;
  if (sort && n > 1) {
    order = detail::hilbert_query_order(queries, n);
    sq = detail::queries_in_order(queries, order);
    sn = detail::queries_in_order(normals, order);
    q = sq.data();
    nm = sn.data();
  }

  const Runtime& rt = index.runtime();
  const cl::CommandQueue& queue = rt.queue();
  const std::size_t k = static_cast<std::size_t>(sp.k);
  const std::size_t max_alloc = rt.info().max_alloc_bytes ? rt.info().max_alloc_bytes : (std::size_t(1) << 30);
  // By default 65536 queries a chunk, or as many whole groups of up to 256 as a launch below the
  // driver's limit holds (PoCL: 65280), so that a chunk is one launch of the kNN and one of ours.
  std::size_t chunk = params.chunk ? params.chunk : detail::items_per_launch(65536, 256, rt.quirks().max_launch_items);
  chunk = std::max<std::size_t>(1, std::min({chunk, n, max_alloc / (4 * std::max<std::size_t>(k, 1))}));
  auto make = [&](std::size_t bytes, const char* what) {
    return detail::device_buffer(rt, bytes, std::string("density_estimate ") + what);
  };
  // Reused by every chunk: the lists never leave the device.
  cl::Buffer qbuf = make(chunk * 3 * sizeof(float), "queries");
  cl::Buffer nbuf = make(chunk * 3 * sizeof(float), "normals");
  ResultBuffers lists(make(chunk * k * sizeof(std::int32_t), "ids"), make(chunk * k * sizeof(float), "dist2"),
                      make(chunk * sizeof(std::int32_t), "counts"));
  cl::Buffer ebuf = make(chunk * 4 * sizeof(float), "estimates");
  out.list_bytes_on_device = chunk * (8 * k + 4);
  {
    // Compiles and launches the method's kernel and ours once, outside the timed chunks.
    auto tc = std::chrono::steady_clock::now();
    index.warm_up(sp);
    rt.program("density_estimate.cl");
    st.compile_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - tc).count();
  }
  cl::Kernel kern = rt.kernel("density_estimate.cl", "bhcl_density_estimate");
  std::vector<float> est(chunk * 4);
  const float max_r = sp.max_radius;
  for (std::size_t first = 0; first < n; first += chunk) {
    const std::size_t m = std::min(chunk, n - first);
    cl::Event uq, un, down;
    check_cl(queue.enqueueWriteBuffer(qbuf, CL_FALSE, 0, m * 3 * sizeof(float), q + 3 * first, nullptr, &uq),
             "clEnqueueWriteBuffer", "density_estimate queries");
    check_cl(queue.enqueueWriteBuffer(nbuf, CL_FALSE, 0, m * 3 * sizeof(float), nm + 3 * first, nullptr, &un),
             "clEnqueueWriteBuffer", "density_estimate normals");
    const std::vector<cl::Event> after_upload = {uq, un};
    const cl::Event knn = index.enqueue_query(queue, qbuf, m, lists, sp, &after_upload);
    detail::KernelArgs(kern, "bhcl_density_estimate")
        .add(lists.ids).add(lists.dist2).add(lists.counts).add(nbuf).add(weights.power()).add(weights.direction())
        .add(cl_int(sp.k)).add(max_r).add(cl_int(rk)).add(cl_int(fk)).add(params.cone).add(params.radius_scale2)
        .add(cl_uint(m)).add(ebuf);
    const std::vector<cl::Event> after_knn = {knn};
    const cl::Event red = detail::launch_1d_split(queue, kern, 14, m, rt.quirks().default_local_size,
                                                  rt.quirks().max_launch_items, &after_knn, "bhcl_density_estimate");
    check_cl(queue.enqueueReadBuffer(ebuf, CL_FALSE, 0, m * 4 * sizeof(float), est.data(), nullptr, &down),
             "clEnqueueReadBuffer", "density_estimate estimates");
    check_cl(queue.finish(), "clFinish", index.method() + " density_estimate");
    st.upload_s += event_seconds(uq) + event_seconds(un);
    st.query_s += event_seconds(knn) + event_seconds(red);
    st.download_s += event_seconds(down);
    st.batches += 2;
    out.bytes_read_back += m * 4 * sizeof(float);
    for (std::size_t i = 0; i < m; ++i) {
      const std::size_t dst = order.empty() ? first + i : order[first + i];
      for (int c = 0; c < 3; ++c) out.estimate[3 * dst + c] = est[4 * i + c];
      out.radius2[dst] = est[4 * i + 3];
    }
  }
  st.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return st;
}

}  // namespace bhcl
