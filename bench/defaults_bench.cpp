// defaults_bench: what a user gets from block hashing with no A and no recall target (issue 25's
// "default-recall table"): recall@k, false negatives and distance dilation of the default search,
// with the tuning's time and its share of the call, beside the kd-tree kernel's time for the same
// batch.
//
// The default search is what bhcl knn and the Python package run: BlockHashIndex::params_for_batch
// (A tuned on a sample of the batch when a budget applies; the grid's exact mode otherwise), then
// Index::query. Per data set, layout, query distribution and k, the FIRST call on a fresh index
// is timed apart (the tuning is done there and then cached), then `--rounds` calls whose medians
// are reported, kd-tree and block hashing interleaved (a ratio from one process on a loaded
// machine). Layouts: "grid" (the auto preset's default: the grid, exact by default) and "blocks"
// (auto with grid = 0: the L tables, where a budget applies and the default
// tunes A for recall 0.95 on the batch). Distributions: "on" (the set's own queries: near the
// data) and "box" (uniform over the points' bounding box).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "bench_cli.hpp"
#include "bench_util.hpp"
#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"

using namespace bhcl;

namespace {

using bench::now_s;

}  // namespace

int main(int argc, char** argv) {
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
#endif
  std::vector<std::string> data = {"uniform", "cornell", "autzen"}, layouts = {"grid", "blocks"},
                           dists = {"on", "box"};
  std::string data_dir, device, csv;
  std::size_t N = 1000000, n_queries = 50000, n_box = 0;
  std::vector<int> ks = {1, 10, 50};
  int rounds = 3;
  bench::BenchCli cli("defaults_bench",
                      "block hashing's default search (no A, no recall target) against the exact kd-tree: "
                      "recall@k, FN, dilation, the tuning's time and share, the speed ratio");
  cli.names("data", data, "data sets: uniform, cornell, clustered, duplicates, or bunny, dragon, autzen (files)");
  cli.names("layouts", layouts, "block hashing builds: grid (the default build), blocks (auto with grid = 0)");
  cli.names("dist", dists, "query distributions: on (the set's queries, near the data), box (uniform over its box)");
  cli.integer("N", N, "points per data set (file sets: the first N)", 1, 2147483646.0);
  cli.queries(n_queries);
  cli.integer("box-queries", n_box, "queries of the box distribution (0: as --queries)", 0, 1e9);
  cli.ks(ks);
  cli.integer("rounds", rounds, "timed calls after the first (medians reported)", 1, 1000);
  cli.csv(csv);
  cli.data_dir(data_dir);
  cli.device(device);
  cli.parse(argc, argv);
  for (const auto& l : layouts)
    if (l != "grid" && l != "blocks") cli.fail("--layouts: unknown layout '" + l + "' (grid, blocks)");
  for (const auto& d : dists)
    if (d != "on" && d != "box") cli.fail("--dist: unknown distribution '" + d + "' (on, box)");
  try {
    auto rt = std::make_shared<Runtime>(device);
    bench::print_run_header(argc, argv, *rt);
    std::printf("# first: the first call on a fresh index (tuning done there); tune_s its tuning, share = tune_s / "
                "first call's wall; t_bh, t_kd: median wall of %d later calls (host-array query, sorting and "
                "transfers included); vs_kd = t_kd / t_bh\n",
                rounds);
    std::FILE* out = cli.csv_file(csv, "data,N,layout,dist,queries,k,A,tuned,sample,sample_recall,recall,fn,maxdil,"
                                       "meandil,incomplete,tune_s,first_wall_s,tune_share,t_bh_s,t_kd_s,vs_kd\n");
    for (const std::string& name : data) {
      std::vector<float> pts, on;
      if (!bench::load_set(data_dir, name, N, n_queries, pts, on)) continue;
      const std::size_t n_pts = pts.size() / 3;
      const std::vector<float> box = bench::box_queries(pts, n_box ? n_box : on.size() / 3, 7);
      auto kd = make_index("kdtree", rt, pts.data(), n_pts);
      std::printf("\n# %s: N = %zu, %zu queries on the data, %zu over its box; kdtree build %.3f s\n", name.c_str(),
                  n_pts, on.size() / 3, box.size() / 3, kd->build_seconds());
      std::printf("%-8s %-6s %-4s %3s %7s %5s %6s %7s %7s %7s %8s %5s %8s %8s %6s %9s %9s %6s\n", "data", "layout",
                  "dist", "k", "A", "tuned", "sample", "s_rec", "recall", "FN", "maxdil", "mdil", "incompl", "tune_s",
                  "share", "t_bh_s", "t_kd_s", "vs_kd");
      for (const std::string& layout : layouts) {
        for (const std::string& dist : dists) {
          const std::vector<float>& q = dist == "on" ? on : box;
          const std::size_t nq = q.size() / 3;
          for (int k : ks) {
            // A fresh index per (distribution, k): its first call does the tuning, as a user's would.
            MethodOptions mo;
            if (layout == "blocks") mo.set("grid", "0");
            auto idx = make_index("blockhash", rt, pts.data(), n_pts, mo);
            SearchParams p;
            p.k = k;
            KnnResult truth, got;
            kd->query(q.data(), nq, p, truth);  // warm-up (compiles) and the exact answer
            auto call = [&](BlockHashIndex::BatchTuning* bt) {
              const double t0 = now_s();
              const SearchParams run = idx->params_for_batch(q.data(), nq, p, bt);
              idx->query(q.data(), nq, run, got);
              return std::make_pair(now_s() - t0, run.A);
            };
            BlockHashIndex::BatchTuning bt;
            // First call: kernel compiles happen here too; they are reported apart (bt.compile_s)
            // and left out of the share.
            auto [first_wall, A] = call(&bt);
            const double tune_s = bt.tuned ? bt.seconds : 0.0;
            const Accuracy acc = evaluate_accuracy(got, truth);
            std::vector<double> tb, tk;
            for (int r = 0; r < rounds; ++r) {
              KnnResult tmp;
              const double t0 = now_s();
              kd->query(q.data(), nq, p, tmp);
              tk.push_back(now_s() - t0);
              tb.push_back(call(nullptr).first);
            }
            const double t_bh = bench::median(tb), t_kd = bench::median(tk);
            const double share = tune_s > 0 ? tune_s / std::max(1e-12, first_wall - bt.compile_s) : 0.0;
            const std::string a_text = std::isinf(A) ? "inf" : A == 0 ? "exact" : std::to_string(A).substr(0, 5);
            std::printf("%-8s %-6s %-4s %3d %7s %5s %6zu %7.4f %7.4f %7.4f %8.3f %5.3f %8zu %8.3f %6.3f %9.4f %9.4f %6.2f\n",
                        name.c_str(), layout.c_str(), dist.c_str(), k, a_text.c_str(), bt.tuned ? "yes" : "no",
                        bt.tuning.sample, bt.tuning.recall, acc.recall, acc.false_negative_rate, acc.max_dilation,
                        acc.mean_dilation, acc.incomplete_queries, tune_s, share, t_bh, t_kd, t_kd / t_bh);
            std::fflush(stdout);
            if (out)
              std::fprintf(out, "%s,%zu,%s,%s,%zu,%d,%s,%d,%zu,%.5f,%.5f,%.5f,%.4f,%.5f,%zu,%.4f,%.4f,%.4f,%.5f,%.5f,%.3f\n",
                           name.c_str(), n_pts, layout.c_str(), dist.c_str(), nq, k, a_text.c_str(), bt.tuned ? 1 : 0,
                           bt.tuning.sample, bt.tuning.recall, acc.recall, acc.false_negative_rate, acc.max_dilation,
                           acc.mean_dilation, acc.incomplete_queries, tune_s, first_wall, share, t_bh, t_kd, t_kd / t_bh);
          }
        }
      }
    }
    if (out) std::fclose(out);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "defaults_bench: %s\n", e.what());
    return 1;
  }
  return 0;
}
