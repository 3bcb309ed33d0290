// Issue 25: float64 point files kept by bhcl (re-centred in double, stored in float32 relative to
// the points' box), recall tuned on the caller's queries (BlockHashIndex::params_for_batch), the
// thread default following the CPUs the process may use.
#include "test_util.hpp"

#include <sched.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <random>

#include <nlohmann/json.hpp>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/kdtree.hpp"
#include "blockhash_cl/metrics.hpp"
#include "blockhash_cl/parallel.hpp"

using namespace bhcl;

namespace {

// UTM-like points (x ~ 5.1e5, y ~ 4.3e6 m, mm decimals) and queries, in double.
void utm_points(std::size_t n, std::uint64_t seed, std::vector<double>& xyz) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  xyz.resize(3 * n);
  for (std::size_t i = 0; i < n; ++i) {
    xyz[3 * i] = std::round((512345.678 + 800.0 * u(rng)) * 1000.0) / 1000.0;
    xyz[3 * i + 1] = std::round((4312345.678 + 800.0 * u(rng)) * 1000.0) / 1000.0;
    xyz[3 * i + 2] = std::round((112.5 + 30.0 * u(rng)) * 1000.0) / 1000.0;
  }
}

std::string write_text(const std::string& name, const std::vector<double>& xyz) {
  const std::string path = test::tmp_path(name);
  std::FILE* f = std::fopen(path.c_str(), "w");
  REQUIRE(f);
  for (std::size_t i = 0; i < xyz.size(); i += 3) std::fprintf(f, "%.3f %.3f %.3f\n", xyz[i], xyz[i + 1], xyz[i + 2]);
  std::fclose(f);
  return path;
}

}  // namespace

TEST_CASE("defaults: io keeps a text file's float64 coordinates and re-centres them") {
  std::vector<double> pts;
  utm_points(500, 1, pts);
  const std::string P = write_text("i25_utm.xyz", pts);
  std::vector<float> as_float;
  const std::vector<double> wide = read_points_file_f64(P, &as_float);
  REQUIRE(wide.size() == pts.size());
  REQUIRE(as_float.size() == pts.size());
  for (std::size_t i = 0; i < pts.size(); ++i) {
    REQUIRE(std::fabs(wide[i] - pts[i]) < 1e-9);  // strtod of "%.3f": the nearest double
    REQUIRE(as_float[i] == static_cast<float>(wide[i]));
  }
  Recentring r = choose_origin(wide.data(), wide.size() / 3);
  REQUIRE(r.recentred);
  CHECK(std::fabs(r.origin[1] - 4312745.678) < 1.0);
  const std::vector<float> rel = relative_points(wide.data(), wide.size() / 3, r, P);
  CHECK(r.max_abs_relative <= 401.0);
  CHECK(r.float32_step <= std::ldexp(1.0, -14));  // 400 m in float: steps of 2^-15 m
  for (std::size_t i = 0; i < pts.size(); ++i) REQUIRE(std::fabs(double(rel[i]) + r.origin[i % 3] - pts[i]) <= 0.5 * r.float32_step);
  // A box around 0 is left as it is (float32 data gives its own answer bit for bit).
  const std::vector<double> unit = {0.0, 0.25, 1.0, 1.0, 0.5, 0.0};
  CHECK_FALSE(choose_origin(unit.data(), 2).recentred);
  // A raw float32 file widens exactly.
  const auto f32 = datasets::uniform(100, 3);
  const std::string R = test::write_points("i25_raw.f32", f32);
  const std::vector<double> w2 = read_points_file_f64(R);
  REQUIRE(w2.size() == f32.size());
  for (std::size_t i = 0; i < f32.size(); ++i) REQUIRE(w2[i] == double(f32[i]));
}

