#include "blockhash_cl/metrics.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <unordered_set>

#include "blockhash_cl/error.hpp"

namespace bhcl {

std::string Accuracy::summary() const {
  char buf[256];
  std::snprintf(buf, sizeof buf,
                "recall %.4f  FN %.4f  dilation max %.4f mean %.5f  rel.err %.2e  incomplete %zu/%zu",
                recall, false_negative_rate, max_dilation, mean_dilation, mean_rel_distance_error,
                incomplete_queries, queries);
  return buf;
}

Accuracy evaluate_accuracy(const KnnResult& approx, const KnnResult& truth) {
  if (approx.n != truth.n || approx.k != truth.k)
    throw Error("evaluate_accuracy: shapes differ (" + std::to_string(approx.n) + " x " +
                std::to_string(approx.k) + " vs truth " + std::to_string(truth.n) + " x " +
                std::to_string(truth.k) + ")");
  // Inconsistent arrays or counts would be read out of bounds: refuse them, naming which.
  auto check_shape = [](const KnnResult& r, const char* which) {
    const std::size_t nk = r.n * static_cast<std::size_t>(std::max(r.k, 0));
    if ((r.k < 1 && r.n > 0) || r.ids.size() != nk || r.dist2.size() != nk || r.counts.size() != r.n)
      throw Error(std::string("evaluate_accuracy: ") + which + " result arrays do not match " +
                  std::to_string(r.n) + " x " + std::to_string(r.k) + " (ids " +
                  std::to_string(r.ids.size()) + ", dist2 " + std::to_string(r.dist2.size()) +
                  ", counts " + std::to_string(r.counts.size()) + ")");
    for (std::size_t q = 0; q < r.n; ++q)
      if (r.counts[q] < 0 || r.counts[q] > r.k)
        throw Error(std::string("evaluate_accuracy: ") + which + " query " + std::to_string(q) +
                    " has count " + std::to_string(r.counts[q]) + ", outside [0, " +
                    std::to_string(r.k) + "]");
  };
  check_shape(approx, "approximate");
  check_shape(truth, "truth");
  Accuracy a;
  const std::size_t k = static_cast<std::size_t>(truth.k);
  double recall_sum = 0, fn_missing = 0, fn_total = 0, dil_sum = 0, rel_sum = 0;
  std::size_t dil_n = 0, rel_n = 0;
  std::unordered_set<std::int32_t> got;
  for (std::size_t q = 0; q < truth.n; ++q) {
    const std::size_t tc = static_cast<std::size_t>(truth.counts[q]);
    const std::size_t ac = static_cast<std::size_t>(approx.counts[q]);
    if (tc == 0) continue;
    ++a.queries;
    const float* td = &truth.dist2[q * k];
    const float* ad = &approx.dist2[q * k];
    const std::int32_t* ti = &truth.ids[q * k];
    const std::int32_t* ai = &approx.ids[q * k];
    // Recall with ties tolerated.
    const double kth = td[tc - 1];
    const double bound = kth + 1e-6 * std::abs(kth);
    std::size_t hits = 0;
    for (std::size_t j = 0; j < std::min(ac, tc); ++j)
      if (ai[j] >= 0 && ad[j] <= bound) ++hits;
    recall_sum += double(hits) / double(tc);
    // False negatives by index.
    got.clear();
    for (std::size_t j = 0; j < ac; ++j) got.insert(ai[j]);
    for (std::size_t j = 0; j < tc; ++j) fn_missing += got.count(ti[j]) ? 0 : 1;
    fn_total += double(tc);
    if (ac < tc) {
      ++a.incomplete_queries;
    } else if (kth > 0) {
      double dil = std::sqrt(double(ad[tc - 1]) / kth);
      a.max_dilation = std::max(a.max_dilation, dil);
      dil_sum += dil;
      ++dil_n;
    }
    for (std::size_t j = 0; j < std::min(ac, tc); ++j) {
      if (td[j] > 0) {
        rel_sum += (std::sqrt(double(ad[j])) - std::sqrt(double(td[j]))) / std::sqrt(double(td[j]));
        ++rel_n;
      }
    }
    bool same = ac == tc;
    for (std::size_t j = 0; same && j < tc; ++j) same = ai[j] == ti[j] && ad[j] == td[j];
    if (same) ++a.identical_rows;
  }
  if (a.queries) {
    a.recall = recall_sum / double(a.queries);
    a.false_negative_rate = fn_total > 0 ? fn_missing / fn_total : 0.0;
  } else {
    a.recall = 1.0;
  }
  a.mean_dilation = dil_n ? dil_sum / double(dil_n) : 1.0;
  a.mean_rel_distance_error = rel_n ? rel_sum / double(rel_n) : 0.0;
  return a;
}

std::string RadiusAccuracy::summary() const {
  char buf[256];
  std::snprintf(buf, sizeof buf,
                "recall %.4f  found %.4f of the true points  missing %zu  false positives %zu  incomplete %zu/%zu",
                recall, found_fraction, missing, false_positives, incomplete_queries, queries);
  return buf;
}

RadiusAccuracy evaluate_radius_accuracy(const RadiusResult& approx, const RadiusResult& truth) {
  if (approx.n != truth.n)
    throw Error("evaluate_radius_accuracy: query counts differ (" + std::to_string(approx.n) + " vs truth " +
                std::to_string(truth.n) + ")");
  // Offsets that are not a non-decreasing walk over the ids would be read out of bounds.
  auto check = [](const RadiusResult& r, const char* which) {
    bool ok = r.offsets.size() == r.n + 1 && !r.offsets.empty() && r.offsets[0] == 0 &&
              static_cast<std::size_t>(r.offsets[r.n]) == r.ids.size();
    for (std::size_t i = 0; ok && i < r.n; ++i) ok = r.offsets[i] <= r.offsets[i + 1];
    if (!ok) throw Error(std::string("evaluate_radius_accuracy: the ") + which + "'s offsets do not index its ids");
  };
  check(approx, "result");
  check(truth, "truth");
  RadiusAccuracy a;
  a.queries = truth.n;
  std::size_t total_true = 0, total_found_true = 0, total_found = 0, with_ball = 0;
  double recall_sum = 0;
  std::unordered_set<std::int32_t> ball;
  for (std::size_t i = 0; i < truth.n; ++i) {
    ball.clear();
    for (std::int64_t j = truth.offsets[i]; j < truth.offsets[i + 1]; ++j) ball.insert(truth.ids[static_cast<std::size_t>(j)]);
    std::size_t hit = 0, found = 0;
    std::unordered_set<std::int32_t> seen;
    for (std::int64_t j = approx.offsets[i]; j < approx.offsets[i + 1]; ++j) {
      const std::int32_t id = approx.ids[static_cast<std::size_t>(j)];
      if (!seen.insert(id).second) continue;  // a repeat counts once
      ++found;
      if (ball.count(id)) ++hit;
      else ++a.false_positives;
    }
    total_true += ball.size();
    total_found_true += hit;
    total_found += found;
    if (!ball.empty()) {
      ++with_ball;
      recall_sum += static_cast<double>(hit) / static_cast<double>(ball.size());
    }
    if (hit < ball.size()) ++a.incomplete_queries;
    if (hit == ball.size() && found == hit) ++a.identical_slices;
  }
  a.missing = total_true - total_found_true;
  if (with_ball) a.recall = recall_sum / static_cast<double>(with_ball);
  if (total_true) a.found_fraction = static_cast<double>(total_found_true) / static_cast<double>(total_true);
  if (truth.n) {
    a.mean_true = static_cast<double>(total_true) / static_cast<double>(truth.n);
    a.mean_found = static_cast<double>(total_found) / static_cast<double>(truth.n);
  }
  return a;
}

}  // namespace bhcl
