// Block hashing accuracy and cost against exact kNN, both presets, the talk's A sweep.
//
//   blockhash_accuracy [--data uniform,cornell,dragon] [--N 1000000] [--queries 5000]
//                      [--A 1,2,4,8,16,32] [--k 10,50] [--presets auto,paper] [--reps 3]
//                      [--csv out.csv] [--data-dir DIR] [--seed 1] [--local-size WG] [block hashing's search options]
//                      [--L L] [--X X] [--hilbert-seed S] [--box-order 0|1] [--target POINTS]  (auto only)
// (blockhash_accuracy --help lists them with their meanings and defaults.)
//
// Data sets: uniform in [0,1]^3; the Cornell photon-like set (datasets::cornell_photons, queries
// 0.5 mm off the surfaces); the dragon scans file (DIR/dragon_stand_scans.xyz.f32: 5000 points
// held out as queries, the rest indexed). Truth: the brute-force kernel (exact, same contract).
// auto is built once per data set. paper follows the talk: B > A k / (X ln N) depends on A and
// k, so paper is built once per distinct B (as the prototype study did); paper-cells once per
// distinct (B, k) (its P follows k too).
// Reported per (preset, k, A): recall@k, false negatives, max/mean distance dilation, incomplete
// rows, mean points examined (the kernel's own count), query time per query (median of reps of the
// kernel's event time, compile excluded by a warm-up), build time, memory per point.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <memory>
#include <numeric>
#include <random>
#include <sstream>
#include <string>
#include <sys/stat.h>
#include <vector>

#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/cornell_box.hpp"
#include "bench_cli.hpp"
#include "bench_util.hpp"

using namespace bhcl;

namespace {

struct Options {
  std::vector<std::string> data = {"uniform", "cornell", "dragon"};
  std::size_t n = 1000000, queries = 5000;
  std::vector<float> A = {1, 2, 4, 8, 16, 32};
  std::vector<int> k = {10, 50};
  std::vector<std::string> presets = {"auto", "paper"};
  int reps = 3;
  std::size_t local = 0;  // work-group size (0: the device default)
  std::map<std::string, std::string> search;  // block hashing's table search options given
  int L = -1, X = -1, seed_blocks = -1, box_order = -1;  // auto build overrides (-1: derive)
  double target = 100;    // auto: target points per median occupied cell
  std::string csv = "blockhash_accuracy.csv";
  std::string data_dir;
  unsigned long long seed = 1;
};

struct DataSet {
  std::string name;
  std::vector<float> points, queries;
};

bool load_data(const std::string& name, const Options& o, DataSet& d) {
  d.name = name;
  if (name == "uniform") {
    d.points = datasets::uniform(o.n, o.seed);
    d.queries = datasets::uniform(o.queries, o.seed + 1000);
  } else if (name == "cornell") {
    d.points = datasets::cornell_photons(o.n, o.seed);
    d.queries = datasets::cornell_queries(o.queries, o.seed + 1000, 0.5f);
  } else if (name == "dragon") {
    std::string path = o.data_dir + "/dragon_stand_scans.xyz.f32";
    struct stat st;
    if (stat(path.c_str(), &st) != 0) {
      std::fprintf(stderr, "dragon: %s is absent: skipped\n", path.c_str());
      return false;
    }
    std::vector<float> all = read_points_file(path);
    const std::size_t N = all.size() / 3;
    std::vector<std::size_t> idx(N);
    std::iota(idx.begin(), idx.end(), 0);
    std::mt19937_64 rng(o.seed);
    std::shuffle(idx.begin(), idx.end(), rng);
    std::vector<bool> held(N, false);
    for (std::size_t i = 0; i < std::min(o.queries, N / 2); ++i) held[idx[i]] = true;
    for (std::size_t i = 0; i < N; ++i) {
      auto& dst = held[i] ? d.queries : d.points;
      dst.insert(dst.end(), all.begin() + 3 * i, all.begin() + 3 * i + 3);
    }
  } else {
    throw Error("unknown data set '" + name + "' (uniform, cornell, dragon)");
  }
  return true;
}



struct Row {
  std::string data, preset;
  std::size_t N;
  int k;
  float A;
  BlockHashBuildInfo info;
  double mem_per_point, overhead, talk_overhead;
  Accuracy acc;
  double examined, query_us, compile_s;
};

Options parse(int argc, char** argv) {
  Options o;
  bench::BenchCli cli("blockhash_accuracy", "Block hashing's accuracy and cost against exact kNN, both presets, the talk's A sweep");
  cli.names("data", o.data, "data sets: uniform, cornell, dragon");
  cli.integer("N", o.n, "points per data set", 1, 2147483646.0);
  cli.budget_sweep(o.queries, o.k, o.A, o.presets);
  cli.reps(o.reps);
  cli.csv(o.csv);
  cli.data_dir(o.data_dir);
  cli.seed(o.seed);
  cli.integer("local-size", o.local, "OpenCL work-group size (0: the device default)", 0, 1 << 20);
  cli.integer("L", o.L, "auto: hash tables (-1: derive)", -1, 1 << 16);
  cli.integer("X", o.X, "auto: points per block (-1: derive)", -1, 16);
  cli.integer("hilbert-seed", o.seed_blocks, "auto: blocks gathered around the query's key on each side (-1: derive)", -1, 1 << 20);
  cli.integer("box-order", o.box_order, "auto: 1 scans blocks by box distance, 0 in bucket order (-1: derive)", -1, 1);
  cli.number("target", o.target, "auto: target points per median occupied cell", 1.0, 1e9);
  cli.table_options("blockhash", OptionInfo::Search, o.search, {"A", "recall"});
  cli.parse(argc, argv);
  if (o.data.empty() || o.A.empty() || o.k.empty() || o.presets.empty()) cli.fail("empty list");
  return o;
}

// A preset's build parameters (auto: with the --L, --X, ... overrides).
BlockHashBuildParams build_params(const Options& o, const std::string& preset, std::size_t N) {
  BlockHashBuildParams bp;
  bp.preset = BlockHashBuildParams::parse_preset(preset);
  bp.seed = o.seed;
  if (bp.preset == BlockHashBuildParams::Preset::Auto) {
    bp.L = o.L;
    bp.X = o.X;
    bp.hilbert_seed = o.seed_blocks;
    bp.box_order = o.box_order;
    bp.target_cell_points = o.target;
    // A block-layout override builds the block layouts (the grid refuses their options).
    if (o.L > 0 || o.X > 0 || o.seed_blocks >= 0 || o.box_order >= 0) bp.grid = 0;
  }
  bp.verbose = N >= 200000;  // the build's own progress lines
  return bp;
}

// One preset's indexes on a data set: auto is built once; paper once per distinct B (its design
// depends on A and k).
struct PresetIndexes {
  const std::shared_ptr<Runtime>& rt;
  const DataSet& d;
  BlockHashBuildParams bp;
  std::map<std::pair<int, int>, std::unique_ptr<BlockHashIndex>> by_b;  // paper presets: per (B, k or 0)
  std::unique_ptr<BlockHashIndex> single;

