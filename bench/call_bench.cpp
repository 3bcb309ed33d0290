// call_bench: the whole host-array call (QueryStats::wall_s: checks, sort, upload, kernel,
// download, unsort, exact fallback), kNN and radius, per method, at small and larger batches.
//
// The query pipeline's host side is what this times (issue 35's one pipeline, issue 37's small
// calls); perf_harness times the kernels alone. Every cell (method x kind x n) runs once per round
// in a shuffled order, `--reps` calls each (the median kept); one line per cell and round:
//   data,method,kind,n,k,round,wall_s,query_s
// so that two builds run in alternation can be compared by the median of per-round ratios
// (bench/call_ab.py does that).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <numeric>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "blockhash_cl/blockhash_cl.hpp"
#include "bench_cli.hpp"
#include "bench_util.hpp"

using namespace bhcl;

namespace {

struct Options {
  std::vector<std::string> data = {"uniform", "cornell"};
  std::size_t N = 200000;
  std::vector<long long> sizes = {1000, 20000};
  std::vector<int> k = {1, 10};
  std::vector<std::string> methods = {"kdtree", "flann", "blockhash"};
  int rounds = 5, reps = 5;
  int radius_points = 10;  // the radius holds about this many points per query
  std::string device, data_dir, csv;
};

Options parse(int argc, char** argv) {
  bench::BenchCli cli("call_bench", "Whole host-array calls (wall_s), kNN and radius, per method");
  Options o;
  cli.device(o.device);
  cli.csv(o.csv);
  cli.data_sets(o.data_dir, o.data, "data sets: uniform, clustered, cornell (generated) or bunny, dragon, autzen");
  cli.integer("N", o.N, "points per set", 1, 2147483646.0);
  cli.integers("n", o.sizes, "queries per call", 1, 1e8);
  cli.integers("k", o.k, "neighbours per kNN query", 1, 256);
  cli.methods(o.methods);
  cli.integer("rounds", o.rounds, "rounds (each cell once per round, shuffled)", 1, 1000);
  cli.integer("reps", o.reps, "calls per cell and round (the median kept)", 1, 1000);
  cli.integer("radius-points", o.radius_points, "the radius holds about this many points per query", 1, 256);
  cli.parse(argc, argv);
  return o;
}

struct Cell {
  const Index* index;
  std::string method, kind;  // kind: "knn" or "radius"
  std::size_t n;
  int k;  // kNN: k; radius: 0
};

// The radius holding about `target` points: the median distance to the target-th neighbour.
float radius_for(const Index& ix, const std::vector<float>& qs, int target) {
  SearchParams p;
  p.k = target;
  const std::vector<float> sample(qs.begin(), qs.begin() + 3 * std::min<std::size_t>(qs.size() / 3, 2000));
  const KnnResult r = ix.query(sample, p);
  std::vector<float> kth;
  for (std::size_t q = 0; q < r.n; ++q)
    if (r.counts[q] == target) kth.push_back(r.d2(q, target - 1));
  std::nth_element(kth.begin(), kth.begin() + kth.size() / 2, kth.end());
  return std::sqrt(kth[kth.size() / 2]);
}

// One call of a cell; its stats.
QueryStats run_cell(const Cell& c, const std::vector<float>& qs, float radius) {
  if (c.kind == "knn") {
    SearchParams p;
    p.k = c.k;
    KnnResult r;
    return c.index->query(qs.data(), c.n, p, r);
  }
  RadiusParams p;
  RadiusResult r;
  return c.index->radius_search(qs.data(), c.n, radius, p, r);
}

void run_set(const Options& o, const std::shared_ptr<Runtime>& rt, const std::string& set, std::ostringstream& out) {
  std::vector<float> pts, qs;
  const std::size_t most = static_cast<std::size_t>(*std::max_element(o.sizes.begin(), o.sizes.end()));
  if (!bench::load_set(o.data_dir, set, o.N, most, pts, qs)) return;
  std::map<std::string, std::unique_ptr<Index>> ix;
  for (const auto& m : o.methods) ix[m] = make_index(m, rt, pts.data(), pts.size() / 3);
  const float radius = radius_for(*ix.at(o.methods.front()), qs, o.radius_points);
  std::vector<Cell> cells;
  for (const auto& m : o.methods)
    for (long long n : o.sizes) {
      for (int k : o.k) cells.push_back({ix.at(m).get(), m, "knn", static_cast<std::size_t>(n), k});
      cells.push_back({ix.at(m).get(), m, "radius", static_cast<std::size_t>(n), 0});
    }
  for (const Cell& c : cells) run_cell(c, qs, radius);  // compiles and first-touch, untimed
  std::mt19937 rng(7);
  for (int round = 0; round < o.rounds; ++round) {
    std::vector<std::size_t> order(cells.size());
    std::iota(order.begin(), order.end(), 0);
    std::shuffle(order.begin(), order.end(), rng);
    for (std::size_t i : order) {
      std::vector<double> wall, query;
      for (int r = 0; r < o.reps; ++r) {
        const QueryStats st = run_cell(cells[i], qs, radius);
        wall.push_back(st.wall_s);
        query.push_back(st.query_s);
      }
      const Cell& c = cells[i];
      out << set << ',' << c.method << ',' << c.kind << ',' << c.n << ',' << c.k << ',' << round << ','
          << bench::median(wall) << ',' << bench::median(query) << '\n';
    }
  }
}

// The rows of every set, to stdout or (through the atomic writer) to --csv.
void run_all(const Options& o, int argc, char** argv) {
  auto rt = std::make_shared<Runtime>(o.device);
  bench::print_run_header(argc, argv, *rt);
  std::ostringstream out;
  out.precision(9);
  out << "data,method,kind,n,k,round,wall_s,query_s\n";
  for (const auto& set : o.data) run_set(o, rt, set, out);
  if (o.csv.empty()) std::fputs(out.str().c_str(), stdout);
  else write_file(o.csv, {out.str()}, "call_bench rows");
}

}  // namespace

int main(int argc, char** argv) {
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);  // the build tree's compiled kernels
#endif
  try {
    run_all(parse(argc, argv), argc, argv);
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "call_bench: %s\n", e.what());
    return 1;
  }
}
