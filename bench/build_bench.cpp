// build_bench: index build times per method, in interleaved rounds (docs/PERFORMANCE.md, "Build").
//
// For each data set and N every method builds the same points once per round, in an order
// shuffled per round; a method's figure is the median of its build seconds over the rounds and the
// median of per-round ratios to the kd-tree kernel index's build. Block hashing's auto (grid)
// build also reports its stages, and `blockhash-rebuild` times BlockHashIndex::rebuild of the
// same points on a built index (the next frame of a photon map: buffers reused). Kernel compiles
// are not part of any build (no query runs here). min_s is the quickest round (the least disturbed
// by other tenants of a shared machine); cpu_s the process's CPU seconds for the build (all its
// threads: a measure of the work that a busy machine inflates far less than the wall time).
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "bench_cli.hpp"
#include "bench_util.hpp"
#include "blockhash_cl/blockhash_cl.hpp"

using namespace bhcl;

namespace {
double cpu_seconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_utime.tv_sec + u.ru_stime.tv_sec) + 1e-6 * double(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}
}  // namespace

int main(int argc, char** argv) try {
  std::vector<std::string> data = {"cornell", "uniform", "autzen"};
  std::vector<std::size_t> Ns = {1000000};
  std::vector<std::string> methods = {"blockhash", "blockhash-rebuild", "kdtree", "flann"};
  int rounds = 3;
  std::string device, data_dir;
  bench::BenchCli cli("build_bench", "Index build times per method in interleaved rounds, with ratios to the kd-tree's");
  cli.names("data", data, "data sets: cornell, uniform, clustered (generated) or bunny, dragon, autzen (files)");
  cli.integers("N", Ns, "points per data set (file sets: the first N)", 1, 2147483646.0);
  cli.names("methods", methods, "methods (registry names, plus blockhash-rebuild)");
  cli.integer("rounds", rounds, "interleaved rounds", 1, 1000);
  cli.device(device);
  cli.data_dir(data_dir);
  cli.parse(argc, argv);
  auto rt = std::make_shared<Runtime>(device);
  std::printf("# build_bench: %s; %d rounds; seconds are medians over rounds, x_kdtree the median of per-round build-time ratios to the kd-tree's (< 1: faster)\n",
              rt->info().summary().c_str(), rounds);
  std::printf("%-10s %10s %-18s %10s %10s %10s %10s %s\n", "set", "N", "method", "build_s", "min_s", "cpu_s", "x_kdtree", "detail");
  for (const std::string& set : data)
    for (std::size_t N : Ns) {
      std::vector<float> pts, qs;
      if (!bench::load_set(data_dir, set, N, 1, pts, qs)) continue;
      const std::size_t n = pts.size() / 3;
      std::unique_ptr<BlockHashIndex> frame;  // the index blockhash-rebuild rebuilds
      std::vector<std::vector<double>> t(methods.size()), cpu(methods.size());
      std::vector<std::string> detail(methods.size());
      std::mt19937_64 rng(7);
      for (int r = 0; r < rounds; ++r) {
        std::vector<std::size_t> order(methods.size());
        for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
        std::shuffle(order.begin(), order.end(), rng);
        for (std::size_t i : order) {
          std::fprintf(stderr, "\r%s N=%zu round %d/%d: %-18s", set.c_str(), n, r + 1, rounds, methods[i].c_str());
          auto t0 = std::chrono::steady_clock::now();
          double c0 = cpu_seconds();
          if (methods[i] == "blockhash-rebuild") {
            if (!frame) frame = BlockHashIndex::build(rt, pts.data(), n);
            t0 = std::chrono::steady_clock::now();
            c0 = cpu_seconds();
            frame->rebuild(pts.data(), n);
            detail[i] = frame->info().summary();
          } else {
            auto index = make_index(methods[i], rt, pts.data(), n);
            detail[i] = index->build_summary();
          }
          t[i].push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
          cpu[i].push_back(cpu_seconds() - c0);
        }
      }
      std::fprintf(stderr, "\r%60s\r", "");
      std::size_t kd = std::find(methods.begin(), methods.end(), "kdtree") - methods.begin();
      for (std::size_t i = 0; i < methods.size(); ++i) {
        std::vector<double> ratio;
        if (kd < methods.size())
          for (int r = 0; r < rounds; ++r) ratio.push_back(t[i][r] / t[kd][r]);
        std::printf("%-10s %10zu %-18s %10.4f %10.4f %10.4f %10.2f %s\n", set.c_str(), n, methods[i].c_str(),
                    bench::median(t[i]), *std::min_element(t[i].begin(), t[i].end()), bench::median(cpu[i]),
                    ratio.empty() ? 0.0 : bench::median(ratio), detail[i].c_str());
      }
      std::fflush(stdout);
    }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "build_bench: %s\n", e.what());
  return 1;
}
