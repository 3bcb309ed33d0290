// Radius search for every method: parameter checks, the count and fill passes with bounded device
// memory, and the slices' final order (sorted by (distance, index), duplicates dropped, the cap).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <sstream>
#include <utility>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/knn.hpp"
#include "core/device_util.hpp"
#include "core/parallel.hpp"
#include "core/query_order.hpp"

namespace bhcl {

namespace {

std::string num(double v) {
  std::ostringstream os;
  os << v;
  return os.str();
}

// Sorts every raw slice by (distance, index) (or, unsorted, only selects the nearest `cap` of a
// slice longer than the cap), applies the cap and compacts the slices. Fills found and
// truncated_queries. The kernels never return a point twice (the L-table kernel filters the
// blocks its tables share), so no repeats are dropped.
void finish_slices(RadiusResult& r, std::size_t cap, bool sorted) {
  const std::size_t n = r.n;
  std::vector<std::int64_t> keep(n, 0);
  detail::parallel_for(n, [&](std::size_t b, std::size_t e) {
    std::vector<std::pair<float, std::int32_t>> tmp;
    for (std::size_t i = b; i < e; ++i) {
      const std::size_t lo = static_cast<std::size_t>(r.offsets[i]), hi = static_cast<std::size_t>(r.offsets[i + 1]);
      const std::size_t count = hi - lo;
      r.found[i] = static_cast<std::int64_t>(count);
      const std::size_t m = cap ? std::min(cap, count) : count;
      keep[i] = static_cast<std::int64_t>(m);
      if (!sorted && m == count) continue;  // nothing to order or cut
      tmp.clear();
      for (std::size_t j = lo; j < hi; ++j) tmp.emplace_back(r.dist2[j], r.ids[j]);
      if (sorted) std::sort(tmp.begin(), tmp.end());
      else std::nth_element(tmp.begin(), tmp.begin() + static_cast<std::ptrdiff_t>(m), tmp.end());
      for (std::size_t j = 0; j < m; ++j) {
        r.dist2[lo + j] = tmp[j].first;
        r.ids[lo + j] = tmp[j].second;
      }
    }
  }, 0, 1024);
  // Compact in place: slices only move left.
  std::int64_t w = 0;
  r.truncated_queries = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const std::int64_t lo = r.offsets[i];
    if (w != lo) {
      std::memmove(r.ids.data() + w, r.ids.data() + lo, static_cast<std::size_t>(keep[i]) * sizeof(std::int32_t));
      std::memmove(r.dist2.data() + w, r.dist2.data() + lo, static_cast<std::size_t>(keep[i]) * sizeof(float));
    }
    r.offsets[i] = w;
    w += keep[i];
    if (keep[i] < r.found[i]) ++r.truncated_queries;
  }
  r.offsets[n] = w;
  r.ids.resize(static_cast<std::size_t>(w));
  r.dist2.resize(static_cast<std::size_t>(w));
}

// The device buffers radius_on_device allocates for n queries (before the fill buffers grow
// past their default size for one very full query).
std::size_t radius_device_bytes(std::size_t n, const RadiusParams& p, std::size_t max_alloc) {
  if (n == 0) return 0;
  const std::size_t chunk = std::min<std::size_t>(n, std::size_t(1) << 20);
  std::size_t cap = p.max_batch_results ? p.max_batch_results : (std::size_t(1) << 24);
  cap = std::max<std::size_t>(1, std::min(cap, max_alloc / 4));
  return chunk * (12 + 4 + 8 + (p.count_examined ? 4 : 0)) + cap * 8;
}

}  // namespace

cl::Event Index::enqueue_radius_batch(const cl::CommandQueue&, const cl::Buffer&, std::size_t,
                                      std::size_t, float, int, const RadiusBuffers&,
                                      const RadiusParams&, std::size_t,
                                      const std::vector<cl::Event>*) const {
  throw Error(method() + ": no radius-search kernel");
}

double Index::host_radius_search(const float*, std::size_t, float, const RadiusParams&,
                                 RadiusResult&) const {
  throw Error(method() + ": host_radius_search is not implemented by this method");
}

