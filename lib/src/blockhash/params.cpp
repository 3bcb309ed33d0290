// The parameters of a block-hash build. paper: the talk's formulas (L = P = round(ln N),
// B > A k / (X ln N)); paper-cells: the same but P so that the median occupied cell holds about
// design_k / 4 points (docs/ACCURACY.md, "Where the talk's rules do not carry over"); auto's L
// tables (grid = 0): from the data (docs/ACCURACY.md, "Choosing P": P so that the median occupied
// cell holds ~100 points; B = 90th percentile of distinct blocks per cell, L = 4).
#include <algorithm>
#include <cmath>
#include <cstdio>

#include "blockhash/build.hpp"
#include "blockhash/options.hpp"
#include "blockhash_cl/error.hpp"
#include "core/parallel.hpp"

namespace bhcl {

BlockHashBuildParams::Preset BlockHashBuildParams::parse_preset(const std::string& name) {
  if (name == "auto" || name.empty()) return Preset::Auto;
  if (name == "paper") return Preset::Paper;
  if (name == "paper-cells") return Preset::PaperCells;
  throw Error("blockhash: unknown preset '" + name + "' (auto, paper, paper-cells)");
}

const char* BlockHashBuildParams::preset_name(Preset p) {
  switch (p) {
    case Preset::Paper: return "paper";
    case Preset::PaperCells: return "paper-cells";
    case Preset::Auto: break;
  }
  return "auto";
}

}  // namespace bhcl

