// The exact baselines side by side in one run: the kd-tree kernel (OpenCL, PoCL by default) and
// FLANN on the host with the same number of threads. For one data set: build both, then for each
// k run the same query batch several times, interleaved, and report medians. Also checks that
// the two answers are identical (ids, squared distances, counts).
//
//   baselines [--data uniform|autzen|PATH] [--n-points N] [--queries n] [--k 10,50] [--reps 3]
//             [--threads T] [--leaf L] [--local-size S] [--jitter J] [--json OUT]
//
// Threads: PoCL's pthread device reads POCL_MAX_PTHREAD_COUNT at start-up; when it is unset this
// program sets it to T before opening the device, so both sides use T threads. kd-tree query time
// is the kernel's event time (compile excluded, reported apart; transfers excluded, the host-call
// wall time is reported too); FLANN's is the wall time of its threaded search.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <sstream>
#include <thread>
#include <string>
#include <vector>

#include "bench_cli.hpp"
#include "bench_util.hpp"
#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/cornell_box.hpp"

using namespace bhcl;

namespace {

struct Options {
  std::string data = "uniform";
  std::size_t n_points = 1000000;
  std::size_t n_queries = 100000;
  std::vector<int> ks = {10, 50};
  int reps = 3;
  int threads = 2;
  int leaf = KdTreeParams{}.leaf_size;
  std::size_t local_size = 0;
  double jitter = 0.5;  // autzen query jitter, in the data's units (feet)
  std::string json;
};

Options parse(int argc, char** argv) {
  Options o;
  bench::BenchCli cli("baselines", "The exact baselines side by side: the kd-tree kernel against FLANN");
  cli.text("data", o.data, "uniform, autzen (../shared/data) or a point file", "SET");
  cli.integer("N", o.n_points, "points (file sets: the first N)", 1, 2147483646.0);
  cli.queries(o.n_queries);
  cli.ks(o.ks);
  cli.reps(o.reps);
  cli.integer("threads", o.threads, "flann: host threads", 1, 4096);
  cli.integer("leaf-size", o.leaf, "kdtree: most points per leaf", 1, 1024);
  cli.integer("local-size", o.local_size, "device methods: OpenCL work-group size (0: the device default)", 0, 1 << 20);
  cli.number("jitter", o.jitter, "file sets: query jitter, in the data's units", 0.0, 1e30);
  cli.text("json", o.json, "write the results here as JSON", "FILE");
  cli.parse(argc, argv);
  if (o.ks.empty()) cli.fail("--k: empty list");
  return o;
}

// Queries from the data set's own distribution. Uniform: more uniform points. Real data: data
// points picked at random and jittered by a Gaussian of `jitter` (so they sit on the surfaces,
// not exactly on points).
std::vector<float> make_queries(const Options& o, const std::vector<float>& pts) {
  if (o.data == "uniform") return datasets::uniform(o.n_queries, 2);
  std::mt19937_64 rng(3);
  std::uniform_int_distribution<std::size_t> pick(0, pts.size() / 3 - 1);
  std::normal_distribution<double> g(0.0, o.jitter);
  std::vector<float> q(3 * o.n_queries);
  for (std::size_t i = 0; i < o.n_queries; ++i) {
    std::size_t p = pick(rng);
    for (int d = 0; d < 3; ++d) q[3 * i + d] = static_cast<float>(pts[3 * p + d] + g(rng));
  }
  return q;
}

std::vector<float> load_points(const Options& o) {
  if (o.data == "uniform") return datasets::uniform(o.n_points, 1);
  std::string path = o.data;
#ifdef BHCL_DEFAULT_DATA_DIR
  if (o.data == "autzen") path = std::string(BHCL_DEFAULT_DATA_DIR) + "/autzen.xyz.f32";
#endif
  std::vector<float> pts = read_points_file(path);
  if (pts.size() / 3 < o.n_points)
    std::fprintf(stderr, "baselines: %s holds %zu points, fewer than --n-points %zu: using all\n",
                 path.c_str(), pts.size() / 3, o.n_points);
  else
    pts.resize(3 * o.n_points);  // the first N points (autzen: a spatially uniform subsample)
  return pts;
}

// First differing entry of two results, or "" when identical.
std::string first_difference(const KnnResult& a, const KnnResult& b) {
  if (a.counts != b.counts) return "counts differ";
  for (std::size_t i = 0; i < a.ids.size(); ++i)
    if (a.ids[i] != b.ids[i] || std::memcmp(&a.dist2[i], &b.dist2[i], sizeof(float)) != 0) {
      char buf[160];
      std::snprintf(buf, sizeof buf, "query %zu rank %zu: kdtree id %d d2 %.9g, flann id %d d2 %.9g",
                    i / a.k, i % a.k, a.ids[i], a.dist2[i], b.ids[i], b.dist2[i]);
      return buf;
    }
  return "";
}

}  // namespace

