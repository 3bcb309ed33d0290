// A recall target instead of a budget: the smallest A that reaches it on a sample of the index's
// own points, each moved off its point (a query sitting on a data point finds it at distance 0,
// which flatters any method), against the exact answers of the kd-tree kernel.
#include <chrono>
#include <cmath>
#include <limits>
#include <random>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/kdtree.hpp"
#include "blockhash_cl/metrics.hpp"

namespace bhcl {

BlockHashIndex::RecallTuning BlockHashIndex::tune_for_recall(double target, const SearchParams& params,
                                                             std::size_t sample) const {
  if (!(target > 0 && target <= 1)) throw Error("blockhash: a recall target must be in (0, 1], got " + std::to_string(target));
  if (sample == 0) throw Error("blockhash: the recall sample must hold at least one query");
  auto t0 = std::chrono::steady_clock::now();
  const std::size_t N = size();
  // The indexed points in the caller's order and coordinates.
  std::vector<std::int32_t> ids;  // after updates the live ids are sparse: truth mapped to them
  std::vector<float> pts = indexed_points(&ids);
  KdTreeIndex exact(runtime_ptr(), pts.data(), N);
  const std::size_t m = std::min(sample, N);
  std::vector<float> qs(3 * m);
  for (std::size_t i = 0; i < m; ++i)
    for (int d = 0; d < 3; ++d) qs[3 * i + d] = pts[3 * (i * (N / m)) + d];
  // Off the point: half the distance to its nearest other point, in a random direction.
  SearchParams nn;
  nn.k = 2;
  KnnResult near = exact.query(qs, nn);
  std::mt19937_64 rng(12345);
  std::normal_distribution<double> g;
  for (std::size_t i = 0; i < m; ++i) {
    if (near.counts[i] < 2 || !std::isfinite(near.d2(i, 1))) continue;
    double r = 0.5 * std::sqrt(double(near.d2(i, 1)));
    double v[3] = {g(rng), g(rng), g(rng)};
    double len = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    if (!(len > 0)) continue;
    for (int d = 0; d < 3; ++d) qs[3 * i + d] = float(qs[3 * i + d] + r * v[d] / len);
  }
  SearchParams p = params;
  p.recall_target = 0;
  p.sort_queries = 0;
  KnnResult truth = exact.query(qs, p);
  for (auto& id : truth.ids)
    if (id >= 0) id = ids[std::size_t(id)];
  RecallTuning out;
  out.sample = m;
  // The grid's exact mode (A = +inf) ends its list: any target is reached.
  const float kInf = std::numeric_limits<float>::infinity();
  for (float A : {1.0f, 1.5f, 2.0f, 3.0f, 4.0f, 6.0f, 8.0f, 12.0f, 16.0f, 24.0f, 32.0f, 48.0f, 64.0f, 128.0f, kInf}) {
    if (std::isinf(A) && !info_.grid) break;
    p.A = A;
    KnnResult r = query(qs, p);
    out.A = A;
    out.recall = evaluate_accuracy(r, truth).recall;
    if (out.recall >= target) {
      out.reached = true;
      break;
    }
  }
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return out;
}

}  // namespace bhcl
