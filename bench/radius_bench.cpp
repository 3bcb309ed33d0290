// radius_bench: radius search of every method against FLANN's, side by side in one process.
//
// Per data set and radius (chosen so that a query finds about `--per-query` points on average:
// the median distance to that neighbour over a sample of the queries), every variant (each
// method; block hashing at each --budget and with each --bh-defines) runs once per round, in a shuffled order, on the same
// queries; the table gives per variant the median over rounds of queries/s and of its time
// ratio to FLANN's radius search in the same round (> 1: faster than FLANN), with the min-max of
// the ratios, and its recall against the exact answer (the points within r found, over all
// queries; exact methods must give 1 and identical slices, checked). Compile time (the first
// call) is reported apart and not timed. --at box: the queries uniform over the points' box (a
// LiDAR scan queried from above it: the radius walk's far case).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <numeric>
#include <random>
#include <thread>
#include <string>
#include <vector>

#include "blockhash_cl/blockhash_cl.hpp"
#include "bench_cli.hpp"
#include "bench_util.hpp"

using namespace bhcl;

namespace {

struct Options {
  std::vector<std::string> data = {"bunny", "cornell", "autzen"};
  std::size_t N = 1000000;
  std::size_t queries = 100000;
  std::vector<int> per_query = {10, 50};
  std::vector<std::string> methods = {"kdtree", "flann", "blockhash"};
  std::vector<long long> budgets = {0, 200, 800};
  int rounds = 5;
  std::string csv, device, data_dir;
  std::string at = "on";                // the queries: on the data, or uniform over its box
  std::vector<std::string> bh_defines;  // more blockhash variants (no budget), with these kernel defines
};

struct Variant {
  std::string name, method;
  RadiusParams params;
  const Index* index = nullptr;
};

struct Tally {
  std::vector<double> seconds, ratio, wall, wall_ratio;
  double compile_s = 0, recall = 1, per_query = 0;
  bool identical = true;
};

// Over all queries, the points of `truth` that `got` holds (slices are sorted by (d, id)).
double radius_recall(const RadiusResult& got, const RadiusResult& truth) {
  std::size_t hit = 0;
  for (std::size_t q = 0; q < truth.n; ++q) {
    std::vector<std::int32_t> a(got.ids.begin() + got.offsets[q], got.ids.begin() + got.offsets[q + 1]);
    std::vector<std::int32_t> b(truth.ids.begin() + truth.offsets[q], truth.ids.begin() + truth.offsets[q + 1]);
    std::sort(a.begin(), a.end());
    std::sort(b.begin(), b.end());
    std::vector<std::int32_t> both;
    std::set_intersection(a.begin(), a.end(), b.begin(), b.end(), std::back_inserter(both));
    hit += both.size();
  }
  return truth.total() ? double(hit) / double(truth.total()) : 1.0;
}

Options parse(int argc, char** argv) {
  bench::BenchCli cli("radius_bench", "Radius search of every method against FLANN's, interleaved in one process");
  Options o;
  cli.data_sets(o.data_dir, o.data, "data sets: bunny, dragon, autzen (files) or uniform, clustered, cornell (generated)");
  cli.integer("N", o.N, "points per set (file sets: the first N; 0: all)", 0, 2147483646.0);
  cli.queries(o.queries);
  cli.integers("per-query", o.per_query, "radii: each holds about this many points per query on average", 1, 1e6);
  cli.methods(o.methods);
  cli.integers("budget", o.budgets, "blockhash: points examined per query at most (0: no budget)", 0, 4294967295.0);
  cli.integer("rounds", o.rounds, "interleaved rounds (medians over them)", 1, 1000);
  cli.text("at", o.at, "the queries: on (the data's points, jittered) or box (uniform over the points' box)")
      ->check(CLI::IsMember({"on", "box"}));
  cli.names("bh-defines", o.bh_defines,
            "blockhash: one more variant (no budget) per entry, with these kernel defines (e.g. -DBHCL_GRID_TBOX=0)");
  cli.csv(o.csv);
  cli.device(o.device);
  cli.parse(argc, argv);
  return o;
}

// The radius: the median over a sample of queries of the distance to the target-th point.
float radius_for(const Index& flann, const std::vector<float>& qs, int target) {
  const std::size_t n = qs.size() / 3;
  std::vector<float> sample(qs.begin(), qs.begin() + 3 * std::min<std::size_t>(n, 2000));
  SearchParams kp;
  kp.k = std::min(target, kMaxK);
  KnnResult kn = flann.query(sample, kp);
  std::vector<float> kth;
  for (std::size_t q = 0; q < kn.n; ++q)
    if (kn.counts[q] == kp.k) kth.push_back(kn.d2(q, kp.k - 1));
  std::nth_element(kth.begin(), kth.begin() + kth.size() / 2, kth.end());
  return std::sqrt(kth[kth.size() / 2]);
}

// Each method (block hashing at each budget), and FLANN when it is not among them.
std::vector<Variant> make_variants(const Options& o, const std::map<std::string, std::unique_ptr<Index>>& indexes) {
  std::vector<Variant> vs;
  for (const auto& m : o.methods) {
    if (m == "blockhash") {
      for (long long b : o.budgets) {
        Variant v{"blockhash budget " + (b ? std::to_string(b) : std::string("none")), m, {}, indexes.at(m).get()};
        v.params.budget = static_cast<std::uint32_t>(b);
        vs.push_back(v);
      }
      for (const std::string& d : o.bh_defines) {
        Variant v{"blockhash " + d, m, {}, indexes.at(m).get()};
        v.params.kernel_defines = d;
        vs.push_back(v);
      }
    } else {
      vs.push_back(Variant{m, m, {}, indexes.at(m).get()});
    }
  }
  if (std::none_of(vs.begin(), vs.end(), [](const Variant& v) { return v.method == "flann"; }))
    vs.push_back(Variant{"flann", "flann", {}, indexes.at("flann").get()});
  return vs;
}

// The first call of each variant (its kernels' compile, untimed), then the rounds in a shuffled
// order; each variant's times and ratios to FLANN's in the same round, and (first round) its
// recall and whether it is the exact answer.
std::vector<Tally> run_rounds(const Options& o, const std::vector<Variant>& vs, const std::vector<float>& qs, float r,
                              const RadiusResult& truth, std::mt19937& rng) {
  const std::size_t n = qs.size() / 3;
  std::vector<Tally> t(vs.size());
  for (std::size_t i = 0; i < vs.size(); ++i) {
    RadiusResult res;
    QueryStats st = vs[i].index->radius_search(qs.data(), std::min<std::size_t>(n, 16), r, vs[i].params, res);
    t[i].compile_s = st.compile_s;
  }
  const std::size_t flann_i = static_cast<std::size_t>(
      std::find_if(vs.begin(), vs.end(), [](const Variant& v) { return v.name == "flann"; }) - vs.begin());
  for (int round = 0; round < o.rounds; ++round) {
    std::vector<std::size_t> order(vs.size());
    std::iota(order.begin(), order.end(), 0);
    std::shuffle(order.begin(), order.end(), rng);
    std::vector<double> secs(vs.size()), walls(vs.size());
    for (std::size_t i : order) {
      RadiusResult res;
      QueryStats st = vs[i].index->radius_search(qs.data(), n, r, vs[i].params, res);
      secs[i] = st.query_s;  // device: kernel time of both passes; host: FLANN's search
      walls[i] = st.wall_s;  // the whole call: transfers, host sort of the slices, the cap
      if (round == 0) {
        t[i].recall = radius_recall(res, truth);
        t[i].per_query = double(res.total()) / double(n);
        t[i].identical = res.offsets == truth.offsets && res.ids == truth.ids && res.dist2 == truth.dist2;
      }
    }
    for (std::size_t i = 0; i < vs.size(); ++i) {
      t[i].seconds.push_back(secs[i]);
      t[i].ratio.push_back(secs[flann_i] / secs[i]);
      t[i].wall.push_back(walls[i]);
      t[i].wall_ratio.push_back(walls[flann_i] / walls[i]);
    }
  }
  return t;
}

// The rows of one (set, radius); an exact variant that differs from FLANN's answer is an error.
void report(const std::string& set, std::size_t N, std::size_t n, int target, float r, const std::vector<Variant>& vs,
            const std::vector<Tally>& t, std::ofstream& csv) {
  for (std::size_t i = 0; i < vs.size(); ++i) {
    const double s = bench::median(t[i].seconds), ratio = bench::median(t[i].ratio);
    const auto [lo, hi] = std::minmax_element(t[i].ratio.begin(), t[i].ratio.end());
    const bool exact = vs[i].index->exact();
    const double wall_ratio = bench::median(t[i].wall_ratio);
    std::printf("| %s | %zu | %.4g | %.1f | %s | %.0f | %.2f (%.2f-%.2f) | %.2f | %.4f%s | %.2f |\n", set.c_str(), N, r,
                t[i].per_query, vs[i].name.c_str(), double(n) / s, ratio, *lo, *hi, wall_ratio, t[i].recall,
                exact ? (t[i].identical ? " (identical)" : " (DIFFERS)") : "", t[i].compile_s);
    if (csv)
      csv << set << ',' << N << ',' << n << ',' << target << ',' << r << ',' << vs[i].name << ','
          << t[i].per_query << ',' << double(n) / s << ',' << ratio << ',' << *lo << ',' << *hi << ','
          << wall_ratio << ',' << t[i].recall << ',' << t[i].compile_s << ',' << (exact ? (t[i].identical ? "yes" : "no") : "") << '\n';
    if (exact && !t[i].identical) throw Error(vs[i].name + ": the exact radius answer differs from FLANN's");
  }
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
#endif
  const Options o = parse(argc, argv);
  try {
    auto rt = std::make_shared<Runtime>(o.device);
    std::printf("# device: %s; baseline: flann (host, %u threads); %d rounds, shuffled order\n",
                rt->info().summary().c_str(), std::thread::hardware_concurrency(), o.rounds);
    std::ofstream csv;
    if (!o.csv.empty()) {
      csv.open(o.csv);
      if (!csv) throw Error(o.csv + ": cannot open for writing");
      csv << "data,N,n,per_query_target,radius,variant,results_per_query,queries_per_s,ratio_vs_flann,"
             "ratio_min,ratio_max,wall_ratio_vs_flann,recall,compile_s,identical\n";
    }
    std::printf("# q/s and 'vs FLANN': search time (device: both passes' kernels; FLANN: its traversal);\n"
                "# 'wall vs FLANN': whole calls (transfers, the host's sort of each slice, the cap)\n");
    std::printf("| data | N | r | pts/query | variant | q/s (median) | vs FLANN (median, min-max) | wall vs FLANN | recall | compile s |\n");
    std::printf("|---|---|---|---|---|---|---|---|---|---|\n");
    std::mt19937 rng(12345);
    for (const auto& set : o.data) {
      std::vector<float> pts, qs;
      if (!bench::load_set(o.data_dir, set, o.N, o.queries, pts, qs)) continue;
      if (o.at == "box") qs = bench::box_queries(pts, o.queries, 7);
      const std::size_t N = pts.size() / 3, n = qs.size() / 3;
      std::map<std::string, std::unique_ptr<Index>> indexes;
      for (const auto& m : o.methods) indexes[m] = make_index(m, rt, pts.data(), N);
      if (!indexes.count("flann")) indexes["flann"] = make_index("flann", rt, pts.data(), N);
      const Index& flann = *indexes["flann"];
      for (int target : o.per_query) {
        const float r = radius_for(flann, qs, target);
        RadiusResult truth;
        flann.radius_search(qs.data(), n, r, {}, truth);
        const std::vector<Variant> vs = make_variants(o, indexes);
        report(set, N, n, target, r, vs, run_rounds(o, vs, qs, r, truth, rng), csv);
      }
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "radius_bench: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
