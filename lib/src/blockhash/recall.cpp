// A recall target instead of a budget: the smallest A that reaches it on a sample of the index's
// own points, each moved off its point (a query sitting on a data point finds it at distance 0,
// which flatters any method), against the exact answers of the kd-tree kernel.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <random>
#include <string>
#include <vector>

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
    if (std::isinf(A) && !exact_mode()) break;
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

namespace bhcl {
namespace {

// The A ladder of params_for_batch: tune_for_recall's, carried on to 1024 (queries spread over a
// clustered set's box need A = 256 at k = 10 for 0.95 on a block layout: measured in
// tests/defaults_tests.cpp); bisection keeps the passes at log2 of its length.
constexpr float kLadder[] = {1.0f,  1.5f,  2.0f,  3.0f,  4.0f,   6.0f,   8.0f,   12.0f,  16.0f,
                             24.0f, 32.0f, 48.0f, 64.0f, 128.0f, 256.0f, 512.0f, 1024.0f};

int eighth(double v, double lo, double ext, bool up) {
  const double t = ext > 0 ? 8.0 * (v - lo) / ext : 0.0;
  const double r = up ? std::ceil(t) : std::floor(t);
  return static_cast<int>(std::max(-64.0, std::min(72.0, r)));  // far outside: one bucket
}

// The sample: the batch's finite queries, evenly spread over it; at most 2000 and an eighth of
// them, so that tuning (about 5 block-hash passes and one exact pass over the sample) stays within
// about twice the batch's own cost even for a small batch; at least 256 (or all of them).
std::vector<float> batch_sample(const float* queries, std::size_t n) {
  std::vector<std::size_t> finite;
  finite.reserve(n);
  for (std::size_t i = 0; i < n; ++i) {
    const float* q = queries + 3 * i;
    if (std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2])) finite.push_back(i);
  }
  const std::size_t nf = finite.size();
  const std::size_t m =
      std::min<std::size_t>(nf, std::max<std::size_t>(std::min<std::size_t>(nf, 256), std::min<std::size_t>(2000, nf / 8)));
  std::vector<float> qs(3 * m);
  for (std::size_t i = 0; i < m; ++i) std::copy_n(queries + 3 * finite[(i * nf) / m], 3, qs.data() + 3 * i);
  return qs;
}

// The indexed points' box (lo, hi) and mean spacing (box measure / N)^(1/d) over the axes of
// nonzero extent.
void points_box(const std::vector<float>& pts, double box[6], double* spacing) {
  const std::size_t N = pts.size() / 3;
  for (int d = 0; d < 3; ++d) {
    box[d] = INFINITY;
    box[3 + d] = -INFINITY;
  }
  for (std::size_t i = 0; i < N; ++i)
    for (int d = 0; d < 3; ++d) {
      box[d] = std::min(box[d], double(pts[3 * i + d]));
      box[3 + d] = std::max(box[3 + d], double(pts[3 * i + d]));
    }
  double measure = 1;
  int dims = 0;
  for (int d = 0; d < 3; ++d) {
    const double e = box[3 + d] - box[d];
    if (e > 0) {
      measure *= e;
      ++dims;
    }
  }
  *spacing = dims ? std::pow(measure / double(N), 1.0 / dims) : 0.0;
}

// The distribution: the sample's box within the index's box, in eighths of its extent, and the
// median distance of the first 256 sampled queries to their nearest indexed point over the mean
// spacing, in half octaves. Queries on the data (median ~ 0.5 spacing) and queries spread over
// the box (larger in sparse regions) get different keys; so do a batch inside a corner and one
// over the whole box. exact: the kd-tree over the indexed points.
std::string batch_distribution(const std::vector<float>& qs, const Index& exact, const double box[6],
                               double spacing, double* compile_s) {
  const std::size_t m = qs.size() / 3;
  double qlo[3] = {INFINITY, INFINITY, INFINITY}, qhi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (std::size_t i = 0; i < m; ++i)
    for (int d = 0; d < 3; ++d) {
      qlo[d] = std::min(qlo[d], double(qs[3 * i + d]));
      qhi[d] = std::max(qhi[d], double(qs[3 * i + d]));
    }
  const std::size_t ms = std::min<std::size_t>(m, 256);
  SearchParams nn;
  nn.k = 1;
  nn.sort_queries = 0;
  KnnResult near;
  *compile_s += exact.query(qs.data(), ms, nn, near).compile_s;
  std::vector<double> nd(ms);
  for (std::size_t i = 0; i < ms; ++i) nd[i] = std::sqrt(double(near.dist2[i]));
  std::nth_element(nd.begin(), nd.begin() + ms / 2, nd.end());
  const double med = nd[ms / 2];
  const int octaves = (med > 0 && spacing > 0) ? static_cast<int>(std::lround(2.0 * std::log2(med / spacing))) : -99;
  std::string dist = "box";
  for (int d = 0; d < 3; ++d) {
    const double lo = box[d], ext = box[3 + d] - box[d];
    dist += " " + std::to_string(eighth(qlo[d], lo, ext, false)) + ":" + std::to_string(eighth(qhi[d], lo, ext, true));
  }
  return dist + "/8, nn 2^(" + std::to_string(octaves) + "/2) spacing";
}