TEST_CASE("defaults: bhcl knn on UTM-like text files gives the exact rows (float64 kept)") {
  std::vector<double> pts, qs;
  utm_points(4000, 2, pts);
  utm_points(200, 3, qs);
  const std::string P = write_text("i25_p.xyz", pts), Q = write_text("i25_q.xyz", qs);
  const int k = 8;
  // The exact answer in double precision.
  std::vector<std::vector<std::pair<double, int>>> truth(200);
  for (std::size_t q = 0; q < 200; ++q) {
    auto& v = truth[q];
    for (std::size_t i = 0; i < 4000; ++i) {
      double d = 0;
      for (int a = 0; a < 3; ++a) d += (qs[3 * q + a] - pts[3 * i + a]) * (qs[3 * q + a] - pts[3 * i + a]);
      v.emplace_back(d, int(i));
    }
    std::partial_sort(v.begin(), v.begin() + k + 1, v.end());
  }
  for (const std::string& method : exact_method_names()) {
    INFO(method);
    const std::string I = test::tmp_path("i25_ids.i32"), D = test::tmp_path("i25_d2.f32"), S = test::tmp_path("i25.json");
    std::string out;
    const int rc = test::run_bhcl("knn --points " + P + " --queries " + Q + " --k " + std::to_string(k) + " --method " +
                                      method + " --out-ids " + I + " --out-dist2 " + D + " --stats " + S + " --quiet",
                                  &out);
    INFO(out);
    REQUIRE(rc == 0);
    const auto ids = test::read_raw<std::int32_t>(I);
    const auto d2 = test::read_raw<float>(D);
    REQUIRE(ids.size() == 200u * k);
    std::size_t wrong = 0, ties = 0;
    for (std::size_t q = 0; q < 200; ++q)
      for (int j = 0; j < k; ++j) {
        const auto& t = truth[q];
        // A rank whose neighbours lie within the stored coordinates' rounding of each other may
        // go either way; every other rank must hold the true id.
        const double tol = 1e-4 * t[j].first + 1e-3;  // d2's change when coordinates move by 2^-15 m
        const bool tie = (j > 0 && t[j].first - t[j - 1].first < tol) || t[j + 1].first - t[j].first < tol;
        if (tie) {
          ++ties;
          continue;
        }
        if (ids[q * k + j] != t[j].second) ++wrong;
        REQUIRE(std::fabs(double(d2[q * k + j]) - t[j].first) <= 1e-5 * t[j].first + 1e-3);
      }
    CHECK(wrong == 0);
    CHECK(ties < 200u * k / 50);
    std::ifstream s(S);
    const nlohmann::json j = nlohmann::json::parse(s);
    CHECK(j.at("coordinates").at("recentred") == true);
    CHECK(j.at("coordinates").at("max_rounding").get<double>() < 5e-5);
  }
}

TEST_CASE("defaults: a block layout's default meets 0.95 on the caller's queries, cached per distribution") {
  // Clustered points, auto's block layout (grid = 0: the L tables, a budget applies),
  // queries on the data and over the data's box. (The paper preset reaches recall@10 0.3-0.45 at
  // A = 128 here: tuned_reached false, which the stats say.)
  const auto pts = datasets::clustered(20000, 5, 30, 0.03f);
  const auto on = datasets::clustered(3000, 6, 30, 0.03f);
  std::vector<float> spread(3 * 3000);
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  for (auto& v : spread) v = u(rng);
  BlockHashBuildParams bp;
  bp.grid = 0;
  auto index = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3, bp);
  KdTreeIndex exact(test::runtime(), pts.data(), pts.size() / 3);
  const std::vector<float>* batches[] = {&on, &spread};
  for (const std::vector<float>* qs : batches) {
    for (int k : {1, 10}) {
      const std::string where = qs == &on ? "on the data" : "over the box";
      INFO("k = " << k << ", " << where);
      SearchParams p = test::knn_params(k);
      BlockHashIndex::BatchTuning bt;
      const SearchParams run = index->params_for_batch(qs->data(), qs->size() / 3, p, &bt);
      REQUIRE(bt.tuned);
      CHECK_FALSE(bt.cached);
      CHECK(bt.target == BlockHashIndex::kDefaultRecallTarget);
      REQUIRE(run.A == bt.tuning.A);
      CHECK(run.recall_target == 0);
      const KnnResult got = index->query(*qs, run);
      const KnnResult truth = exact.query(*qs, p);
      const double recall = evaluate_accuracy(got, truth).recall;
      MESSAGE("recall " << recall << " at A = " << run.A << ", sample " << bt.tuning.sample << " ("
                        << bt.tuning.recall << "), tuning " << bt.seconds << " s, " << bt.distribution);
      // Met, or said not to be: queries far from every cell a block-layout query probes stay
      // unreached at any A (measured: k = 10 over the box saturates at 0.938 from A = 128 to
      // 1024); the stats say tuned_reached false and the grid layout (exact) is the answer there.
      if (bt.tuning.reached) CHECK(recall >= 0.95);
      else CHECK(run.A == 1024.0f);
      BlockHashIndex::BatchTuning again;
      const SearchParams run2 = index->params_for_batch(qs->data(), qs->size() / 3, p, &again);
      CHECK(again.cached);
      CHECK(run2.A == run.A);
      // (No timing assertion: `cached` says no sample was answered; a check that the cached call
      // was quicker failed on this shared machine at load 11, 12 ms against 7 ms.)
    }
  }
  // An explicit A is left alone.
  SearchParams a8;
  a8.A = 8;
  BlockHashIndex::BatchTuning none;
  CHECK(index->params_for_batch(on.data(), 10, a8, &none).A == 8);
  CHECK_FALSE(none.tuned);
}

TEST_CASE("defaults: the default thread count is the CPUs the process may use") {
  cpu_set_t set;
  CPU_ZERO(&set);
  REQUIRE(sched_getaffinity(0, sizeof set, &set) == 0);
  CHECK(detail::available_cpus() == static_cast<unsigned>(CPU_COUNT(&set)));
  CHECK(detail::default_threads() == detail::available_cpus());
}
