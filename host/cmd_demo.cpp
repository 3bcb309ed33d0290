// bhcl demo: the main job of the README, on embedded defaults only (no data files):
//  1. the measured Cornell Box rendered by photon mapping, the final-gather queries answered by
//     the exact kd-tree kernel and by block hashing (A = 4, 8), images and errors side by side;
//  2. a benchmark table: every method on a Cornell photon-like set and a uniform cube, with
//     queries/s and accuracy against exact kNN.
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>

#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/metrics.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "commands.hpp"

namespace bhcl::cli {
namespace {

int run_registered(const std::string& name, std::vector<std::string> args) {
  args.insert(args.begin(), name);
  return run_command(args);
}

void table(const std::shared_ptr<Runtime>& rt, std::size_t N, std::size_t n, int k) {
  std::printf("\n== Benchmark: N = %zu points, %zu queries, k = %d, device %s\n", N, n, k,
              rt->info().summary().c_str());
  std::printf("   exact truth: flann; query s = kernel time (OpenCL profiling events) or host search "
              "time, median of 3; compile time apart\n\n");
  std::printf("%-9s %-15s %9s %9s %9s %11s %8s %8s %8s %8s\n", "data", "method", "build s", "compile",
              "query s", "queries/s", "recall", "FN", "max dil", "B/point");
  for (const char* name : {"cornell", "uniform"}) {
    std::vector<float> pts = datasets::by_name(name, N, 1);
    std::vector<float> qs = datasets::queries_by_name(name, n, 2);
    SearchParams p;
    p.k = k;
    KnnResult truth = make_index(default_truth_method(), rt, pts.data(), N)->query(qs, p);
    for (const auto& method : method_names()) {
      if (method == "bruteforce") continue;  // O(N) per query: see `bhcl eval` for small N
      auto index = make_index(method, rt, pts.data(), N);
      std::vector<float> As = index->exact() ? std::vector<float>{0} : std::vector<float>{2, 4, 8};
      for (float A : As) {
        SearchParams sp = p;
        if (A > 0) sp.A = A;
        double compile = index->warm_up(sp);
        std::vector<double> t;
        KnnResult r;
        for (int rep = 0; rep < 3; ++rep) t.push_back(index->query(qs.data(), n, sp, r).query_s);
        std::sort(t.begin(), t.end());
        Accuracy acc = evaluate_accuracy(r, truth);
        std::string label = A > 0 ? method + " A=" + std::to_string(int(A)) : method;
        std::printf("%-9s %-15s %9.3f %9.3f %9.4f %11.0f %8.4f %8.4f %8.3f %8.1f\n", name,
                    label.c_str(), index->build_seconds(), compile, t[1], n / t[1], acc.recall,
                    acc.false_negative_rate, acc.max_dilation, double(index->memory_bytes()) / N);
      }
    }
  }
}

void declare_demo(Args& a) {
  a.add_integer("N", "points of each benchmark set", 1, 1LL << 31, "200000");
  a.add_integer("n", "queries of each benchmark set", 1, 1LL << 31, "20000");
  a.add_integer("k", "neighbours per query in the benchmark", 1, kMaxK, "50");
  declare_device_option(a);
  a.add_text("out-dir", "directory for the images", "bhcl-demo", "DIR");
  a.add_flag("no-render", "skip the Cornell Box render, print the benchmark table only");
}

int run_demo(const Args& args) {
  const std::size_t N = static_cast<std::size_t>(args.integer("N", 200000));
  const std::size_t n = static_cast<std::size_t>(args.integer("n", 20000));
  const int k = static_cast<int>(args.integer("k", 50));
  const std::string dir = args.str("out-dir", "bhcl-demo");
  if (mkdir(dir.c_str(), 0755) != 0 && errno != EEXIST)
    throw Error(dir + ": cannot create the output directory");
  if (!args.flag("no-render")) {
    std::printf("== The measured Cornell Box, photon mapping with final gather (192x192, 100k photons, "
                "16 gather rays per pixel, k = 50)\n");
    std::fflush(stdout);
    std::vector<std::string> r = {"--scene", "cornell", "--compare", "--photons", "100000", "--gather", "16",
                                  "--size", "192x192", "--compare-A", "4,8", "--out", dir + "/cornell.exr"};
    if (args.has("device")) r.insert(r.end(), {"--device", args.str("device")});
    if (int rc = run_registered("render", r)) return rc;
  }
  auto rt = std::make_shared<Runtime>(args.str("device", ""));
  table(rt, N, n, k);
  std::printf("\nImages: %s/cornell.exr (linear half float), %s/cornell_compare.png (side by side). "
              "Full sweeps and plots: bench/sweep.sh quick|full.\n",
              dir.c_str(), dir.c_str());
  return 0;
}

RegisterCommand reg_demo("demo", "the README's main job: the Cornell Box render and a benchmark table",
                         declare_demo, run_demo);

}  // namespace
}  // namespace bhcl::cli