  BlockHashIndex* get(int k, float A) {
    const std::size_t N = d.points.size() / 3;
    if (BlockHashBuildParams::is_paper(bp.preset)) {
      BlockHashBuildParams pb = bp;
      pb.design_A = A;
      pb.design_k = k;
      double lnN = std::log(double(N));
      int B = int(std::ceil(A * k / (10.0 * lnN))) + 1;
      const bool cells = bp.preset == BlockHashBuildParams::Preset::PaperCells;
      auto& slot = by_b[{B, cells ? k : 0}];
      if (!slot) {
        std::fprintf(stderr, "  %s %s build (B = %d) ...\n", d.name.c_str(), BlockHashBuildParams::preset_name(bp.preset), B);
        slot = BlockHashIndex::build(rt, d.points.data(), N, pb);
        std::fprintf(stderr, "  %s\n", slot->info().summary().c_str());
      }
      return slot.get();
    }
    if (!single) {
      std::fprintf(stderr, "  %s auto build ...\n", d.name.c_str());
      single = BlockHashIndex::build(rt, d.points.data(), N, bp);
      std::fprintf(stderr, "  %s\n", single->info().summary().c_str());
    }
    return single.get();
  }
};

// One (preset, k, A): the accuracy against the truth, the mean points examined (the kernel's own
// count) and the median query time of the repetitions (which must give the same rows).
Row measure(const Options& o, const DataSet& d, const std::string& preset, BlockHashIndex& idx, int k, float A,
            const KnnResult& truth) {
  const std::size_t N = d.points.size() / 3, nq = d.queries.size() / 3;
  SearchParams p;
  p.k = k;
  p.A = A;
  p.local_size = o.local;
  bench::BenchCli::apply_search("blockhash", o.search, p);
  const double compile_s = idx.warm_up(p);
  KnnResult r;
  SearchParams pe = p;
  pe.count_examined = true;
  idx.query(d.queries.data(), nq, pe, r);
  std::vector<double> times;
  for (int rep = 0; rep < o.reps; ++rep) {
    KnnResult r2;
    QueryStats st = idx.query(d.queries.data(), nq, p, r2);
    times.push_back(st.query_s);
    if (r2.ids != r.ids) throw Error("results differ between repetitions");
  }
  double sum = 0;
  for (auto e : r.examined) sum += e;
  return Row{d.name, preset, N, k, A, idx.info(), idx.memory_per_point(), idx.measured_overhead(),
             BlockHashIndex::talk_overhead(N, A, k, idx.X()), evaluate_accuracy(r, truth), sum / double(nq),
             bench::median(times) / double(nq) * 1e6, compile_s};
}

// Every (preset, k, A) on one data set, against the brute-force kernel's exact rows.
void run_set(const Options& o, const std::shared_ptr<Runtime>& rt, const DataSet& d, std::vector<Row>& rows) {
  const std::string& name = d.name;
  const std::size_t N = d.points.size() / 3, nq = d.queries.size() / 3;
  const int kmax = *std::max_element(o.k.begin(), o.k.end());
  std::fprintf(stderr, "%s: N = %zu, %zu queries; exact truth by the brute-force kernel ...\n",
               name.c_str(), N, nq);
  auto t0 = std::chrono::steady_clock::now();
  BruteForceIndex bf(rt, d.points.data(), N);
  SearchParams tp;
  tp.k = kmax;
  KnnResult truth_all = bf.query(d.queries, tp);
  std::fprintf(stderr, "  truth in %.1f s\n",
               std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  for (const auto& pr : o.presets) {
    PresetIndexes indexes{rt, d, build_params(o, pr, N), {}, {}};
    for (int k : o.k) {
      KnnResult truth = truth_all.leading_columns(k);
      for (float A : o.A) {
        const Row row = measure(o, d, pr, *indexes.get(k, A), k, A, truth);
        rows.push_back(row);
        std::fprintf(stderr, "  %-7s %-5s k=%-3d A=%-4g recall %.4f  FN %.4f  dil max %7.3f mean %.4f  incompl %4zu  examined %7.1f  %.2f us/query\n",
                     name.c_str(), pr.c_str(), k, A, row.acc.recall, row.acc.false_negative_rate,
                     row.acc.max_dilation, row.acc.mean_dilation, row.acc.incomplete_queries,
                     row.examined, row.query_us);
      }
    }
  }
}

// The table and the CSV.
void write_rows(const Options& o, const std::vector<Row>& rows) {
  std::printf("\n| data | preset | k | A | L | P | B | X | recall@k | FN | dil. max | dil. mean | incompl. | examined | us/query | build s | B/point |%s\n",
              " talk ovh | our ovh |");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  // Built in memory, then written through the atomic writer (a temporary renamed into place).
  std::ostringstream csv;
  csv << "data,preset,N,k,A,L,P,B,X,recall,false_negative_rate,max_dilation,mean_dilation,incomplete,examined_mean,query_us,build_s,memory_per_point,overhead,talk_overhead,median_cell_points,p90_cell_blocks,compile_s\n";
  for (const auto& r : rows) {
    std::printf("| %s | %s | %d | %g | %d | %d | %d | %d | %.4f | %.4f | %.3f | %.4f | %zu | %.1f | %.2f | %.2f | %.1f | %.3f | %.3f |\n",
                r.data.c_str(), r.preset.c_str(), r.k, r.A, r.info.L, r.info.P, r.info.B, r.info.X,
                r.acc.recall, r.acc.false_negative_rate, r.acc.max_dilation, r.acc.mean_dilation,
                r.acc.incomplete_queries, r.examined, r.query_us, r.info.t_total, r.mem_per_point,
                r.talk_overhead, r.overhead);
    csv << r.data << "," << r.preset << "," << r.N << "," << r.k << "," << r.A << "," << r.info.L << ","
        << r.info.P << "," << r.info.B << "," << r.info.X << "," << r.acc.recall << ","
        << r.acc.false_negative_rate << "," << r.acc.max_dilation << "," << r.acc.mean_dilation << ","
        << r.acc.incomplete_queries << "," << r.examined << "," << r.query_us << "," << r.info.t_total
        << "," << r.mem_per_point << "," << r.overhead << "," << r.talk_overhead << ","
        << r.info.median_cell_points << "," << r.info.p90_cell_blocks << "," << r.compile_s << "\n";
  }
  write_file(o.csv, {csv.str()}, "the accuracy table (CSV)");
  std::fprintf(stderr, "CSV: %s\n", o.csv.c_str());
}

}  // namespace

int main(int argc, char** argv) {
  const Options o = parse(argc, argv);
  if (!std::getenv("POCL_CACHE_DIR")) setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
  try {
    auto rt = std::make_shared<Runtime>();
    std::fprintf(stderr, "device: %s\n", rt->info().summary().c_str());
    std::vector<Row> rows;
    for (const auto& name : o.data) {
      DataSet d;
      if (load_data(name, o, d)) run_set(o, rt, d, rows);
    }
    write_rows(o, rows);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "blockhash_accuracy: %s\n", e.what());
    return 1;
  }
  return 0;
}
