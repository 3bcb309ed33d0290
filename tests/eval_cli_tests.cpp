// bhcl eval: the table and the JSON stats of a method against an exact truth; bad input.
#include "test_util.hpp"

#include <nlohmann/json.hpp>

using namespace bhcl;

namespace {

using test::write_points;

nlohmann::json read_json(const std::string& path) {
  std::ifstream in(path);
  return nlohmann::json::parse(in);  // throws (fails the test) unless valid JSON
}

// A number of the stats; NaN when the key is missing or not a number.
double json_number(const nlohmann::json& j, const std::string& key) {
  return j.contains(key) && j.at(key).is_number() ? j.at(key).get<double>() : NAN;
}

}  // namespace

TEST_CASE("eval_cli: kdtree against the flann truth prints one table and writes the stats") {
  auto pts = datasets::clustered(3000, 401, 6, 0.02f);
  auto qs = datasets::uniform(150, 402);
  std::string P = write_points("eval_p.f32", pts), Q = write_points("eval_q.f32", qs);
  std::string S = test::tmp_path("eval_stats.json");
  std::string out = test::run_bhcl_ok("eval --points " + P + " --queries " + Q +
                              " --k 12 --method kdtree --threads 2 --stats " + S);
  for (const char* row : {"kdtree", "flann (truth)", "build s", "compile s", "query s", "queries/s",
                          "recall", "false negatives", "dilation max", "dilation mean",
                          "mean rel. dist. error", "identical rows", "N=3000 n=150 k=12"})
    CHECK_MESSAGE(out.find(row) != std::string::npos, row);
  const nlohmann::json json = read_json(S);
  INFO(json.dump(2));
  CHECK(json.at("method") == "kdtree");
  CHECK(json.at("truth_method") == "flann");
  CHECK(json.at("command") == "eval");
  CHECK(json.at("version").get<std::string>().size() > 0);
  CHECK(json.at("truth_build").at("threads") == 2);  // flann's --threads, as used
  CHECK(json_number(json, "N") == 3000);
  CHECK(json_number(json, "n") == 150);
  CHECK(json_number(json, "k") == 12);
  // Both exact: every row identical, perfect metrics.
  CHECK(json_number(json, "recall") == 1.0);
  CHECK(json_number(json, "false_negative_rate") == 0.0);
  CHECK(json_number(json, "max_dilation") == 1.0);
  CHECK(json_number(json, "identical_rows") == 150);
  CHECK(json_number(json, "compared_queries") == 150);
  CHECK(json_number(json, "queries_per_s") > 0);
  CHECK(json_number(json, "truth_queries_per_s") > 0);
  CHECK(json_number(json, "build_s") >= 0);
  CHECK(json_number(json, "truth_build_s") >= 0);
}

TEST_CASE("eval_cli: flann against the brute-force truth with a radius: rows cut short are compared") {
  auto [pts, qs, P, Q] = test::cli_inputs("eval2", 2000, 411, 100, 412);
  std::string S = test::tmp_path("eval2_stats.json");
  std::string out = test::run_bhcl_ok("eval --points " + P + " --queries " + Q +
                              " --k 20 --max-radius 0.08 --method flann --truth bruteforce --stats " + S);
  CHECK(out.find("bruteforce (truth)") != std::string::npos);
  const nlohmann::json json = read_json(S);
  INFO(json.dump(2));
  SearchParams p = test::knn_params(20);
  p.max_radius = 0.08f;
  KnnResult ref = reference::knn_float(pts.data(), 2000, qs.data(), 100, p);
  std::size_t nonempty = 0;
  for (auto c : ref.counts) nonempty += c > 0;
  REQUIRE(nonempty < 100);  // the radius empties some rows: they are not compared
  CHECK(json_number(json, "compared_queries") == double(nonempty));
  CHECK(json_number(json, "identical_rows") == double(nonempty));
  CHECK(json_number(json, "recall") == 1.0);
  CHECK(json_number(json, "max_radius") == doctest::Approx(0.08));
}

