// Radius search for every method: the radius kind of query (query_pipeline.hpp): the count and
// fill passes, and the slices' final order (sorted by (distance, index), the cap).
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
#include "core/query_pipeline.hpp"

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

// The radius kind of query (query_pipeline.hpp): variable slices, a count pass and a fill pass.
class Index::RadiusKind final : public Index::QueryKind {
 public:
  // r Euclidean (squared = false) or squared; r2_ the squared radius in the structure's
  // coordinates (an exact power-of-two scaling: a finite r whose square overflows becomes +inf,
  // every point at a finite distance), r2d_ the caller's in double.
  RadiusKind(const Index& ix, const RadiusParams& p, float r, bool squared, RadiusResult& out)
      : QueryKind(ix), p_(p), out_(out), r2d_(squared ? double(r) : double(r) * double(r)) {
    // +inf is a radius (every point at a finite distance), as scipy's query_ball_point takes it.
    if (std::isnan(r) || r < 0)
      throw Error(squared ? "radius_search_squared: the squared radius must be >= 0 (+inf: every point), got " + num(r)
                          : "radius_search: the radius must be >= 0 (+inf: every point), got " + num(r));
    const int e = scale_exponent();
    const float rs = std::ldexp(r, -e);
    r2_ = squared ? std::ldexp(r, -2 * e) : rs * rs;
  }
  const char* name() const override { return "radius_search"; }
  const DispatchParams& dispatch() const override { return p_; }
  std::size_t row_k() const override { return 0; }
  int kernel_variant() const override { return 0; }
  void check(std::size_t n, int copies) const override;
  void begin(std::size_t n) override;
  std::size_t chunk_rows(std::size_t n) const override { return std::min<std::size_t>(n, std::size_t(1) << 20); }
  void warm_launch(const QueryBuffers& b, std::size_t local) const override {
    for (int pass = 0; pass < 2; ++pass) {
      cl::Event w = ix_.enqueue_radius_batch(ix_.runtime_->warm_queue(), b.q, 0, 0, r2_, pass, buffers(b), p_,
                                             local, nullptr);
      check_cl(w.wait(), "clWaitForEvents", ix_.method() + " radius warm-up");
    }
  }
  void search_chunk(QueryBuffers& b, std::size_t first, std::size_t m, const std::size_t* order, std::size_t per,
                    std::size_t local, const float* caller_queries, QueryStats& st,
                    std::vector<std::size_t>& suspects) override;
  void search_host(const float* queries, std::size_t n, const std::size_t*, const float*, QueryStats& st,
                   std::vector<std::size_t>&) override {
    st.query_s = ix_.host_radius_search(queries, n, r2_, p_, out_);
  }
  void finish(const std::size_t* order, const float* caller_queries, QueryStats& st,
              std::vector<std::size_t>& suspects) override;
  void answer_exactly(const float* caller_queries, const std::vector<std::size_t>& rows) override;

 private:
  RadiusBuffers buffers(const QueryBuffers& b) const {
    RadiusBuffers rb;
    rb.counts = b.counts;
    rb.examined = p_.count_examined ? b.examined_buf : b.counts;
    rb.offsets = b.offsets;
    rb.ids = b.ids;
    rb.dist2 = b.dist2;
    return rb;
  }
  std::size_t max_alloc() const {
    const std::size_t a = ix_.runtime_->info().max_alloc_bytes;
    return a ? a : (std::size_t(1) << 30);
  }
  void count_pass(QueryBuffers& b, std::size_t first, std::size_t m, std::size_t per, std::size_t local,
                  QueryStats& st);
  void fill_pass(QueryBuffers& b, std::size_t first, std::size_t m, std::size_t per, std::size_t local,
                 QueryStats& st);
  std::size_t fill_group_end(std::size_t a, std::size_t m, std::size_t per, std::size_t cap) const;
  void reorder_to_caller(const std::size_t* order);

