// bhcl demo: the main job of the README. Generates point sets, answers a query batch with every
// method on the OpenCL device and prints time and accuracy against an exact host reference.
#include <chrono>
#include <cstdio>
#include <thread>

#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/metrics.hpp"
#include "blockhash_cl/reference.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "commands.hpp"

namespace bhcl::cli {
namespace {

int run_demo(int argc, char** argv) {
  Args args(argc, argv, 1);
  args.allow_only({"N", "n", "k", "device", "methods"});
  const std::size_t N = static_cast<std::size_t>(args.integer("N", 100000));
  const std::size_t n = static_cast<std::size_t>(args.integer("n", 10000));
  SearchParams params;
  params.k = static_cast<int>(args.integer("k", 10));
  if (N == 0 || n == 0) throw UsageError("--N and --n must be positive");

  auto rt = std::make_shared<Runtime>(args.str("device", ""));
  std::printf("device: %s\n", rt->info().summary().c_str());
  std::printf("exact truth: host double-precision brute force (%u threads)\n\n",
              std::thread::hardware_concurrency());
  std::printf("%-10s %-11s %8s %7s %4s %9s %9s %9s %11s %8s %8s %8s\n", "data", "method", "N", "n",
              "k", "build s", "compile s", "query s", "queries/s", "recall", "FN", "max dil");
  for (const char* name : {"uniform", "clustered"}) {
    std::vector<float> pts = datasets::by_name(name, N, 1);
    std::vector<float> qs = datasets::by_name(name, n, 2);
    KnnResult truth = reference::knn_double(pts.data(), N, qs.data(), n, params);
    for (const auto& method : method_names()) {
      auto index = make_index(method, rt, pts.data(), N);
      double compile_s = index->warm_up(params);
      KnnResult r;
      QueryStats st = index->query(qs.data(), n, params, r);
      Accuracy acc = evaluate_accuracy(r, truth);
      std::printf("%-10s %-11s %8zu %7zu %4d %9.3f %9.3f %9.4f %11.0f %8.4f %8.4f %8.4f\n", name,
                  method.c_str(), N, n, params.k, index->build_seconds(),
                  compile_s + st.compile_s, st.query_s,
                  st.queries_per_s(), acc.recall, acc.false_negative_rate, acc.max_dilation);
    }
  }
  std::printf("\ncompile s: kernel build and first launch (a warm-up before timing; PoCL caches "
              "the machine code, so later runs show less); query s: kernel time from OpenCL "
              "profiling events.\n");
  return 0;
}

RegisterCommand reg("demo", "demo [--N POINTS] [--n QUERIES] [--k K] [--device SPEC]", run_demo);

}  // namespace
}  // namespace bhcl::cli
