// The accuracy metrics on hand-made results whose answers are worked out by hand.
#include "test_util.hpp"

using namespace bhcl;

namespace {

// A result of rows given as (id, squared distance) lists; each row may be shorter than k.
KnnResult make(int k, const std::vector<std::vector<std::pair<int, float>>>& rows) {
  KnnResult r;
  r.resize(rows.size(), k);
  for (std::size_t q = 0; q < rows.size(); ++q) {
    REQUIRE(rows[q].size() <= static_cast<std::size_t>(k));
    for (std::size_t j = 0; j < rows[q].size(); ++j) {
      r.ids[q * k + j] = rows[q][j].first;
      r.dist2[q * k + j] = rows[q][j].second;
    }
    r.counts[q] = static_cast<int>(rows[q].size());
  }
  return r;
}

// One query, k = 4, true neighbours 0..3 at squared distances 1, 4, 9, 16.
KnnResult truth4() { return make(4, {{{0, 1.0f}, {1, 4.0f}, {2, 9.0f}, {3, 16.0f}}}); }

}  // namespace

TEST_CASE("metrics: a result equal to the truth is perfect") {
  KnnResult t = make(3, {{{5, 0.5f}, {2, 1.0f}, {9, 2.0f}}, {{1, 0.0f}, {4, 0.0f}, {3, 7.0f}}});
  Accuracy a = evaluate_accuracy(t, t);
  CHECK(a.queries == 2);
  CHECK(a.recall == 1.0);
  CHECK(a.false_negative_rate == 0.0);
  CHECK(a.max_dilation == 1.0);
  CHECK(a.mean_dilation == 1.0);
  CHECK(a.mean_rel_distance_error == 0.0);
  CHECK(a.incomplete_queries == 0);
  CHECK(a.identical_rows == 2);
}

TEST_CASE("metrics: one wrong neighbour, by hand") {
  // Rank 3 is point 5 at distance 5 instead of point 3 at distance 4.
  KnnResult approx = make(4, {{{0, 1.0f}, {1, 4.0f}, {2, 9.0f}, {5, 25.0f}}});
  Accuracy a = evaluate_accuracy(approx, truth4());
  CHECK(a.queries == 1);
  CHECK(a.recall == doctest::Approx(0.75));
  CHECK(a.false_negative_rate == doctest::Approx(0.25));
  CHECK(a.max_dilation == doctest::Approx(1.25));  // sqrt(25 / 16)
  CHECK(a.mean_dilation == doctest::Approx(1.25));
  CHECK(a.mean_rel_distance_error == doctest::Approx(0.25 / 4));  // (5 - 4) / 4 at one rank of 4
  CHECK(a.identical_rows == 0);
  CHECK(a.incomplete_queries == 0);
  CHECK(a.summary().find("recall 0.7500") != std::string::npos);
  CHECK(a.summary().find("FN 0.2500") != std::string::npos);
}

TEST_CASE("metrics: a tie swapped for an equally near point is not punished by recall") {
  // Point 7 ties point 3 at the k-th distance: recall 1, but by index one true neighbour is
  // missing (the talk's false negatives count it).
  KnnResult approx = make(4, {{{0, 1.0f}, {1, 4.0f}, {2, 9.0f}, {7, 16.0f}}});
  Accuracy a = evaluate_accuracy(approx, truth4());
  CHECK(a.recall == 1.0);
  CHECK(a.false_negative_rate == doctest::Approx(0.25));
  CHECK(a.max_dilation == 1.0);
  CHECK(a.mean_rel_distance_error == 0.0);
  CHECK(a.identical_rows == 0);
  // A distance within the 1e-6 relative tolerance of the k-th also counts; one beyond it does not.
  KnnResult near = make(4, {{{0, 1.0f}, {1, 4.0f}, {2, 9.0f}, {7, 16.000008f}}});
  CHECK(evaluate_accuracy(near, truth4()).recall == 1.0);
  KnnResult beyond = make(4, {{{0, 1.0f}, {1, 4.0f}, {2, 9.0f}, {7, 16.01f}}});
  CHECK(evaluate_accuracy(beyond, truth4()).recall == doctest::Approx(0.75));
}

