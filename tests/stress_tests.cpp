// The stress suite (CTest label "stress"): every method of method_names() on generated hard
// cases. No crash; exact methods equal the double-precision reference (ids with the tie rule,
// distances within float rounding); approximate methods return valid, unique, sorted rows;
// builds stay near-linear on duplicates.
#include <chrono>
#include <functional>
#include <map>
#include <random>

#include "test_util.hpp"

using namespace bhcl;

namespace {

struct Case {
  std::string name;
  std::vector<float> pts, qs;
  std::vector<int> ks = {1, 10, 64};
  float max_radius = INFINITY;
};

std::vector<float> scaled_uniform(std::size_t n, std::uint64_t seed, double scale, double offset = 0) {
  auto v = datasets::uniform(n, seed);
  for (auto& x : v) x = static_cast<float>(double(x) * scale + offset);
  return v;
}

std::vector<Case> make_cases() {
  std::vector<Case> cs;
  const std::size_t N = 2000, n = 150;
  for (double off : {1e4, 1e5, 1e6, 1e7})
    cs.push_back({"offset " + std::to_string(off), scaled_uniform(N, 1, 100.0, off),
                  scaled_uniform(n, 2, 100.0, off)});
  cs.push_back({"tiny box 1e-20", scaled_uniform(N, 3, 1e-20), scaled_uniform(n, 4, 1e-20)});
  cs.push_back({"huge box 1e30", scaled_uniform(N, 5, 1e30), scaled_uniform(n, 6, 1e30)});
  cs.push_back({"subnormal coordinates", scaled_uniform(N, 7, 1e-40), scaled_uniform(n, 8, 1e-40)});
  cs.push_back({"all points identical", std::vector<float>(3 * N, 0.375f), scaled_uniform(n, 9, 1.0)});
  cs.push_back({"1% duplicates", datasets::with_duplicates(N, 10, 0.01), datasets::uniform(n, 11)});
  cs.push_back({"50% duplicates, queries on points", datasets::with_duplicates(N, 12, 0.5), {}});
  cs.back().qs.assign(cs.back().pts.begin(), cs.back().pts.begin() + 3 * n);
  {
    auto flat = datasets::uniform(N, 13), fq = datasets::uniform(n, 14);
    for (std::size_t i = 0; i < N; ++i) flat[3 * i + 2] = 0.5f;
    for (std::size_t i = 0; i < n; ++i) fq[3 * i + 2] = 0.5f + 1e-3f * float(i % 3);
    cs.push_back({"flat (coplanar), queries on and just off the plane", flat, fq});
    auto line = datasets::uniform(N, 15), lq = datasets::uniform(n, 16);
    for (std::size_t i = 0; i < N; ++i) line[3 * i + 1] = line[3 * i + 2] = 0.25f;
    cs.push_back({"collinear", line, lq});
  }
  {
    auto a = datasets::clustered(N, 17, 2, 1e-3f);
    for (std::size_t i = N / 2; i < N; ++i) a[3 * i] += 1e6f;
    auto q = datasets::clustered(n, 18, 2, 1e-3f);
    for (std::size_t i = n / 2; i < n; ++i) q[3 * i] += 1e6f;
    cs.push_back({"two tight clusters far apart", a, q});
  }
  cs.push_back({"N = 1", {0.1f, 0.2f, 0.3f}, datasets::uniform(n, 19), {1, 5}});
  cs.push_back({"N < k", datasets::uniform(5, 20), datasets::uniform(n, 21), {3, 32, 256}});
  {
    auto far = datasets::uniform(n, 22);
    for (auto& x : far) x = x * 10.0f + 1e6f;
    cs.push_back({"queries far outside the bounds", datasets::uniform(N, 23), far});
  }
  cs.push_back({"k from 1 to the maximum", datasets::uniform(N, 24), datasets::uniform(60, 25),
                {1, 2, 3, 8, 9, 16, 17, 31, 100, 255, 256}});
  cs.push_back({"maximum radius", datasets::uniform(N, 26), datasets::uniform(n, 27), {1, 10, 64}, 0.05f});
  {
    const std::string autzen = test::data_file("autzen.xyz.f32");
    if (!autzen.empty()) {
      auto pts = read_points_file(autzen);
      pts.resize(3 * 20000);
      datasets::offset(pts, 637291.0, 851210.0, 511.0);  // georeferenced: a float32 step is 0.06 ft
      std::vector<float> qs(pts.begin(), pts.begin() + 3 * n);
      for (std::size_t i = 0; i < qs.size(); i += 3) qs[i] += 0.5f;
      cs.push_back({"Autzen LiDAR with its georeferencing offset", pts, qs});
    } else {
      MESSAGE("Autzen case skipped: autzen.xyz.f32 is not in BHCL_DATA_DIR");
    }
  }
  return cs;
}

const std::vector<Case>& cases() {
  static const std::vector<Case> cs = make_cases();
  return cs;
}

}  // namespace