  const RadiusParams& p_;
  RadiusResult& out_;
  const double r2d_;
  float r2_ = 0;
  std::size_t n_ = 0;
  std::vector<std::int32_t> counts_;  // the chunk's counts (count pass)
  std::vector<cl_ulong> offs_;        // a fill group's offsets
};

void Index::RadiusKind::check(std::size_t n, int copies) const {
  ix_.check_radius_params(p_);
  // What the n queries need whatever they find (the points found are checked by the count pass
  // before they are fetched).
  const std::size_t device = ix_.answers_on_host() ? 0 : radius_device_bytes(n, p_, max_alloc());
  check_radius_memory(n, 0, p_.count_examined, copies, device, ix_.method());
}

void Index::RadiusKind::begin(std::size_t n) {
  n_ = n;
  out_.n = n;
  out_.offsets.assign(n + 1, 0);
  out_.ids.clear();
  out_.dist2.clear();
  out_.found.assign(n, 0);
  out_.truncated_queries = 0;
  out_.examined.assign(p_.count_examined ? n : 0, 0);
}

void Index::RadiusKind::search_chunk(QueryBuffers& b, std::size_t first, std::size_t m, const std::size_t*,
                                     std::size_t per, std::size_t local, const float*, QueryStats& st,
                                     std::vector<std::size_t>&) {
  count_pass(b, first, m, per, local, st);
  fill_pass(b, first, m, per, local, st);
}

void Index::RadiusKind::count_pass(QueryBuffers& b, std::size_t first, std::size_t m, std::size_t per,
                                   std::size_t local, QueryStats& st) {
  const cl::CommandQueue& queue = ix_.runtime_->queue();
  const RadiusBuffers rb = buffers(b);
  counts_.resize(m);
  std::vector<cl::Event> kernels;
  for (std::size_t f = 0; f < m; f += per)
    kernels.push_back(ix_.enqueue_radius_batch(queue, b.q, f, std::min(per, m - f), r2_, 0, rb, p_, local, nullptr));
  cl::Event rc;
  check_cl(queue.enqueueReadBuffer(rb.counts, CL_FALSE, 0, m * sizeof(std::int32_t), counts_.data(), nullptr, &rc),
           "clEnqueueReadBuffer", "radius counts");
  if (p_.count_examined)
    check_cl(queue.enqueueReadBuffer(rb.examined, CL_FALSE, 0, m * sizeof(std::int32_t), out_.examined.data() + first),
             "clEnqueueReadBuffer", "radius examined");
  check_cl(queue.finish(), "clFinish", ix_.method() + " radius count pass");
  st.download_s += event_seconds(rc);
  for (const auto& k : kernels) st.query_s += event_seconds(k);
  st.batches += kernels.size();
  // The chunk's slices follow the ones already written.
  const std::size_t base = out_.ids.size();
  std::size_t total = 0;
  for (std::size_t i = 0; i < m; ++i) {
    out_.offsets[first + i] = static_cast<std::int64_t>(base + total);
    total += static_cast<std::size_t>(counts_[i]);
  }
  // Counted, not yet fetched: refused here when the points found cannot be held.
  check_radius_memory(n_, base + total, p_.count_examined, 1, 0, ix_.method());
  out_.offsets[first + m] = static_cast<std::int64_t>(base + total);
  out_.ids.resize(base + total);
  out_.dist2.resize(base + total);
}

std::size_t Index::RadiusKind::fill_group_end(std::size_t a, std::size_t m, std::size_t per, std::size_t cap) const {
  std::size_t b = a, sum = 0;
  while (b < m && b - a < per && (b == a || sum + static_cast<std::size_t>(counts_[b]) <= cap)) {
    sum += static_cast<std::size_t>(counts_[b]);
    ++b;
  }
  return b;
}