namespace bhcl::blockhash {

std::vector<std::uint64_t> cell_block_pairs(const Structure& s, const float* const thr[3],
                                            std::uint32_t P, std::size_t stride);
void cell_populations(const std::vector<std::uint64_t>& pairs, std::vector<std::uint32_t>* points,
                      std::vector<std::uint32_t>* blocks);

namespace {

double median_of(std::vector<std::uint32_t> v) {
  if (v.empty()) return 0;
  auto mid = v.begin() + v.size() / 2;
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

// Table-0 thresholds for a candidate P over every stride-th sorted point.
std::vector<float> table0_thresholds(const Structure& s, const TableBuildParams& p, int P,
                                     std::size_t stride, const std::vector<float>& pts) {
  std::vector<float> thr(3 * std::size_t(P), INFINITY);
  for (int d = 0; d < 3; ++d) {
    Histogram h = histogram(pts.data(), pts.size() / 3, d, p.hist_bins, stride);
    auto t = make_thresholds(h, P, p.seed, 0, d, s.info.guard_thresholds);
    std::copy(t.begin(), t.end(), thr.begin() + std::size_t(d) * P);
  }
  return thr;
}

std::vector<float> sorted_points(const Structure& s) {
  std::vector<float> pts(3 * s.n_points);
  for (std::size_t i = 0; i < s.n_points; ++i) s.point(i, &pts[3 * i]);
  return pts;
}

}  // namespace

int derive_x(const TableBuildParams& p) {
  int X = p.X > 0 ? p.X : (BlockHashBuildParams::is_paper(p.preset) ? 10 : BHCL_BH_BLOCK_SLOTS);
  if (p.X == 0 || X > BHCL_BH_BLOCK_SLOTS)
    throw Error("blockhash: X must be in [1, " + std::to_string(BHCL_BH_BLOCK_SLOTS) +
                "] (points per 256-byte block), got " + std::to_string(p.X));
  return X;
}

CellSample::CellSample(const Structure& s, const TableBuildParams& p, std::size_t stride)
    : stride(stride) {
  pts.reserve(3 * (s.n_points / stride + 1));
  for (std::size_t i = 0; i < s.n_points; i += stride) {
    float q[3];
    s.point(i, q);
    pts.insert(pts.end(), q, q + 3);
  }
  for (int d = 0; d < 3; ++d) hist[d] = histogram(pts.data(), pts.size() / 3, d, p.hist_bins);
}

double CellSample::median_points(const Structure& s, const TableBuildParams& p, int P) const {
  std::vector<float> thr(3 * std::size_t(P), INFINITY);
  for (int d = 0; d < 3; ++d) {
    auto t = make_thresholds(hist[d], P, p.seed, 0, d, s.info.guard_thresholds);
    std::copy(t.begin(), t.end(), thr.begin() + std::size_t(d) * P);
  }
  const std::uint32_t side = std::uint32_t(P) + 1;
  std::vector<std::uint32_t> keys(pts.size() / 3);
  // Cells and a sort per half in parallel, then one merge.
  const std::size_t half = keys.size() / 2;
  detail::parallel_for(2, [&](std::size_t part, std::size_t) {
    const std::size_t b = part ? half : 0, e = part ? keys.size() : half;
    for (std::size_t i = b; i < e; ++i) {
      std::uint32_t h[3];
      for (int d = 0; d < 3; ++d) h[d] = hash_coord(thr.data() + std::size_t(d) * P, std::uint32_t(P), pts[3 * i + d]);
      keys[i] = (h[0] * side + h[1]) * side + h[2];
    }
    std::sort(keys.begin() + b, keys.begin() + e);
  }, 2, 1);
  std::inplace_merge(keys.begin(), keys.begin() + half, keys.end());
  std::vector<std::uint32_t> np;
  for (std::size_t i = 0; i < keys.size();) {
    std::size_t j = i;
    while (j < keys.size() && keys[j] == keys[i]) ++j;
    np.push_back(std::uint32_t(j - i));
    i = j;
  }
  return median_of(np) * double(stride);
}

double median_cell_points(const Structure& s, const TableBuildParams& p, int P,
                          std::size_t stride) {
  return CellSample(s, p, stride).median_points(s, p, P);
}

// The P whose median occupied cell (table 0, over a stride sample) is nearest `target` points in
// ratio: a bisection for the smallest P at or below it, then P - 1 if that is nearer.
int p_for_cell_points(const Structure& s, const TableBuildParams& p, double target, std::size_t stride) {
  // One sample and its histograms for every candidate P: only the inversion depends on P.
  const CellSample sample(s, p, stride);
  auto f = [&](int P) { return sample.median_points(s, p, P); };
  int lo = 1, hi = BHCL_BH_MAX_P;
  if (f(hi) > target) {
    lo = hi;
  } else {
    while (lo < hi) {
      int mid = (lo + hi) / 2;
      if (f(mid) <= target) hi = mid;
      else lo = mid + 1;
    }
  }
  int P = lo;
  if (lo > 1) {
    double a = f(lo), b = f(lo - 1);
    if (a > 0 && b > 0 && std::abs(std::log(b / target)) < std::abs(std::log(a / target))) P = lo - 1;
  }
  return P;
}

// The sample stride of the P bisection: at most 2^18 points sampled, and below a quarter of the
// target population (the median of a stride sample's cell counts times the stride is only
// unbiased while a cell keeps several sampled points: at 10M points a 2^18 sample put P at its
// cap with 3-point cells).
std::size_t bisection_stride(std::size_t n, double target) {
  return std::max<std::size_t>(1, std::min<std::size_t>(n >> 18, static_cast<std::size_t>(target / 4)));
}

// The fields the L tables share with the user's parameters: one list for both directions, so that
// a field cannot be carried one way only.
#define BHCL_TABLE_FIELDS(F)                                                                     \
  F(preset) F(L) F(P) F(B) F(X) F(target_cell_points) F(b_percentile) F(design_A) F(design_k)    \
  F(hist_bins) F(hilbert_bits) F(guard_thresholds) F(keep_top_count) F(direct_addressing)        \
  F(box_skip) F(box_order) F(hilbert_seed) F(neighbour_probes) F(seed) F(verbose)
#define BHCL_COPY_FIELD(f) to.f = from.f;

TableBuildParams table_params(const BlockHashBuildParams& from) {
  TableBuildParams to;
  BHCL_TABLE_FIELDS(BHCL_COPY_FIELD)
  return to;
}

BlockHashBuildParams user_params(const TableBuildParams& from) {
  BlockHashBuildParams to;
  BHCL_TABLE_FIELDS(BHCL_COPY_FIELD)
  to.grid = BlockHashBuildParams::is_paper(from.preset) ? -1 : 0;  // auto's tables are grid = 0
  return to;
}
#undef BHCL_COPY_FIELD
#undef BHCL_TABLE_FIELDS

void derive_params(const TableBuildParams& p, Structure& s) {
  const BlockHashBuildParams user = user_params(p);
  check_build_fields(option_table(), &user, "blockhash");  // every range, from the option table
  BlockHashBuildInfo& in = s.info;
  const bool paper = BlockHashBuildParams::is_paper(p.preset);
  const bool paper_cells = p.preset == BlockHashBuildParams::Preset::PaperCells;
  auto flag = [&](int v, bool paper_default) { return v < 0 ? (paper ? paper_default : !paper_default) : v != 0; };
  in.preset = p.preset;
  in.guard_thresholds = flag(p.guard_thresholds, false);
  in.keep_top_count = flag(p.keep_top_count, false);
  // paper-cells: (P+1)^3 buckets of B slots per table would be GBs at its P (~90 at 1M photons);
  // the directory of occupied cells holds the same buckets.
  in.direct_addressing = flag(p.direct_addressing, !paper_cells);
  in.box_skip = flag(p.box_skip, false);
  in.neighbour_probes = flag(p.neighbour_probes, false);
  in.box_order = flag(p.box_order, false);
  in.hilbert_seed = p.hilbert_seed < 0 ? (paper ? 0 : 1) : p.hilbert_seed;
  if (in.hilbert_seed > 64) throw Error("blockhash: hilbert_seed must be in [0, 64], got " + std::to_string(p.hilbert_seed));
  const double N = double(s.n_points), lnN = std::log(std::max(N, 1.0));
  if (p.L == 0 || p.L > 64) throw Error("blockhash: L must be in [1, 64], got " + std::to_string(p.L));
  if (p.P == 0 || p.P > BHCL_BH_MAX_P)
    throw Error("blockhash: P must be in [1, " + std::to_string(BHCL_BH_MAX_P) + "], got " + std::to_string(p.P));
  if (p.B == 0 || p.B > 65535) throw Error("blockhash: B must be in [1, 65535], got " + std::to_string(p.B));
  if (!(p.target_cell_points >= 1) && p.target_cell_points != -1.0)
    throw Error("blockhash: target_cell_points must be >= 1 (or -1: the layout's default)");
  if (!(p.b_percentile > 0 && p.b_percentile <= 1)) throw Error("blockhash: b_percentile must be in (0, 1]");
  if (p.hist_bins < 2 || p.hist_bins > (1 << 22)) throw Error("blockhash: hist_bins must be in [2, 2^22]");
  const int lnr = std::max(1, static_cast<int>(std::lround(lnN)));
  if (paper) {
    in.L = p.L > 0 ? p.L : std::min(64, lnr);
    if (p.P > 0) {
      in.P = p.P;
    } else if (paper_cells) {
      // A cell of k / 4 points on a surface is a square of side ~0.89 r_k (the k-neighbourhood a
      // disc of k points), in a volume a cube of side ~1.0 r_k: the L jittered cells around a
      // query then tile its neighbourhood, and B blocks hold a whole cell, not a sample of it.
      const double target = p.target_cell_points > 0 ? p.target_cell_points : std::max(1.0, p.design_k / 4.0);
      in.P = p_for_cell_points(s, p, target, bisection_stride(s.n_points, target));
      if (p.verbose) std::fprintf(stderr, "blockhash: paper-cells P = %d (median cell ~%.0f points)\n", in.P, target);
    } else {
      in.P = std::min(BHCL_BH_MAX_P, lnr);
    }
    if (p.B > 0) {
      in.B = p.B;
    } else {
      if (!(p.design_A > 0) || p.design_k < 1) throw Error("blockhash: design_A and design_k must be positive");
      // The talk: B > A k / (X ln N). The prototype study used ceil(.) + 1 (B = 2..13 at 1M).
      double x = p.design_A * p.design_k / (in.X * std::max(lnN, 1.0));
      in.B = static_cast<int>(std::min(65535.0, std::ceil(x) + 1));
    }
    return;
  }
  in.L = p.L > 0 ? p.L : 4;
  // P: bisection on the median points per occupied cell (table 0, guarded thresholds), over a
  // stride sample of the Hilbert-sorted points (spatially even; bisection_stride says how large).
  const double target = p.target_cell_points > 0 ? p.target_cell_points : 100.0;
  const std::size_t stride = bisection_stride(s.n_points, target);
  if (p.P > 0) {
    in.P = p.P;
  } else {
    in.P = p_for_cell_points(s, p, target, stride);
    if (p.verbose) std::fprintf(stderr, "blockhash: auto P = %d\n", in.P);
  }
  if (p.B > 0) {
    in.B = p.B;
  } else {
    // B: the percentile of distinct blocks per occupied cell of table 0, all points.
    std::vector<float> pts = sorted_points(s);
    std::vector<float> thr = table0_thresholds(s, p, in.P, 1, pts);
    const float* t3[3] = {thr.data(), thr.data() + in.P, thr.data() + 2 * std::size_t(in.P)};
    std::vector<std::uint32_t> nb;
    cell_populations(cell_block_pairs(s, t3, std::uint32_t(in.P), 1), nullptr, &nb);
    std::sort(nb.begin(), nb.end());
    std::size_t idx = static_cast<std::size_t>(std::ceil(p.b_percentile * nb.size()));
    idx = std::min(nb.size() - 1, idx ? idx - 1 : 0);
    in.B = std::max<int>(1, std::min<int>(65535, static_cast<int>(nb.empty() ? 1 : nb[idx])));
  }
}

}  // namespace bhcl::blockhash