TEST_SUITE("stress") {
  TEST_CASE("stress: block hashing's host reference and examined counts take the query path") {
    // One query path: the host reference and the per-query examined counts scale coordinates as
    // query() does, so on every hard case (1e-20 and 1e30 boxes, subnormals included) they give
    // the kernel's rows, distances in the caller's units.
    auto rt = test::runtime();
    for (const char* preset : {"auto", "paper"}) {
      for (const auto& c : cases()) {
        const std::size_t N = c.pts.size() / 3, n = c.qs.size() / 3;
        CAPTURE(preset);
        CAPTURE(c.name);
        BlockHashBuildParams bp;
        bp.preset = BlockHashBuildParams::parse_preset(preset);
        auto index = BlockHashIndex::build(rt, c.pts.data(), N, bp);
        for (int k : c.ks) {
          CAPTURE(k);
          SearchParams p = test::knn_params(k);
          p.max_radius = c.max_radius;
          p.sort_queries = 0;
          KnnResult r = index->query(c.qs, p);
          std::vector<std::int32_t> ex_ref;
          KnnResult ref = index->reference_query(c.qs.data(), n, p, &ex_ref);
          SearchParams pe = p;
          pe.count_examined = true;
          KnnResult rex = index->query(c.qs, pe);
          const std::vector<std::int32_t>& ex = rex.examined;
          REQUIRE(ref.ids == r.ids);
          REQUIRE(rex.ids == r.ids);
          REQUIRE(ref.counts == r.counts);
          REQUIRE(ex == ex_ref);
          for (std::size_t i = 0; i < r.dist2.size(); ++i) {
            INFO("entry " << i);
            const bool both_inf = std::isinf(r.dist2[i]) && std::isinf(ref.dist2[i]) && std::isinf(rex.dist2[i]);
            REQUIRE((both_inf || (ref.dist2[i] == r.dist2[i] && rex.dist2[i] == r.dist2[i])));
          }
        }
      }
    }
  }

  TEST_CASE("stress: every method on the hard cases") {
    auto rt = test::runtime();
    std::map<std::string, int> runs;
    for (const auto& method : method_names()) {
      for (const auto& c : cases()) {
        const std::size_t N = c.pts.size() / 3, n = c.qs.size() / 3;
        CAPTURE(method);
        CAPTURE(c.name);
        std::unique_ptr<Index> index;
        REQUIRE_NOTHROW(index = make_index(method, rt, c.pts.data(), N));
        for (int k : c.ks) {
          CAPTURE(k);
          SearchParams p = test::knn_params(k);
          p.max_radius = c.max_radius;
          KnnResult r;
          REQUIRE_NOTHROW(index->query(c.qs.data(), n, p, r));
          if (index->exact()) {
            test::check_exact_vs_double(r, c.pts.data(), N, c.qs.data(), n, p);
          } else {
            test::check_contract(r, c.pts.data(), N, c.qs.data(), p);
            std::size_t found = 0;
            for (auto cnt : r.counts) found += static_cast<std::size_t>(cnt);
            CHECK(found > 0);
          }
          ++runs[method];
        }
      }
    }
    for (const auto& [m, count] : runs) MESSAGE(m << ": " << count << " stress cases (data set x k) run");
  }

  TEST_CASE("stress: empty input and bad points are refused by every method") {
    auto rt = test::runtime();
    std::vector<float> pts = datasets::uniform(100, 1);
    for (const auto& method : method_names()) {
      CAPTURE(method);
      CHECK_THROWS_WITH_AS(make_index(method, rt, pts.data(), 0), doctest::Contains("empty"), Error);
      auto bad = pts;
      bad[3 * 42] = INFINITY;
      CHECK_THROWS_WITH_AS(make_index(method, rt, bad.data(), 100), doctest::Contains("point 42"), Error);
      bad[3 * 42] = NAN;
      CHECK_THROWS_WITH_AS(make_index(method, rt, bad.data(), 100), doctest::Contains("point 42"), Error);
    }
  }

  TEST_CASE("stress: non-finite queries get empty rows in every method, the rest are answered") {
    auto rt = test::runtime();
    std::vector<float> pts = datasets::uniform(1000, 2), qs = datasets::uniform(50, 3);
    qs[3 * 7] = NAN;
    qs[3 * 8 + 1] = -INFINITY;
    for (const auto& method : method_names()) {
      CAPTURE(method);
      auto index = make_index(method, rt, pts.data(), 1000);
      SearchParams p = test::knn_params(10);
      QueryStats st;
      KnnResult r = index->query(qs, p, &st);
      CHECK(st.nonfinite_queries == 2);
      CHECK(r.counts[7] == 0);
      CHECK(r.counts[8] == 0);
      CHECK(r.id(7, 0) == -1);
      for (std::size_t q = 0; q < 50; ++q)
        if (q != 7 && q != 8) CHECK(r.counts[q] > 0);
    }
  }

  TEST_CASE("stress: builds stay near-linear on duplicates") {
    // A blow-up detector, not a benchmark: a quadratic build on 200k identical points would take
    // minutes; the bound is generous against machine noise.
    auto rt = test::runtime();
    const std::size_t N = 200000;
    std::vector<float> uni = datasets::uniform(N, 4);
    std::vector<float> same(3 * N, 0.5f);
    std::vector<float> half = datasets::with_duplicates(N, 5, 0.5);
    for (const auto& method : method_names()) {
      CAPTURE(method);
      auto time_build = [&](const std::vector<float>& pts) {
        auto t0 = std::chrono::steady_clock::now();
        auto index = make_index(method, rt, pts.data(), N);
        return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      };
      double t_uni = time_build(uni), t_same = time_build(same), t_half = time_build(half);
      MESSAGE(method << " build of 200k points: uniform " << t_uni << " s, all identical " << t_same
                     << " s, 50% duplicates " << t_half << " s");
      CHECK(t_same < 10 * t_uni + 2.0);
      CHECK(t_half < 10 * t_uni + 2.0);
    }
  }
}

