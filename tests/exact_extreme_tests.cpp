// Issue 22, class 1: exact means exact for every finite input. Points in [0,1]^3 with far
// outliers (1e19 .. 3e38) and mixed scales; every exact method against a double-precision brute
// force over the caller's float points.
#include <chrono>
#include <random>
#include <tuple>

#include "blockhash_cl/config.hpp"
#include "test_util.hpp"

namespace bhcl {
namespace {

struct Ref {
  std::vector<double> d;  // n*k true squared distances (double), +inf for missing
  std::vector<std::int32_t> ids;
  std::vector<int> counts;
};

// The true k nearest in double, ties to the lower index, within r2 (double).
Ref double_knn(const std::vector<float>& pts, const std::vector<float>& qs, int k, double r2) {
  const std::size_t N = pts.size() / 3, n = qs.size() / 3;
  Ref r;
  r.d.assign(n * k, INFINITY);
  r.ids.assign(n * k, -1);
  r.counts.assign(n, 0);
  std::vector<std::pair<double, std::int32_t>> all(N);
  for (std::size_t q = 0; q < n; ++q) {
    std::size_t m = 0;
    for (std::size_t i = 0; i < N; ++i) {
      double dx = double(qs[3 * q]) - pts[3 * i], dy = double(qs[3 * q + 1]) - pts[3 * i + 1],
             dz = double(qs[3 * q + 2]) - pts[3 * i + 2];
      double d = dx * dx + dy * dy + dz * dz;
      if (d <= r2) all[m++] = {d, static_cast<std::int32_t>(i)};
    }
    const std::size_t c = std::min<std::size_t>(m, k);
    std::partial_sort(all.begin(), all.begin() + c, all.begin() + m);
    for (std::size_t j = 0; j < c; ++j) {
      r.d[q * k + j] = all[j].first;
      r.ids[q * k + j] = all[j].second;
    }
    r.counts[q] = static_cast<int>(c);
  }
  return r;
}

double true_d2(const std::vector<float>& pts, const std::vector<float>& qs, std::size_t q, std::int32_t id) {
  double s = 0;
  for (int d = 0; d < 3; ++d) {
    double t = double(qs[3 * q + d]) - pts[3 * std::size_t(id) + d];
    s += t * t;
  }
  return s;
}

bool close(double a, double b) {
  if (a == b) return true;
  return std::fabs(a - b) <= 1e-6 * std::max(std::fabs(a), std::fabs(b));
}

// Every row of `got` holds the true k nearest: the true distance of each returned id equals the
// reference's at that rank (ties in either order), and the reported distance is the true one
// rounded to float (+inf above FLT_MAX).
void check_exact(const KnnResult& got, const Ref& ref, const std::vector<float>& pts,
                 const std::vector<float>& qs, const std::string& what) {
  const int k = got.k;
  std::size_t bad = 0;
  for (std::size_t q = 0; q < got.n; ++q) {
    bool ok = got.counts[q] == ref.counts[q];
    for (int j = 0; ok && j < got.counts[q]; ++j) {
      const std::int32_t id = got.id(q, j);
      ok = id >= 0 && static_cast<std::size_t>(id) < pts.size() / 3;
      if (!ok) break;
      const double t = true_d2(pts, qs, q, id);
      ok = close(t, ref.d[q * k + j]);
      const float reported = got.d2(q, j);
      if (t > double(std::numeric_limits<float>::max())) ok = ok && std::isinf(reported);
      // (A subnormal float has fewer digits: the true value rounded to float, within an ulp.)
      else ok = ok && (close(reported, t) || std::fabs(double(reported) - t) <= 2 * 1.4013e-45);
    }
    if (!ok) {
      if (bad < 3) {
        std::ostringstream os;
        os << what << ": row " << q << " count " << got.counts[q] << " (ref " << ref.counts[q] << ") first id "
           << got.id(q, 0) << " d2 " << got.d2(q, 0) << " (ref id " << ref.ids[q * k] << " d2 " << ref.d[q * k] << ")";
        MESSAGE(os.str());
      }
      ++bad;
    }
  }
  CHECK_MESSAGE(bad == 0, what << ": " << bad << " of " << got.n << " rows are not the true k nearest");
}

std::vector<std::unique_ptr<Index>> exact_indexes(const std::vector<float>& pts) {
  std::vector<std::unique_ptr<Index>> v;
  const std::size_t N = pts.size() / 3;
  v.push_back(std::make_unique<BruteForceIndex>(test::runtime(), pts.data(), N));
  v.push_back(std::make_unique<KdTreeIndex>(test::runtime(), pts.data(), N));
#if BHCL_HAVE_FLANN
  v.push_back(std::make_unique<FlannIndex>(test::runtime(), pts.data(), N));
#endif
  return v;
}

std::vector<float> unit_points(std::size_t n, std::uint32_t seed) {
  std::mt19937 g(seed);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::vector<float> v(3 * n);
  for (auto& x : v) x = u(g);
  return v;
}

void run_case(const std::vector<float>& pts, const std::vector<float>& qs, const std::string& name) {
  for (const auto& index : exact_indexes(pts)) {
    for (int k : {1, 10}) {
      for (float r : {INFINITY, 0.05f}) {
        SearchParams p = test::knn_params(k);
        p.max_radius = r;
        const double r2 = std::isinf(r) ? INFINITY : double(r) * double(r);
        const Ref ref = double_knn(pts, qs, k, r2);
        KnnResult got;
        index->query(qs.data(), qs.size() / 3, p, got);
        check_exact(got, ref, pts, qs, name + " " + index->method() + " k=" + std::to_string(k) + " r=" + std::to_string(r));
      }
    }
    // Radius search: the exact set within r of each query.
    const float r = 0.05f;
    RadiusResult rr;
    index->radius_search(qs.data(), qs.size() / 3, r, RadiusParams{}, rr);
    const std::size_t n = qs.size() / 3, N = pts.size() / 3;
    std::size_t bad = 0;
    for (std::size_t q = 0; q < n; ++q) {
      std::set<std::int32_t> want, have(rr.ids.begin() + rr.offsets[q], rr.ids.begin() + rr.offsets[q + 1]);
      for (std::size_t i = 0; i < N; ++i)
        if (true_d2(pts, qs, q, static_cast<std::int32_t>(i)) <= double(r) * double(r)) want.insert(static_cast<std::int32_t>(i));
      if (want != have) ++bad;
    }
    CHECK_MESSAGE(bad == 0, name << " " << index->method() << " radius: " << bad << " of " << n << " slices differ");
  }
}

}  // namespace

TEST_CASE("exact extreme: one far outlier among unit-cube points (1e19 .. 3e38)") {
  const std::size_t N = 6000;
  std::vector<float> qs = unit_points(300, 7);
  for (float far : {1e19f, 1e21f, 3e24f, 1e30f, 3e38f}) {
    std::vector<float> pts = unit_points(N, 1);
    pts.insert(pts.end(), {far, far, far});
    std::vector<float> q = qs;
    q.insert(q.end(), {far, far, far});            // the outlier itself
    q.insert(q.end(), {far * 0.5f, 0.0f, 0.0f});   // between: every distance overflows
    q.insert(q.end(), {pts[0], pts[1], pts[2]});   // a point itself (distance 0)
    run_case(pts, q, "outlier " + std::to_string(far));
  }
}

TEST_CASE("exact extreme: the Hilbert dispatch at an extreme scale (queries gathered and scaled in the sort's pass) answers as the given order") {
  // Points and queries in a cube of side 1e25 (squared distances past FLT_MAX): the structure's
  // coordinates are scaled by 2^-e, and on a CPU device the sorted dispatch gathers and scales the
  // queries in the sort's last pass; its rows must equal the given order's, and the exact answer.
  std::vector<float> pts = unit_points(6000, 4);
  std::vector<float> qs = unit_points(2000, 5);
  for (auto& x : pts) x *= 1e25f;
  for (auto& x : qs) x *= 1e25f;
  qs.insert(qs.end(), {pts[0], pts[1], pts[2], NAN, 0.0f, 0.0f});
  const Ref ref = double_knn(pts, qs, 10, INFINITY);
  for (const auto& index : exact_indexes(pts)) {
    SearchParams given = test::knn_params(10), sorted = test::knn_params(10);
    given.sort_queries = 0;
    sorted.sort_queries = 1;
    KnnResult a, b;
    index->query(qs.data(), qs.size() / 3, given, a);
    index->query(qs.data(), qs.size() / 3, sorted, b);
    test::require_identical(b, a, index->method() + ": sorted dispatch at scale 1e25");
    check_exact(b, ref, pts, qs, index->method() + " sorted, scale 1e25");
  }
}

TEST_CASE("exact extreme: mixed scales (clusters at 1e-20 and 1, outliers of both signs)") {
  std::vector<float> pts = unit_points(3000, 2);
  std::vector<float> tiny = unit_points(2000, 3);
  for (auto& x : tiny) x *= 1e-20f;
  pts.insert(pts.end(), tiny.begin(), tiny.end());
  pts.insert(pts.end(), {-3e38f, 3e38f, 0.0f, 3e38f, -3e38f, 1e-30f, 1e25f, 0.0f, 0.0f});
  std::vector<float> qs = unit_points(150, 8);
  std::vector<float> qt = unit_points(150, 9);
  for (auto& x : qt) x *= 1e-20f;
  qs.insert(qs.end(), qt.begin(), qt.end());
  qs.insert(qs.end(), {0.0f, 0.0f, 0.0f, -3e38f, 3e38f, 0.0f, 1e-40f, 0.0f, 0.0f});
  run_case(pts, qs, "mixed scales");
}

}  // namespace bhcl

