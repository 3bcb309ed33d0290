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

}  // namespace bhcl