void Index::check_radius_params(const RadiusParams& p) const {
  // The options radius search shares with kNN are checked by the method's own kNN check.
  SearchParams s;
  static_cast<DispatchParams&>(s) = p;
  s.k = 1;
  check_params(s);
  if (p.sort_queries < -1 || p.sort_queries > 1)
    throw Error("radius_search: sort_queries must be -1 (auto), 0 or 1, got " + std::to_string(p.sort_queries));
}

QueryStats Index::radius_search(const float* queries, std::size_t n, float radius,
                                const RadiusParams& params, RadiusResult& out) const {
  // +inf is a radius (every point at a finite distance), as scipy's query_ball_point takes it.
  if (std::isnan(radius) || radius < 0)
    throw Error("radius_search: the radius must be >= 0 (+inf: every point), got " + num(radius));
  return radius_impl(queries, n, radius, false, params, out);
}

QueryStats Index::radius_search_squared(const float* queries, std::size_t n, float r2,
                                        const RadiusParams& params, RadiusResult& out) const {
  if (std::isnan(r2) || r2 < 0)
    throw Error("radius_search_squared: the squared radius must be >= 0 (+inf: every point), got " + num(r2));
  return radius_impl(queries, n, r2, true, params, out);
}

QueryStats Index::radius_impl(const float* queries, std::size_t n, float r, bool squared,
                              const RadiusParams& params, RadiusResult& out) const {
  auto t0 = std::chrono::steady_clock::now();
  ReadLock lock(*this);  // queries share the index; insert/remove wait (see Index::insert)
  check_radius_params(params);
  if (n > 0 && !queries) throw Error("radius_search: queries is null with n = " + std::to_string(n));
  const bool sort = params.sort_queries > 0 || (params.sort_queries < 0 && n >= kAutoSortQueries);
  // Sizes before allocation: what the n queries need whatever they find, before any search (the
  // points found are checked by the count pass, radius_on_device, before they are fetched).
  check_radius_memory(n, 0, params.count_examined, sort && n > 1 ? 2 : 1,
                        answers_on_host() ? 0 : radius_device_bytes(n, params, runtime().info().max_alloc_bytes
                                                                                  ? runtime().info().max_alloc_bytes
                                                                                  : (std::size_t(1) << 30)),
                        method());
  if (sort && n > 1) {
    // Dispatch in Hilbert order, return the slices in the caller's order.
    std::vector<std::size_t> order = detail::hilbert_query_order(queries, n);
    const std::vector<float> sorted = detail::queries_in_order(queries, order);
    RadiusParams p = params;
    p.sort_queries = 0;
    RadiusResult tmp;
    QueryStats st = radius_impl(sorted.data(), n, r, squared, p, tmp);
    out.n = n;
    out.offsets.assign(n + 1, 0);
    out.found.assign(n, 0);
    out.examined.assign(params.count_examined ? n : 0, 0);
    out.truncated_queries = tmp.truncated_queries;
    for (std::size_t i = 0; i < n; ++i) {
      out.offsets[order[i] + 1] = static_cast<std::int64_t>(tmp.count(i));
      out.found[order[i]] = tmp.found[i];
      if (params.count_examined) out.examined[order[i]] = tmp.examined[i];
    }
    for (std::size_t i = 0; i < n; ++i) out.offsets[i + 1] += out.offsets[i];
    out.ids.resize(tmp.ids.size());
    out.dist2.resize(tmp.dist2.size());
    for (std::size_t i = 0; i < n; ++i) {
      const std::size_t c = tmp.count(i), from = static_cast<std::size_t>(tmp.offsets[i]);
      const std::size_t to = static_cast<std::size_t>(out.offsets[order[i]]);
      std::copy_n(tmp.ids.data() + from, c, out.ids.data() + to);
      std::copy_n(tmp.dist2.data() + from, c, out.dist2.data() + to);
    }
    st.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return st;
  }
  QueryStats st;
  st.n_queries = n;
  out.n = n;
  out.offsets.assign(n + 1, 0);
  out.ids.clear();
  out.dist2.clear();
  out.found.assign(n, 0);
  out.truncated_queries = 0;
  out.examined.assign(params.count_examined ? n : 0, 0);
  if (n == 0) return st;
  for (std::size_t i = 0; i < n; ++i) {
    const float* q = queries + 3 * i;
    if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) ++st.nonfinite_queries;
  }
  // The squared radius in the structure's coordinates (an exact power-of-two scaling). A finite
  // Euclidean r whose square overflows becomes +inf: every point with a finite distance is within.
  const int e = scale_exponent();
  float r2;
  if (squared) {
    r2 = std::ldexp(r, -2 * e);
  } else {
    const float rs = std::ldexp(r, -e);
    r2 = rs * rs;
  }
  std::vector<float> storage;
  const float* q = to_structure(queries, n, storage);
  if (answers_on_host()) {
    st.query_s = host_radius_search(q, n, r2, params, out);
  } else {
    radius_on_device(q, n, r2, params, out, st);
  }
  finish_slices(out, params.max_results, params.sorted);
  if (exact()) {
    // Slices the float search cannot vouch for answered again in double (see the contract).
    const double r2d = squared ? double(r) : double(r) * double(r);
    radius_exact_fallback(queries, n, r2d, r2, params, out);
  } else {
    distances_to_caller(out.dist2.data(), out.dist2.size());
  }
  st.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return st;
}