TEST_SUITE("stress") {
TEST_CASE("stress: extreme scales through the buffer-level call equal the host-array call") {
  auto rt = test::runtime();
  for (double scale : {1e30, 1e-20}) {
    CAPTURE(scale);
    auto pts = datasets::uniform(1500, 31), qs = datasets::uniform(100, 32);
    for (auto& x : pts) x = static_cast<float>(x * scale);
    for (auto& x : qs) x = static_cast<float>(x * scale);
    for (const auto& method : method_names()) {
      CAPTURE(method);
      auto index = make_index(method, rt, pts.data(), 1500);
      SearchParams p = test::knn_params(9);
      KnnResult host = index->query(qs, p);
      KnnResult buf = test::buffer_query(*index, qs, p);
      CHECK(buf.ids == host.ids);
      CHECK(buf.dist2 == host.dist2);
      CHECK(buf.counts == host.counts);
    }
  }
}

TEST_CASE("stress: results do not depend on batch size, work-group size or query order") {
  auto rt = test::runtime();
  auto pts = datasets::cornell_photons(5000, 41);
  auto qs = datasets::cornell_queries(700, 42);
  qs[3 * 5] = NAN;  // a non-finite query inside the batch
  for (const auto& method : method_names()) {
    CAPTURE(method);
    auto index = make_index(method, rt, pts.data(), 5000);
    SearchParams p = test::knn_params(12);
    KnnResult base = index->query(qs, p);
    struct Variant { std::size_t local, batch; bool sort; };
    for (Variant v : {Variant{16, 0, false}, Variant{128, 0, false}, Variant{0, 97, false},
                      Variant{0, 0, true}, Variant{32, 250, true}}) {
      CAPTURE(v.local);
      CAPTURE(v.batch);
      CAPTURE(v.sort);
      SearchParams q = p;
      q.local_size = v.local;
      q.max_batch = v.batch;
      q.sort_queries = v.sort;
      KnnResult r = index->query(qs, q);
      CHECK(r.ids == base.ids);
      CHECK(r.dist2 == base.dist2);
      CHECK(r.counts == base.counts);
    }
  }
}

TEST_CASE("stress: results do not depend on PoCL's thread count (or FLANN's)") {
  auto pts = datasets::clustered(20000, 51, 8, 0.02f);
  auto qs = datasets::clustered(3000, 52, 8, 0.02f);
  std::string P = test::tmp_path("threads_p.f32"), Q = test::tmp_path("threads_q.f32");
  write_points_file(P, pts);
  write_points_file(Q, qs);
  for (const auto& method : method_names()) {
    CAPTURE(method);
    std::vector<std::vector<std::int32_t>> ids;
    std::vector<std::vector<float>> d2;
    for (int threads : {1, 2, 3}) {
      std::string I = test::tmp_path("threads_ids"), D = test::tmp_path("threads_d2");
      std::string out;
      // --threads is FLANN's own (bhcl refuses it for the other methods).
      const std::string flann_threads = method == "flann" ? " --threads " + std::to_string(threads) : "";
      int rc = test::run_bhcl("knn --points " + P + " --queries " + Q + " --k 20 --method " + method +
                                  flann_threads + " --out-ids " + I + " --out-dist2 " + D,
                              &out, "POCL_MAX_PTHREAD_COUNT=" + std::to_string(threads));
      INFO(out);
      REQUIRE(rc == 0);
      ids.push_back(test::read_raw<std::int32_t>(I));
      d2.push_back(test::read_raw<float>(D));
    }
    CHECK(ids[0] == ids[1]);
    CHECK(ids[0] == ids[2]);
    CHECK(d2[0] == d2[1]);
    CHECK(d2[0] == d2[2]);
  }
}

TEST_CASE("stress: n x k that overflows the index type is refused, never wrapped") {
  auto rt = test::runtime();
  auto pts = datasets::uniform(100, 61);
  cl::Buffer small(rt->context(), CL_MEM_READ_WRITE, 64);
  ResultBuffers out{small, small, small};
  SearchParams p = test::knn_params(256);
  for (const auto& method : method_names()) {
    CAPTURE(method);
    auto index = make_index(method, rt, pts.data(), 100);
    const std::size_t huge = std::numeric_limits<std::size_t>::max() / 100;
    CHECK_THROWS_WITH_AS(index->enqueue_query(rt->queue(), small, huge, out, p),
                         doctest::Contains("overflows"), Error);
    // A count that fits but exceeds the caller's buffers: refused before any kernel runs.
    CHECK_THROWS_WITH_AS(index->enqueue_query(rt->queue(), small, 1000, out, p),
                         doctest::Contains("bytes"), Error);
  }
}
}