// The smallest A of the ladder whose recall@k on the sample clears target by 1.5 standard errors
// (about sqrt(t (1 - t) / (m k)), neighbours counted as independent, so that the whole batch meets
// it rather than half the time), by bisection: recall grows with A, so 1 + log2(17) ~ 5 passes
// over the sample answer it (a linear scan took up to 17). Not reached: the largest A, or on the
// grid its exact mode, which reaches any target.
RecallTuning tune_on_sample(const Index& index, const Index& exact, const std::vector<std::int32_t>& exact_ids,
                            const std::vector<float>& qs, const SearchParams& params, double target, bool has_exact_mode,
                            double* compile_s) {
  const auto t1 = std::chrono::steady_clock::now();
  const double compile0 = *compile_s;
  const std::size_t m = qs.size() / 3;
  SearchParams tp = params;
  tp.recall_target = 0;
  tp.sort_queries = 0;
  tp.max_radius = INFINITY;  // the budget a recall needs does not depend on the radius
  tp.count_examined = false;
  KnnResult truth;
  *compile_s += exact.query(qs.data(), m, tp, truth).compile_s;
  for (auto& id : truth.ids)
    if (id >= 0) id = exact_ids[std::size_t(id)];
  RecallTuning t;
  t.sample = m;
  const double margin = std::min(1.0 - target, 1.5 * std::sqrt(target * (1.0 - target) / (double(m) * params.k)));
  constexpr int kRungs = static_cast<int>(sizeof kLadder / sizeof kLadder[0]);
  std::vector<double> seen(kRungs, -1.0);
  auto recall_at = [&](int i) {
    if (seen[i] < 0) {
      tp.A = kLadder[i];
      KnnResult r;
      *compile_s += index.query(qs.data(), m, tp, r).compile_s;
      seen[i] = evaluate_accuracy(r, truth).recall;
    }
    return seen[i];
  };
  int lo = 0, hi = kRungs - 1;
  if (recall_at(hi) < target + margin) {
    lo = hi;  // not reached: the largest A
  } else {
    while (lo < hi) {
      const int mid = (lo + hi) / 2;
      if (recall_at(mid) >= target + margin) hi = mid;
      else lo = mid + 1;
    }
  }
  t.A = kLadder[lo];
  t.recall = recall_at(lo);
  t.reached = t.recall >= target + margin;
  if (!t.reached && has_exact_mode) {
    t.A = std::numeric_limits<float>::infinity();
    t.recall = 1.0;
    t.reached = true;
  }
  const double spent = std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
  t.seconds = std::max(0.0, spent - (*compile_s - compile0));
  return t;
}

}  // namespace

SearchParams BlockHashIndex::params_for_batch(const float* queries, std::size_t n, const SearchParams& params,
                                              BatchTuning* info) const {
  const auto t0 = std::chrono::steady_clock::now();
  BatchTuning bt;
  SearchParams p = params;
  double target = 0;
  if (params.recall_target > 0 && params.recall_target < 1) target = params.recall_target;
  else if (params.recall_target == 0 && params.A == 0 && !exact_mode()) target = kDefaultRecallTarget;
  // Nothing to tune (an explicit A, the grid's exact default or exact target, no queries): the
  // parameters as given, which the query validates.
  if (info) *info = bt;
  if (target == 0 || n == 0 || queries == nullptr) return p;
  kmax_variant(params.k);  // a bad k is the query's error, named before any work
  const std::vector<float> qs = batch_sample(queries, n);
  if (qs.empty()) return p;

  // The read lock before the tuning's: an update holds the write lock and then takes the tuning's
  // (forget_tunings), so taking them the other way round (the queries below take the read lock)
  // could deadlock against a concurrent insert.
  ReadLock read(*this);
  std::lock_guard<std::mutex> lock(tune_mutex_);
  if (!exact_) {
    // The exact answers come from a kd-tree over the indexed points in the caller's coordinates
    // (what the batch's queries are in), kept for later tunings.
    // After removes the live ids are sparse: the tree's answers (positions in pts) are mapped to
    // them before they are compared with the index's.
    const std::vector<float> pts = indexed_points(&exact_ids_);
    points_box(pts, exact_box_, &exact_spacing_);
    exact_ = std::make_shared<KdTreeIndex>(runtime_ptr(), pts.data(), size());
  }
  double compile_s = 0;
  bt.distribution = batch_distribution(qs, *exact_, exact_box_, exact_spacing_, &compile_s);
  bt.target = target;
  bt.tuned = true;
  const auto key = std::make_tuple(params.k, params.neighbour_probes, target, bt.distribution);
  auto it = batch_tuned_.find(key);
  bt.cached = it != batch_tuned_.end();
  bt.tuning = bt.cached ? it->second
                        : (batch_tuned_[key] = tune_on_sample(*this, *exact_, exact_ids_, qs, params, target, exact_mode(), &compile_s));
  p.A = bt.tuning.A;
  p.recall_target = 0;
  bt.compile_s = compile_s;
  bt.seconds = std::max(0.0, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() - compile_s);
  if (info) *info = bt;
  return p;
}

}  // namespace bhcl
