// The test helper module's data sets and exact-result checks (declared in test_util.hpp).
#include "test_util.hpp"

#include <cstring>
#include <random>

namespace bhcl::test {

// Queries for a point set: uniform over its box grown by 10 %, exact copies of points (distance
// 0 ties, duplicates), and points moved by a tiny jitter (near-ties).
std::vector<float> queries_for(const std::vector<float>& pts, std::uint64_t seed, std::size_t each) {
  const std::size_t N = pts.size() / 3;
  float lo[3], hi[3];
  for (int d = 0; d < 3; ++d) lo[d] = hi[d] = pts[d];
  for (std::size_t i = 0; i < N; ++i)
    for (int d = 0; d < 3; ++d) {
      lo[d] = std::min(lo[d], pts[3 * i + d]);
      hi[d] = std::max(hi[d], pts[3 * i + d]);
    }
  std::mt19937_64 rng(seed);
  std::vector<float> q;
  for (std::size_t i = 0; i < each; ++i)
    for (int d = 0; d < 3; ++d) {
      double ext = double(hi[d]) - lo[d];
      std::uniform_real_distribution<double> u(lo[d] - 0.1 * ext, hi[d] + 0.1 * ext);
      q.push_back(static_cast<float>(u(rng)));
    }
  std::uniform_int_distribution<std::size_t> pick(0, N - 1);
  for (std::size_t i = 0; i < each; ++i) {
    std::size_t p = pick(rng);
    q.insert(q.end(), pts.begin() + 3 * p, pts.begin() + 3 * p + 3);
  }
  std::normal_distribution<float> jitter(0.0f, 1.0f);
  for (std::size_t i = 0; i < each; ++i) {
    std::size_t p = pick(rng);
    for (int d = 0; d < 3; ++d) {
      float v = pts[3 * p + d];
      float step = std::max(std::abs(v) * 1e-6f, 1e-4f * float(double(hi[d]) - lo[d]));
      q.push_back(v + step * jitter(rng));
    }
  }
  return q;
}

std::vector<PointSet> exact_point_sets() {
  std::vector<PointSet> sets;
  auto add = [&](const std::string& name, std::vector<float> pts, std::uint64_t seed) {
    std::vector<float> q = queries_for(pts, seed);
    sets.push_back({name, std::move(pts), std::move(q)});
  };
  add("uniform", datasets::uniform(3000, 101), 1);
  add("clustered", datasets::clustered(4000, 102, 8, 0.002f), 2);
  add("duplicates", datasets::with_duplicates(3000, 103, 0.5), 3);
  add("identical", std::vector<float>(3 * 1000, 0.375f), 4);
  {
    auto pts = datasets::uniform(3000, 105);
    for (std::size_t i = 0; i < pts.size(); i += 3) pts[i + 2] = 0.5f;  // flat: z = const
    add("flat", std::move(pts), 5);
  }
  {
    // Collinear: a diagonal line (x = y = z) and an axis-aligned one, with repeated positions.
    std::mt19937_64 rng(106);
    std::uniform_int_distribution<int> t(0, 1500);
    std::vector<float> pts;
    for (int i = 0; i < 2000; ++i) {
      float v = static_cast<float>(t(rng)) / 1500.0f;
      pts.insert(pts.end(), {v, v, v});
    }
    for (int i = 0; i < 1000; ++i) pts.insert(pts.end(), {static_cast<float>(t(rng)) / 1500.0f, 0.25f, 0.75f});
    add("collinear", std::move(pts), 6);
  }
  {
    // Offset far from the origin: at 1e6 a float step is 0.0625, so coordinates are coarsely
    // quantised and distances tie often.
    auto pts = datasets::uniform(3000, 107, -50.0f, 50.0f);
    datasets::offset(pts, 1e4, -2e5, 1e6);
    add("offset", std::move(pts), 7);
  }
  return sets;
}

// A radius that cuts many rows short: the median distance to the 8th neighbour.
float cutting_radius(const PointSet& s) {
  SearchParams p = test::knn_params(8);
  const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
  KnnResult r = reference::knn_float(s.points.data(), N, s.queries.data(), n, p);
  std::vector<float> d;
  for (std::size_t q = 0; q < n; ++q)
    if (r.counts[q] == 8) d.push_back(r.d2(q, 7));
  std::nth_element(d.begin(), d.begin() + d.size() / 2, d.end());
  return std::sqrt(d[d.size() / 2]);
}

// Bit-exact equality of two results (ids, counts, distances including +inf), naming the first
// differing entry.
void require_identical(const KnnResult& r, const KnnResult& ref, const std::string& what) {
  REQUIRE(r.n == ref.n);
  REQUIRE(r.k == ref.k);
  CHECK(r.counts == ref.counts);
  for (std::size_t i = 0; i < r.ids.size(); ++i) {
    if (r.ids[i] == ref.ids[i] && std::memcmp(&r.dist2[i], &ref.dist2[i], sizeof(float)) == 0) continue;
    FAIL_CHECK(what << ": query " << i / r.k << " rank " << i % r.k << ": id " << r.ids[i] << " d2 "
                    << r.dist2[i] << ", brute force id " << ref.ids[i] << " d2 " << ref.dist2[i]);
    return;
  }
}

// Runs an exact index on a point set for every k, with and without the cutting radius.
void check_index_on_set(const Index& index, const PointSet& s) {
  const std::size_t N = s.points.size() / 3, n = s.queries.size() / 3;
  const float radius = cutting_radius(s);
  for (float r : {INFINITY, radius}) {
    for (int k : {1, 8, 10, 50, 100, 256}) {
      SearchParams p = test::knn_params(k);
      p.max_radius = r;
      CAPTURE(k);
      CAPTURE(r);
      KnnResult got;
      index.query(s.queries.data(), n, p, got);
      KnnResult ref = reference::knn_float(s.points.data(), N, s.queries.data(), n, p);
      require_identical(got, ref, index.method() + " on " + s.name);
    }
  }
}

KnnResult buffer_query(const Index& index, const std::vector<float>& qs, const SearchParams& p) {
  const auto& rt = index.runtime();
  const std::size_t n = qs.size() / 3, nk = n * static_cast<std::size_t>(p.k);
  cl::Buffer qb(rt.context(), CL_MEM_READ_ONLY | CL_MEM_COPY_HOST_PTR, qs.size() * 4,
                const_cast<float*>(qs.data()));
  ResultBuffers out{cl::Buffer(rt.context(), CL_MEM_READ_WRITE, nk * 4),
                    cl::Buffer(rt.context(), CL_MEM_READ_WRITE, nk * 4),
                    cl::Buffer(rt.context(), CL_MEM_READ_WRITE, n * 4),
                    cl::Buffer(rt.context(), CL_MEM_READ_WRITE, n * 4)};
  cl::Event e = index.enqueue_query(rt.queue(), qb, n, out, p);
  std::vector<cl::Event> wait{e};
  KnnResult r;
  r.resize(n, p.k);
  rt.queue().enqueueReadBuffer(out.ids, CL_TRUE, 0, nk * 4, r.ids.data(), &wait);
  rt.queue().enqueueReadBuffer(out.dist2, CL_TRUE, 0, nk * 4, r.dist2.data(), &wait);
  rt.queue().enqueueReadBuffer(out.counts, CL_TRUE, 0, n * 4, r.counts.data(), &wait);
  if (p.count_examined) {
    r.examined.resize(n);
    rt.queue().enqueueReadBuffer(out.examined, CL_TRUE, 0, n * 4, r.examined.data(), &wait);
  }
  return r;
}

RadiusResult reference_radius_slices(const std::vector<float>& pts, const std::vector<float>& qs,
                                     const std::vector<float>& r2) {
  RadiusResult r;
  r.n = qs.size() / 3;
  r.offsets.assign(r.n + 1, 0);
  r.found.assign(r.n, 0);
  const std::size_t N = pts.size() / 3;
  for (std::size_t q = 0; q < r.n; ++q) {
    const float* qp = &qs[3 * q];
    const float rq = r2.size() == 1 ? r2[0] : r2[q];
    std::vector<std::pair<float, std::int32_t>> row;
    if (std::isfinite(qp[0]) && std::isfinite(qp[1]) && std::isfinite(qp[2]))
      for (std::size_t i = 0; i < N; ++i) {
        const float d = reference::dist2_float(&pts[3 * i], qp);
        if (d <= rq) row.emplace_back(d, static_cast<std::int32_t>(i));
      }
    std::sort(row.begin(), row.end());
    for (auto& [d, id] : row) {
      r.dist2.push_back(d);
      r.ids.push_back(id);
    }
    r.found[q] = static_cast<std::int64_t>(row.size());
    r.offsets[q + 1] = static_cast<std::int64_t>(r.ids.size());
  }
  return r;
}

void require_same_slices(const RadiusResult& a, const RadiusResult& b, const std::string& what) {
  INFO(what);
  REQUIRE(a.n == b.n);
  REQUIRE(a.offsets == b.offsets);
  REQUIRE(a.found == b.found);
  REQUIRE(a.ids == b.ids);
  for (std::size_t i = 0; i < a.dist2.size(); ++i)
    if (std::memcmp(&a.dist2[i], &b.dist2[i], sizeof(float)) != 0) {
      FAIL_CHECK("entry " << i << ": id " << a.ids[i] << " d2 " << a.dist2[i] << " vs " << b.dist2[i]);
      return;
    }
}

}  // namespace bhcl::test