TEST_CASE("metrics: the same neighbours in a different order") {
  // Ranks 1 and 2 swapped (an unsorted row): every true neighbour is there and within the k-th
  // distance, so recall and FN are perfect. The relative error is signed, per rank: +0.5 at rank
  // 1 (3 vs 2) and -1/3 at rank 2 (2 vs 3). (Sorted rows can only have errors >= 0.)
  KnnResult approx = make(4, {{{0, 1.0f}, {2, 9.0f}, {1, 4.0f}, {3, 16.0f}}});
  Accuracy a = evaluate_accuracy(approx, truth4());
  CHECK(a.recall == 1.0);
  CHECK(a.false_negative_rate == 0.0);
  CHECK(a.max_dilation == 1.0);
  CHECK(a.mean_rel_distance_error == doctest::Approx((0.5 - 1.0 / 3.0) / 4));
}

TEST_CASE("metrics: incomplete rows count as misses and are left out of dilation") {
  KnnResult approx = make(4, {{{0, 1.0f}, {1, 4.0f}}});
  Accuracy a = evaluate_accuracy(approx, truth4());
  CHECK(a.recall == doctest::Approx(0.5));
  CHECK(a.false_negative_rate == doctest::Approx(0.5));
  CHECK(a.incomplete_queries == 1);
  CHECK(a.max_dilation == 1.0);  // no complete row: the neutral value
  CHECK(a.mean_dilation == 1.0);
  CHECK(a.mean_rel_distance_error == 0.0);  // ranks 0 and 1 are exact
  CHECK(a.identical_rows == 0);
}

TEST_CASE("metrics: means over queries, empty truth rows skipped") {
  // q0 exact; q1 has one of two neighbours and a k-th distance twice the true one; q2's truth is
  // empty (nothing within the radius) and is not counted.
  KnnResult truth = make(2, {{{0, 1.0f}, {1, 4.0f}}, {{2, 1.0f}, {3, 4.0f}}, {}});
  KnnResult approx = make(2, {{{0, 1.0f}, {1, 4.0f}}, {{2, 1.0f}, {9, 16.0f}}, {}});
  Accuracy a = evaluate_accuracy(approx, truth);
  CHECK(a.queries == 2);
  CHECK(a.recall == doctest::Approx(0.75));  // (1 + 0.5) / 2
  CHECK(a.false_negative_rate == doctest::Approx(0.25));  // 1 of 4 true neighbours missing
  CHECK(a.max_dilation == doctest::Approx(2.0));  // sqrt(16 / 4)
  CHECK(a.mean_dilation == doctest::Approx(1.5));  // (1 + 2) / 2
  CHECK(a.mean_rel_distance_error == doctest::Approx(1.0 / 4));  // (4 - 2) / 2 at one rank of 4
  CHECK(a.identical_rows == 1);
}

TEST_CASE("metrics: zero true distances are left out of the ratios") {
  // Duplicates of the query: the true k-th distance is 0, a dilation would divide by zero.
  KnnResult truth = make(2, {{{0, 0.0f}, {1, 0.0f}}, {{2, 0.0f}, {3, 1.0f}}});
  KnnResult approx = make(2, {{{0, 0.0f}, {5, 4.0f}}, {{2, 0.0f}, {3, 1.0f}}});
  Accuracy a = evaluate_accuracy(approx, truth);
  CHECK(a.recall == doctest::Approx(0.75));
  CHECK(a.max_dilation == 1.0);  // q0 skipped (true k-th 0), q1 exact
  CHECK(a.mean_dilation == 1.0);
  CHECK(a.mean_rel_distance_error == 0.0);  // only q1's rank 1 has a non-zero true distance
}

TEST_CASE("metrics: an all-empty truth gives perfect scores over zero queries") {
  KnnResult truth = make(3, {{}, {}});
  Accuracy a = evaluate_accuracy(truth, truth);
  CHECK(a.queries == 0);
  CHECK(a.recall == 1.0);
  CHECK(a.false_negative_rate == 0.0);
}

TEST_CASE("metrics: on real results, an exact method scores perfectly") {
  auto pts = datasets::clustered(2000, 301, 5, 0.02f);
  auto qs = datasets::uniform(200, 302);
  SearchParams p = test::knn_params(10);
  KnnResult truth = reference::knn_float(pts.data(), 2000, qs.data(), 200, p);
  Accuracy a = evaluate_accuracy(truth, truth);
  CHECK(a.identical_rows == 200);
  CHECK(a.recall == 1.0);
  // Dropping the last neighbour of every row: the k-th is missing everywhere.
  KnnResult cut = truth;
  for (std::size_t q = 0; q < 200; ++q) {
    cut.counts[q] = 9;
    cut.ids[q * 10 + 9] = -1;
    cut.dist2[q * 10 + 9] = INFINITY;
  }
  Accuracy c = evaluate_accuracy(cut, truth);
  CHECK(c.recall == doctest::Approx(0.9));
  CHECK(c.false_negative_rate == doctest::Approx(0.1));
  CHECK(c.incomplete_queries == 200);
}