TEST_CASE("eval_cli: --radius: exact methods find every ball, block hashing most of them, misuse refused") {
  auto pts = datasets::clustered(4000, 431, 6, 0.02f);
  auto qs = datasets::clustered(300, 432, 6, 0.02f);
  std::string P = write_points("eval_r_p.f32", pts), Q = write_points("eval_r_q.f32", qs);
  std::string S = test::tmp_path("eval_r.json");
  std::string out;
  REQUIRE(test::run_bhcl("eval --points " + P + " --queries " + Q + " --radius 0.02 --method kdtree --truth bruteforce "
                         "--quiet --stats " + S, &out) == 0);
  INFO(out);
  for (const char* row : {"points per query", "recall", "found of true points", "missing points", "false positives",
                          "identical slices", "r=0.02"})
    CHECK_MESSAGE(out.find(row) != std::string::npos, row);
  nlohmann::json j = read_json(S);
  CHECK(json_number(j, "recall") == 1.0);
  CHECK(json_number(j, "identical_slices") == 300);
  CHECK(json_number(j, "mean_true") > 2);  // the balls are not empty
  REQUIRE(test::run_bhcl("eval --points " + P + " --queries " + Q + " --radius 0.02 --method blockhash --truth kdtree "
                         "--budget 0 --quiet --stats " + S, &out) == 0);
  j = read_json(S);
  CHECK(json_number(j, "recall") >= 0.9);
  CHECK(json_number(j, "recall") <= 1.0);
  CHECK(json_number(j, "false_positives") == 0);  // a subset of each ball, always
  CHECK(json_number(j, "mean_found") <= json_number(j, "mean_true"));
  // A small budget loses points, never adds any.
  REQUIRE(test::run_bhcl("eval --points " + P + " --queries " + Q + " --radius 0.02 --method blockhash --truth kdtree "
                         "--budget 8 --quiet --stats " + S, &out) == 0);
  const nlohmann::json tight = read_json(S);
  CHECK(json_number(tight, "recall") < json_number(j, "recall"));
  CHECK(json_number(tight, "false_positives") == 0);
  const std::string base = "eval --points " + P + " --queries " + Q + " --method kdtree ";
  CHECK(test::run_bhcl(base + "--radius 0.02 --k 5", &out) == 2);
  CHECK(out.find("--k does not apply with --radius") != std::string::npos);
  CHECK(test::run_bhcl(base + "--radius 0.02 --budget 5", &out) == 2);
  CHECK(out.find("--budget does not apply to method kdtree") != std::string::npos);
  CHECK(test::run_bhcl(base + "--budget 5", &out) == 2);
  CHECK(out.find("--budget applies only with --radius") != std::string::npos);
  CHECK(test::run_bhcl(base + "--radius -1", &out) == 2);
  CHECK(out.find("--radius must be a finite number >= 0") != std::string::npos);
}

TEST_CASE("eval_cli: bad input exits non-zero with one clear line") {
  auto pts = datasets::uniform(100, 421);
  std::string P = write_points("eval_bad_p.f32", pts);
  struct Case {
    std::string args, expect;
    int rc;
  };
  std::vector<Case> cases = {
      {"eval --points " + P + " --queries " + P + " --k 3 --method kdtree --truth nope", "unknown method 'nope'", 1},
      {"eval --points " + P + " --queries " + P + " --k 3 --method nope", "unknown method 'nope'", 1},
      {"eval --points " + P + " --queries " + P + " --k 3", "missing required option --method", 2},
      {"eval --points " + P + " --k 3 --method kdtree", "missing required option --queries", 2},
      {"eval --points " + P + " --queries " + P + " --k 999 --method kdtree", "--k must be in [1, 256]", 2},
      {"eval --points " + P + " --queries " + P + " --k 3 --method kdtree --frob 1", "unknown option --frob", 2},
      {"eval --points /no/such.f32 --queries " + P + " --k 3 --method kdtree", "/no/such.f32: cannot open", 1},
  };
  for (const auto& c : cases) {
    std::string out;
    int rc = test::run_bhcl(c.args, &out);
    INFO(c.args);
    INFO(out);
    CHECK(rc == c.rc);
    CHECK(out.find(c.expect) != std::string::npos);
  }
}