void Index::RadiusKind::fill_pass(QueryBuffers& b, std::size_t first, std::size_t m, std::size_t per,
                                  std::size_t local, QueryStats& st) {
  const cl::CommandQueue& queue = ix_.runtime_->queue();
  const std::size_t most = max_alloc();
  std::size_t cap = p_.max_batch_results ? p_.max_batch_results : (std::size_t(1) << 24);
  cap = std::max<std::size_t>(1, std::min(cap, most / 4));
  // In groups of queries whose results fit the fill buffers.
  for (std::size_t a = 0, e; a < m; a = e) {
    e = fill_group_end(a, m, per, cap);
    offs_.assign(e - a, 0);
    cl_ulong sum = 0;
    for (std::size_t i = a; i < e; ++i) {
      offs_[i - a] = sum;
      sum += static_cast<cl_ulong>(counts_[i]);
    }
    if (sum == 0) continue;
    if (sum * sizeof(float) > most)
      throw Error("radius_search: query " + std::to_string(first + a) + " has " + std::to_string(sum) +
                  " points within the radius, more than one device buffer holds (" + std::to_string(most) +
                  " bytes): use a smaller radius");
    if (sum > b.fill) {  // grown, and kept with the call's other buffers for the next call
      b.fill = std::max<std::size_t>(sum, std::min(cap, most / 4));
      b.ids = detail::io_buffer(*ix_.runtime_, b.host, b.fill * sizeof(std::int32_t), "radius search ids");
      b.dist2 = detail::io_buffer(*ix_.runtime_, b.host, b.fill * sizeof(float), "radius search dist2");
    }
    const RadiusBuffers rb = buffers(b);
    cl::Event uo, d1, d2;
    check_cl(queue.enqueueWriteBuffer(rb.offsets, CL_FALSE, 0, offs_.size() * sizeof(cl_ulong), offs_.data(), nullptr, &uo),
             "clEnqueueWriteBuffer", "radius offsets");
    cl::Event kf = ix_.enqueue_radius_batch(queue, b.q, a, e - a, r2_, 1, rb, p_, local, nullptr);
    const std::size_t at = static_cast<std::size_t>(out_.offsets[first + a]);
    check_cl(queue.enqueueReadBuffer(rb.ids, CL_FALSE, 0, sum * sizeof(std::int32_t), out_.ids.data() + at, nullptr, &d1),
             "clEnqueueReadBuffer", "radius ids");
    check_cl(queue.enqueueReadBuffer(rb.dist2, CL_FALSE, 0, sum * sizeof(float), out_.dist2.data() + at, nullptr, &d2),
             "clEnqueueReadBuffer", "radius dist2");
    check_cl(queue.finish(), "clFinish", ix_.method() + " radius fill pass");
    st.upload_s += event_seconds(uo);
    st.query_s += event_seconds(kf);
    st.download_s += event_seconds(d1) + event_seconds(d2);
    ++st.batches;
  }
}

void Index::RadiusKind::finish(const std::size_t* order, const float* caller_queries, QueryStats& st,
                               std::vector<std::size_t>& suspects) {
  finish_slices(out_, p_.max_results, p_.sorted);
  // Slices the float search cannot vouch for (see the contract), noted by the caller's row.
  const bool tiny_radius = r2_ > 0 && r2_ < detail::trusted_min_distance();
  for (std::size_t i = 0; i < n_ && checks_rows(); ++i) {
    const std::size_t row = order ? order[i] : i;
    const float* q = caller_queries + 3 * row;
    if (!detail::finite_query(q)) continue;
    bool bad = tiny_radius;
    for (std::int64_t j = out_.offsets[i]; j < out_.offsets[i + 1] && !bad; ++j)
      bad = entry_suspect(q, out_.ids[static_cast<std::size_t>(j)], out_.dist2[static_cast<std::size_t>(j)]);
    if (bad) suspects.push_back(row);
  }
  ix_.distances_to_caller(out_.dist2.data(), out_.dist2.size());
  if (!order) return;
  const auto tu = std::chrono::steady_clock::now();
  reorder_to_caller(order);
  st.unsort_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - tu).count();
}