void Index::radius_exact_fallback(const float* caller_queries, std::size_t n, double r2, float r2s,
                                  const RadiusParams& params, RadiusResult& out) const {
  std::vector<std::size_t> rows;
  const bool tiny_radius = r2s > 0 && r2s < std::ldexp(1.0f, -120);
  for (std::size_t i = 0; i < n && !caller_points_.empty(); ++i) {
    const float* q = caller_queries + 3 * i;
    if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) continue;
    bool bad = tiny_radius;
    for (std::int64_t j = out.offsets[i]; j < out.offsets[i + 1] && !bad; ++j)
      bad = entry_suspect(q, out.ids[static_cast<std::size_t>(j)], out.dist2[static_cast<std::size_t>(j)]);
    if (bad) rows.push_back(i);
  }
  distances_to_caller(out.dist2.data(), out.dist2.size());
  if (rows.empty()) return;
  // The suspect slices in double over the caller's points, then the layout rebuilt.
  // Every id issued: a removed one holds NaN, which `d <= r2` rejects.
  const std::size_t N = caller_points_.size() / 3;
  const float* pts = caller_points_.data();
  std::vector<std::vector<std::pair<double, std::int32_t>>> redo(rows.size());
  detail::parallel_for(rows.size(), [&](std::size_t b, std::size_t e) {
    for (std::size_t t = b; t < e; ++t) {
      const float* q = caller_queries + 3 * rows[t];
      auto& v = redo[t];
      for (std::size_t i = 0; i < N; ++i) {
        const double dx = double(q[0]) - pts[3 * i], dy = double(q[1]) - pts[3 * i + 1],
                     dz = double(q[2]) - pts[3 * i + 2];
        const double d = dx * dx + dy * dy + dz * dz;
        if (d <= r2) v.emplace_back(d, static_cast<std::int32_t>(i));
      }
      std::sort(v.begin(), v.end());  // sorted whatever params.sorted says: any order is allowed
    }
  }, 0, 1);
  RadiusResult r;
  r.n = n;
  r.offsets.assign(n + 1, 0);
  r.found = out.found;
  r.examined = out.examined;
  r.truncated_queries = 0;
  const float fmax = std::numeric_limits<float>::max();
  std::size_t t = 0;
  for (std::size_t i = 0; i < n; ++i) {
    if (t < rows.size() && rows[t] == i) {
      const auto& v = redo[t++];
      const std::size_t m = params.max_results ? std::min(params.max_results, v.size()) : v.size();
      for (std::size_t j = 0; j < m; ++j) {
        r.ids.push_back(v[j].second);
        r.dist2.push_back(v[j].first > double(fmax) ? INFINITY : static_cast<float>(v[j].first));
      }
      r.found[i] = static_cast<std::int64_t>(v.size());
    } else {
      r.ids.insert(r.ids.end(), out.ids.begin() + out.offsets[i], out.ids.begin() + out.offsets[i + 1]);
      r.dist2.insert(r.dist2.end(), out.dist2.begin() + out.offsets[i], out.dist2.begin() + out.offsets[i + 1]);
    }
    r.offsets[i + 1] = static_cast<std::int64_t>(r.ids.size());
    if (static_cast<std::int64_t>(r.count(i)) < r.found[i]) ++r.truncated_queries;
  }
  out = std::move(r);
}