#if BHCL_HAVE_FLANN
namespace bhcl {
TEST_CASE("bounded work: coincident points, FLANN within 3x brute force and identical to it") {
  // FLANN visits every point that ties the k-th distance: before the guard, N identical points
  // cost it a full scan per query (2M points: 43-65 s, 11x brute force).
  const std::size_t N = 400000, n = 400;
  std::vector<float> pts(3 * N);
  for (std::size_t i = 0; i < N; ++i) {
    pts[3 * i] = 0.25f;
    pts[3 * i + 1] = 0.5f;
    pts[3 * i + 2] = 0.75f;
  }
  for (std::size_t i = 0; i < 1000; ++i) pts[3 * (i * 397)] = 0.25f + float(i) * 1e-3f;  // a few apart
  const std::vector<float> qs = unit_points(n, 11);
  SearchParams p = test::knn_params(16);
  auto timed = [&](auto make) {
    auto t0 = std::chrono::steady_clock::now();
    auto index = make();
    KnnResult r;
    index->query(qs.data(), n, p, r);
    RadiusResult rr;
    index->radius_search(qs.data(), 4, 0.3f, RadiusParams{}, rr);
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return std::make_tuple(s, r, rr);
  };
  // Warm the brute-force kernel so that its compile does not count.
  BruteForceIndex(test::runtime(), pts.data(), 1000).warm_up(p);
  const auto [bf_s, bf, bfr] = timed([&] { return std::make_unique<BruteForceIndex>(test::runtime(), pts.data(), N); });
  const auto [fl_s, fl, flr] = timed([&] { return std::make_unique<FlannIndex>(test::runtime(), pts.data(), N); });
  MESSAGE("coincident points N = " << N << ": brute force " << bf_s << " s, flann " << fl_s << " s");
  test::require_identical(fl, bf, "flann on coincident points");
  CHECK(flr.offsets == bfr.offsets);
  CHECK(flr.ids == bfr.ids);
  CHECK(fl_s <= 3 * bf_s + 0.1);
}
}  // namespace bhcl
#endif