void Index::RadiusKind::reorder_to_caller(const std::size_t* order) {
  // Slice i of the dispatch order is the caller's row order[i].
  const RadiusResult tmp = std::move(out_);
  const std::size_t n = n_;
  out_ = RadiusResult{};
  out_.n = n;
  out_.offsets.assign(n + 1, 0);
  out_.found.assign(n, 0);
  out_.examined.assign(tmp.examined.empty() ? 0 : n, 0);
  out_.truncated_queries = tmp.truncated_queries;
  for (std::size_t i = 0; i < n; ++i) {
    out_.offsets[order[i] + 1] = static_cast<std::int64_t>(tmp.count(i));
    out_.found[order[i]] = tmp.found[i];
    if (!tmp.examined.empty()) out_.examined[order[i]] = tmp.examined[i];
  }
  for (std::size_t i = 0; i < n; ++i) out_.offsets[i + 1] += out_.offsets[i];
  out_.ids.resize(tmp.ids.size());
  out_.dist2.resize(tmp.dist2.size());
  detail::parallel_for(n, [&](std::size_t lo, std::size_t hi) {
    for (std::size_t i = lo; i < hi; ++i) {
      const std::size_t c = tmp.count(i), from = static_cast<std::size_t>(tmp.offsets[i]);
      const std::size_t to = static_cast<std::size_t>(out_.offsets[order[i]]);
      std::copy_n(tmp.ids.data() + from, c, out_.ids.data() + to);
      std::copy_n(tmp.dist2.data() + from, c, out_.dist2.data() + to);
    }
  }, 0, 8192);
}

void Index::RadiusKind::answer_exactly(const float* caller_queries, const std::vector<std::size_t>& rows) {
  // The suspect slices in double over the caller's points, then the layout rebuilt.
  std::vector<std::vector<Candidate>> redo(rows.size());
  detail::parallel_for(rows.size(), [&](std::size_t b, std::size_t e) {
    // Sorted whatever params.sorted says: any order is allowed.
    for (std::size_t t = b; t < e; ++t) exact_candidates(caller_queries + 3 * rows[t], r2d_, 0, redo[t]);
  }, 0, 1);
  RadiusResult r;
  r.n = n_;
  r.offsets.assign(n_ + 1, 0);
  r.found = out_.found;
  r.examined = out_.examined;
  r.truncated_queries = 0;
  std::size_t t = 0;
  for (std::size_t i = 0; i < n_; ++i) {
    if (t < rows.size() && rows[t] == i) {
      const auto& v = redo[t++];
      const std::size_t m = p_.max_results ? std::min(p_.max_results, v.size()) : v.size();
      for (std::size_t j = 0; j < m; ++j) {
        r.ids.push_back(v[j].second);
        r.dist2.push_back(detail::to_float_or_inf(v[j].first));
      }
      r.found[i] = static_cast<std::int64_t>(v.size());
    } else {
      r.ids.insert(r.ids.end(), out_.ids.begin() + out_.offsets[i], out_.ids.begin() + out_.offsets[i + 1]);
      r.dist2.insert(r.dist2.end(), out_.dist2.begin() + out_.offsets[i], out_.dist2.begin() + out_.offsets[i + 1]);
    }
    r.offsets[i + 1] = static_cast<std::int64_t>(r.ids.size());
    if (static_cast<std::int64_t>(r.count(i)) < r.found[i]) ++r.truncated_queries;
  }
  out_ = std::move(r);
}

QueryStats Index::radius_search(const float* queries, std::size_t n, float radius,
                                const RadiusParams& params, RadiusResult& out) const {
  RadiusKind kind(*this, params, radius, false, out);
  return run_query(queries, n, kind);
}

QueryStats Index::radius_search_squared(const float* queries, std::size_t n, float r2,
                                        const RadiusParams& params, RadiusResult& out) const {
  RadiusKind kind(*this, params, r2, true, out);
  return run_query(queries, n, kind);
}

}  // namespace bhcl