double Index::warm_up_radius(const cl::Buffer& queries, const RadiusBuffers& rb, float r2,
                             const RadiusParams& params, std::size_t local) const {
  // The first launch compiles the program; a zero-size launch of each pass keeps that out of the
  // timed dispatches, once per (local size, defines), in warm_up's cache (kmax 0: the radius
  // kernels, which have no k variants).
  const auto key = std::make_tuple(0, local, params.kernel_defines);
  std::lock_guard<std::mutex> lock(warm_mutex_);
  if (warmed_.count(key)) return 0.0;
  auto t0 = std::chrono::steady_clock::now();
  for (int pass = 0; pass < 2; ++pass) {
    cl::Event w = enqueue_radius_batch(runtime().warm_queue(), queries, 0, 0, r2, pass, rb, params, local, nullptr);
    check_cl(w.wait(), "clWaitForEvents", method() + " radius warm-up");
  }
  runtime().keep_program_binaries();  // the launches compiled this local size: kept for later processes
  warmed_.insert(key);
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void Index::radius_on_device(const float* queries, std::size_t n, float r2,
                             const RadiusParams& params, RadiusResult& out, QueryStats& st) const {
  const Runtime& rt = runtime();
  const cl::CommandQueue& queue = rt.queue();
  const std::size_t local = params.local_size ? params.local_size : rt.quirks().default_local_size;
  std::size_t per = params.max_batch ? std::min(params.max_batch, max_dispatch_queries()) : max_dispatch_queries();
  per = std::max<std::size_t>(per, 1);
  const std::size_t chunk = std::min<std::size_t>(n, std::size_t(1) << 20);
  const std::size_t max_alloc = rt.info().max_alloc_bytes ? rt.info().max_alloc_bytes : (std::size_t(1) << 30);
  std::size_t cap_results = params.max_batch_results ? params.max_batch_results : (std::size_t(1) << 24);
  cap_results = std::max<std::size_t>(1, std::min(cap_results, max_alloc / 4));
  auto make = [&](std::size_t bytes, const char* what) {
    return detail::device_buffer(rt, bytes, std::string("radius search ") + what);
  };
  cl::Buffer qbuf = make(chunk * 3 * sizeof(float), "queries");
  RadiusBuffers rb;
  rb.counts = make(chunk * sizeof(std::int32_t), "counts");
  rb.examined = params.count_examined ? make(chunk * sizeof(std::int32_t), "examined") : rb.counts;
  rb.offsets = make(std::min(chunk, per) * sizeof(cl_ulong), "offsets");
  std::size_t fill_capacity = 0;  // results the fill buffers hold
  rb.ids = rb.dist2 = make(4, "fill");

  st.compile_s += warm_up_radius(qbuf, rb, r2, params, local);
  std::vector<std::int32_t> counts(chunk);
  std::vector<cl_ulong> offs;
  for (std::size_t first = 0; first < n; first += chunk) {
    const std::size_t m = std::min(chunk, n - first);
    // Pass 0: the counts.
    cl::Event up, rc;
    check_cl(queue.enqueueWriteBuffer(qbuf, CL_FALSE, 0, m * 3 * sizeof(float), queries + 3 * first, nullptr, &up),
             "clEnqueueWriteBuffer", "radius queries");
    std::vector<cl::Event> kernels;
    for (std::size_t f = 0; f < m; f += per)
      kernels.push_back(enqueue_radius_batch(queue, qbuf, f, std::min(per, m - f), r2, 0, rb, params, local, nullptr));
    check_cl(queue.enqueueReadBuffer(rb.counts, CL_FALSE, 0, m * sizeof(std::int32_t), counts.data(), nullptr, &rc),
             "clEnqueueReadBuffer", "radius counts");
    if (params.count_examined)
      check_cl(queue.enqueueReadBuffer(rb.examined, CL_FALSE, 0, m * sizeof(std::int32_t), out.examined.data() + first),
               "clEnqueueReadBuffer", "radius examined");
    check_cl(queue.finish(), "clFinish", method() + " radius count pass");
    st.upload_s += event_seconds(up);
    st.download_s += event_seconds(rc);
    for (const auto& k : kernels) st.query_s += event_seconds(k);
    st.batches += kernels.size();
    // The chunk's slices follow the ones already written.
    const std::size_t base = out.ids.size();
    std::size_t total = 0;
    for (std::size_t i = 0; i < m; ++i) {
      out.offsets[first + i] = static_cast<std::int64_t>(base + total);
      total += static_cast<std::size_t>(counts[i]);
    }
    // Counted, not yet fetched: refused here when the points found cannot be held.
    check_radius_memory(n, base + total, params.count_examined, 1, 0, method());
    out.offsets[first + m] = static_cast<std::int64_t>(base + total);
    out.ids.resize(base + total);
    out.dist2.resize(base + total);
    // Pass 1 in groups of queries whose results fit the fill buffers.
    for (std::size_t a = 0; a < m;) {
      std::size_t b = a, sum = 0;
      while (b < m && b - a < per &&
             (b == a || sum + static_cast<std::size_t>(counts[b]) <= cap_results)) {
        sum += static_cast<std::size_t>(counts[b]);
        ++b;
      }
      if (sum > 0) {
        if (sum * sizeof(float) > max_alloc)
          throw Error("radius_search: query " + std::to_string(first + a) + " has " + std::to_string(sum) +
                      " points within the radius, more than one device buffer holds (" +
                      std::to_string(max_alloc) + " bytes): use a smaller radius");
        if (sum > fill_capacity) {
          fill_capacity = std::max(sum, std::min(cap_results, max_alloc / 4));
          rb.ids = make(fill_capacity * sizeof(std::int32_t), "ids");
          rb.dist2 = make(fill_capacity * sizeof(float), "dist2");
        }
        offs.assign(b - a, 0);
        cl_ulong o = 0;
        for (std::size_t i = a; i < b; ++i) {
          offs[i - a] = o;
          o += static_cast<cl_ulong>(counts[i]);
        }
        cl::Event uo, d1, d2;
        check_cl(queue.enqueueWriteBuffer(rb.offsets, CL_FALSE, 0, offs.size() * sizeof(cl_ulong), offs.data(), nullptr, &uo),
                 "clEnqueueWriteBuffer", "radius offsets");
        cl::Event kf = enqueue_radius_batch(queue, qbuf, a, b - a, r2, 1, rb, params, local, nullptr);
        const std::size_t at = static_cast<std::size_t>(out.offsets[first + a]);
        check_cl(queue.enqueueReadBuffer(rb.ids, CL_FALSE, 0, sum * sizeof(std::int32_t), out.ids.data() + at, nullptr, &d1),
                 "clEnqueueReadBuffer", "radius ids");
        check_cl(queue.enqueueReadBuffer(rb.dist2, CL_FALSE, 0, sum * sizeof(float), out.dist2.data() + at, nullptr, &d2),
                 "clEnqueueReadBuffer", "radius dist2");
        check_cl(queue.finish(), "clFinish", method() + " radius fill pass");
        st.upload_s += event_seconds(uo);
        st.query_s += event_seconds(kf);
        st.download_s += event_seconds(d1) + event_seconds(d2);
        ++st.batches;
      }
      a = b;
    }
  }
}

}  // namespace bhcl