int main(int argc, char** argv) {
  Options o = parse(argc, argv);
  // Both sides on the same number of threads: PoCL reads this once, at device start-up.
  const char* env = std::getenv("POCL_MAX_PTHREAD_COUNT");
  if (!env) setenv("POCL_MAX_PTHREAD_COUNT", std::to_string(o.threads).c_str(), 1);
  else if (std::atoi(env) != o.threads)
    std::fprintf(stderr, "baselines: warning: POCL_MAX_PTHREAD_COUNT=%s but --threads %d: the "
                         "thread counts differ\n", env, o.threads);
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  if (!std::getenv("POCL_CACHE_DIR")) setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 1);
#endif
  try {
    std::vector<float> pts = load_points(o);
    std::vector<float> qs = make_queries(o, pts);
    const std::size_t N = pts.size() / 3, n = qs.size() / 3;
    auto rt = std::make_shared<Runtime>();
    std::printf("baselines: data %s N=%zu n=%zu reps=%d on %s\n", o.data.c_str(), N, n, o.reps,
                rt->info().summary().c_str());
    std::printf("threads: POCL_MAX_PTHREAD_COUNT=%s, FLANN %d std::threads; hardware threads %u\n",
                std::getenv("POCL_MAX_PTHREAD_COUNT"), o.threads, std::thread::hardware_concurrency());

    KdTreeParams kp;
    kp.leaf_size = o.leaf;
    KdTreeIndex kd(rt, pts.data(), N, kp);
    FlannParams fp;
    fp.threads = o.threads;
    FlannIndex fl(rt, pts.data(), N, fp);
    std::printf("kdtree: build %.3f s, %zu nodes, %zu leaves of <= %d points, depth %d, %.1f MiB\n",
                kd.build_seconds(), kd.node_count(), kd.leaf_count(), kd.leaf_size(), kd.depth(),
                kd.memory_bytes() / 1048576.0);
    std::printf("flann:  build %.3f s (KDTreeSingleIndex, leaf_max_size %d), %.1f MiB\n",
                fl.build_seconds(), fp.leaf_max_size, fl.memory_bytes() / 1048576.0);

    // query s and queries/s: medians over the repetitions; best: the fastest repetition (the one
    // least disturbed by other processes); spread: (slowest - fastest) / median.
    std::printf("\n%-8s %-7s %4s %8s %9s %9s %9s %11s %11s %7s %7s  %s\n", "data", "method", "k",
                "build s", "compile s", "query s", "wall s", "queries/s", "best q/s", "spread",
                "threads", "identical");
    std::string json = "{\n  \"data\": \"" + o.data + "\", \"N\": " + std::to_string(N) +
                       ", \"n\": " + std::to_string(n) + ", \"threads\": " + std::to_string(o.threads) +
                       ", \"device\": \"" + rt->info().device_name + "\",\n  \"runs\": [";
    bool all_identical = true;
    for (std::size_t ki = 0; ki < o.ks.size(); ++ki) {
      SearchParams p;
      p.k = o.ks[ki];
      p.local_size = o.local_size;
      const double compile = kd.warm_up(p);
      std::vector<double> kq, kw, fq, fw;
      KnnResult kr, fr;
      std::string diff;
      for (int r = 0; r < o.reps; ++r) {
        // Interleaved, so that load from other processes hits both sides alike.
        QueryStats ks = kd.query(qs.data(), n, p, kr);
        QueryStats fs = fl.query(qs.data(), n, p, fr);
        kq.push_back(ks.query_s);
        kw.push_back(ks.wall_s);
        fq.push_back(fs.query_s);
        fw.push_back(fs.wall_s);
        if (r == 0) diff = first_difference(kr, fr);
      }
      all_identical = all_identical && diff.empty();
      auto line = [&](const char* m, double build, double comp, const std::vector<double>& q,
                      const std::vector<double>& w) {
        const double mq = bench::median(q);
        const auto mm = std::minmax_element(q.begin(), q.end());
        char spread[32];
        std::snprintf(spread, sizeof spread, "%.0f%%", 100.0 * (*mm.second - *mm.first) / mq);
        std::printf("%-8s %-7s %4d %8.3f %9.3f %9.4f %9.4f %11.0f %11.0f %7s %7d  %s\n", o.data.c_str(),
                    m, p.k, build, comp, mq, bench::median(w), n / mq, n / *mm.first, spread, o.threads,
                    diff.empty() ? "yes" : "NO");
        char buf[512];
        std::snprintf(buf, sizeof buf,
                      "%s\n    {\"method\": \"%s\", \"k\": %d, \"build_s\": %.6f, \"compile_s\": %.6f, "
                      "\"query_s\": %.6f, \"best_query_s\": %.6f, \"wall_s\": %.6f, \"queries_per_s\": %.1f, "
                      "\"identical\": %s}",
                      json.back() == '[' ? "" : ",", m, p.k, build, comp, mq, *mm.first, bench::median(w),
                      n / mq, diff.empty() ? "true" : "false");
        json += buf;
      };
      line("kdtree", kd.build_seconds(), compile, kq, kw);
      line("flann", fl.build_seconds(), 0.0, fq, fw);
      std::printf("%-8s %-7s %4d  kdtree/flann queries/s = %.2f (medians), %.2f (best)\n",
                  o.data.c_str(), "ratio", p.k, bench::median(fq) / bench::median(kq),
                  *std::min_element(fq.begin(), fq.end()) / *std::min_element(kq.begin(), kq.end()));
      if (!diff.empty()) std::printf("  MISMATCH: %s\n", diff.c_str());
    }
    json += "\n  ]\n}\n";
    if (!o.json.empty()) {
      FILE* f = std::fopen(o.json.c_str(), "w");
      if (!f) throw Error(o.json + ": cannot open for writing");
      std::fputs(json.c_str(), f);
      std::fclose(f);
    }
    return all_identical ? 0 : 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "baselines: %s\n", e.what());
    return 1;
  }
}