TEST_CASE("metrics: mismatched or malformed results are refused") {
  KnnResult other_k = make(3, {{{0, 1.0f}}});
  CHECK_THROWS_WITH_AS(evaluate_accuracy(other_k, truth4()), doctest::Contains("shapes differ"), Error);
  KnnResult other_n = make(4, {{}, {}});
  CHECK_THROWS_WITH_AS(evaluate_accuracy(other_n, truth4()), doctest::Contains("shapes differ"), Error);
  // Arrays shorter than n x k would be read out of bounds.
  KnnResult short_arrays = truth4();
  short_arrays.ids.pop_back();
  CHECK_THROWS_WITH_AS(evaluate_accuracy(short_arrays, truth4()), doctest::Contains("ids"), Error);
  KnnResult short_counts = truth4();
  short_counts.counts.clear();
  CHECK_THROWS_WITH_AS(evaluate_accuracy(truth4(), short_counts), doctest::Contains("counts"), Error);
  // A count outside [0, k] would index past the row.
  KnnResult bad_count = truth4();
  bad_count.counts[0] = 5;
  CHECK_THROWS_WITH_AS(evaluate_accuracy(bad_count, truth4()), doctest::Contains("count"), Error);
  bad_count.counts[0] = -1;
  CHECK_THROWS_WITH_AS(evaluate_accuracy(truth4(), bad_count), doctest::Contains("count"), Error);
}

namespace {
RadiusResult slices(const std::vector<std::vector<std::int32_t>>& rows) {
  RadiusResult r;
  r.n = rows.size();
  r.offsets.assign(1, 0);
  for (const auto& row : rows) {
    for (std::int32_t id : row) {
      r.ids.push_back(id);
      r.dist2.push_back(static_cast<float>(id));
    }
    r.offsets.push_back(static_cast<std::int64_t>(r.ids.size()));
    r.found.push_back(static_cast<std::int64_t>(row.size()));
  }
  return r;
}
}  // namespace

TEST_CASE("metrics: radius accuracy by hand: recall, missing, false positives, identical slices") {
  const RadiusResult truth = slices({{0, 1, 2}, {}, {5}});
  const RadiusAccuracy a = evaluate_radius_accuracy(slices({{1, 0}, {}, {5, 9}}), truth);
  CHECK(a.queries == 3);
  CHECK(a.recall == doctest::Approx((2.0 / 3.0 + 1.0) / 2.0));  // the empty ball is left out
  CHECK(a.found_fraction == doctest::Approx(3.0 / 4.0));
  CHECK(a.missing == 1);
  CHECK(a.false_positives == 1);      // 9 is not in the ball
  CHECK(a.incomplete_queries == 1);
  CHECK(a.identical_slices == 1);     // the empty one; {5, 9} is not {5}
  CHECK(a.mean_true == doctest::Approx(4.0 / 3.0));
  CHECK(a.mean_found == doctest::Approx(4.0 / 3.0));
  const RadiusAccuracy self = evaluate_radius_accuracy(slices({{2, 1, 0}, {}, {5}}), truth);  // order free
  CHECK(self.recall == 1.0);
  CHECK(self.identical_slices == 3);
  CHECK(self.missing == 0);
  CHECK(evaluate_radius_accuracy(slices({}), slices({})).recall == 1.0);  // no queries
  CHECK(a.summary().find("recall 0.8333") != std::string::npos);
  CHECK_THROWS_WITH_AS(evaluate_radius_accuracy(slices({{0}}), truth), doctest::Contains("query counts differ"), Error);
  RadiusResult bad = truth;
  bad.offsets[1] = 99;  // past the ids
  CHECK_THROWS_WITH_AS(evaluate_radius_accuracy(bad, truth), doctest::Contains("offsets"), Error);
  bad = truth;
  bad.offsets.pop_back();
  CHECK_THROWS_WITH_AS(evaluate_radius_accuracy(truth, bad), doctest::Contains("truth's offsets"), Error);
}