TEST_CASE("eval_cli: bhcl knn --method kdtree and --method flann --threads T write the exact answer") {
  auto pts = datasets::with_duplicates(2000, 431, 0.3);
  std::vector<float> qs(pts.begin(), pts.begin() + 3 * 60);
  std::string P = write_points("knnkd_p.f32", pts), Q = write_points("knnkd_q.f32", qs);
  SearchParams p = test::knn_params(9);
  KnnResult ref = reference::knn_float(pts.data(), 2000, qs.data(), 60, p);
  for (std::string m : {"kdtree", "flann --threads 2"}) {
    CAPTURE(m);
    std::string I = test::tmp_path("knnkd_ids.i32"), D = test::tmp_path("knnkd_d2.f32");
    std::string out = test::run_bhcl_ok("knn --points " + P + " --queries " + Q + " --k 9 --method " + m +
                                " --out-ids " + I + " --out-dist2 " + D);
    CHECK(test::read_raw<std::int32_t>(I) == ref.ids);
    CHECK(test::read_raw<float>(D) == ref.dist2);
  }
}

TEST_CASE("eval_cli: an approximate method's metrics are those of its own knn output") {
  // blockhash (always built) at a budget: the approximate method.
  auto pts = datasets::clustered(5000, 441, 12, 0.03f);
  auto qs = datasets::uniform(300, 442);
  std::string P = write_points("evalbh_p.f32", pts), Q = write_points("evalbh_q.f32", qs);
  std::string I = test::tmp_path("evalbh_ids.i32"), D = test::tmp_path("evalbh_d2.f32"),
              C = test::tmp_path("evalbh_counts.i32"), S = test::tmp_path("evalbh_stats.json");
  std::string out;
  REQUIRE(test::run_bhcl("knn --points " + P + " --queries " + Q + " --k 10 --A 1 --method blockhash" +
                             " --out-ids " + I + " --out-dist2 " + D + " --out-counts " + C,
                         &out) == 0);
  int rc = test::run_bhcl("eval --points " + P + " --queries " + Q +
                              " --k 10 --A 1 --method blockhash --truth bruteforce --stats " + S,
                          &out);
  INFO(out);
  REQUIRE(rc == 0);
  KnnResult approx;
  approx.resize(300, 10);
  approx.ids = test::read_raw<std::int32_t>(I);
  approx.dist2 = test::read_raw<float>(D);
  approx.counts = test::read_raw<std::int32_t>(C);
  SearchParams p = test::knn_params(10);
  Accuracy a = evaluate_accuracy(approx, reference::knn_float(pts.data(), 5000, qs.data(), 300, p));
  const nlohmann::json json = read_json(S);
  INFO(json.dump(2));
  CHECK(json_number(json, "recall") == doctest::Approx(a.recall).epsilon(1e-8));
  CHECK(json_number(json, "false_negative_rate") == doctest::Approx(a.false_negative_rate).epsilon(1e-8));
  CHECK(json_number(json, "max_dilation") == doctest::Approx(a.max_dilation).epsilon(1e-8));
  CHECK(json_number(json, "mean_dilation") == doctest::Approx(a.mean_dilation).epsilon(1e-8));
  CHECK(json_number(json, "mean_rel_distance_error") ==
        doctest::Approx(a.mean_rel_distance_error).epsilon(1e-6));
  CHECK(json_number(json, "identical_rows") == double(a.identical_rows));
  MESSAGE("blockhash A=1 recall " << a.recall);
}

TEST_CASE("eval_cli: blockhash with --recall reaches the target and records the tuned A") {
  auto [pts, qs, P, Q] = test::cli_inputs("eval_recall", 30000, 411, 1000, 412);
  std::string S = test::tmp_path("eval_recall_stats.json");
  std::string out = test::run_bhcl_ok("eval --points " + P + " --queries " + Q +
                              " --k 10 --method blockhash --recall 0.95 --truth kdtree --stats " + S);
  const nlohmann::json json = read_json(S);
  INFO(json.dump(2));
  CHECK(json.at("search").at("recall_target") == 0.95);
  CHECK(json.at("search").at("A").get<double>() > 0);
  CHECK(json.at("search").at("tuned_reached") == true);
  CHECK(json_number(json, "recall") >= 0.94);
  // A usage mistake: both knobs, or a target outside [0, 1].
  CHECK(test::run_bhcl("eval --points " + P + " --queries " + Q + " --method blockhash --recall 0.9 --A 4", &out) == 2);
  CHECK(test::run_bhcl("eval --points " + P + " --queries " + Q + " --method blockhash --recall 1.5", &out) == 2);
  CHECK(test::run_bhcl("eval --points " + P + " --queries " + Q + " --method kdtree --recall 0.9", &out) == 2);
}
