// Helpers the benchmark programs share.
#pragma once

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <random>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/runtime.hpp"

namespace bhcl::bench {

// Seconds on the steady clock (differences of two calls time a span).
inline double now_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// The bounding box of n x 3 points.
struct Bounds {
  float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  explicit Bounds(const std::vector<float>& p) {
    for (std::size_t i = 0; i < p.size() / 3; ++i)
      for (int d = 0; d < 3; ++d) lo[d] = std::min(lo[d], p[3 * i + d]), hi[d] = std::max(hi[d], p[3 * i + d]);
  }
  float diag() const {
    float s = 0;
    for (int d = 0; d < 3; ++d) s += (hi[d] - lo[d]) * (hi[d] - lo[d]);
    return std::sqrt(s);
  }
};

// n queries uniform over the points' bounding box (seeded).
inline std::vector<float> box_queries(const std::vector<float>& pts, std::size_t n, unsigned long long seed) {
  const Bounds b(pts);
  std::mt19937_64 rng(seed);
  std::vector<float> q(3 * n);
  for (std::size_t i = 0; i < n; ++i)
    for (int d = 0; d < 3; ++d) q[3 * i + d] = std::uniform_real_distribution<float>(b.lo[d], b.hi[d])(rng);
  return q;
}

// The first lines of a run's output: the command line, the device and the threads.
inline void print_run_header(int argc, char** argv, const Runtime& rt) {
  const char* pt = std::getenv("POCL_MAX_PTHREAD_COUNT");
  std::string command = "#";
  for (int i = 0; i < argc; ++i) command += std::string(" ") + argv[i];
  std::printf("%s\n# device: %s; host threads %u (POCL_MAX_PTHREAD_COUNT=%s)\n", command.c_str(),
              rt.info().summary().c_str(), std::thread::hardware_concurrency(), pt ? pt : "unset");
}

// The median of timings (the mean of the two middle values for an even count; 0 for none).
inline double median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const std::size_t m = v.size() / 2;
  return v.size() % 2 ? v[m] : 0.5 * (v[m - 1] + v[m]);
}

// Points and queries of a named set (knn_bench and perf_harness read sets the same way).
// Generated sets (datasets::by_name: uniform, clustered, duplicates, cornell): N points of seed 1,
// queries_by_name of seed 2. File sets (bunny, dragon, autzen, read from data_dir): the first N
// points (all when N is 0 or larger than the file), queries are data points picked at random
// (seeded) and jittered by a Gaussian of 1e-4 of the bounding-box diagonal. Returns false, with a
// line on stdout, when the file is absent.
inline bool load_set(const std::string& data_dir, const std::string& name, std::size_t N,
                     std::size_t n_queries, std::vector<float>& pts, std::vector<float>& qs) {
  static const std::map<std::string, std::string> files = {
      {"bunny", "bunny.xyz.f32"}, {"dragon", "dragon_stand_scans.xyz.f32"}, {"autzen", "autzen.xyz.f32"}};
  auto f = files.find(name);
  if (f == files.end()) {
    pts = datasets::by_name(name, N, 1);
    qs = datasets::queries_by_name(name, n_queries, 2);
    return true;
  }
  std::string path = data_dir + "/" + f->second;
  if (!std::ifstream(path).good()) {
    std::printf("# %s: %s not present (set BHCL_DATA_DIR or --data-dir to ../shared/data): skipped\n",
                name.c_str(), path.c_str());
    return false;
  }
  pts = read_points_file(path);
  if (N && N < pts.size() / 3) pts.resize(3 * N);
  std::size_t n_pts = pts.size() / 3;
  // Jitter scale: 1e-4 of the bounding box diagonal.
  const float diag = Bounds(pts).diag();
  std::mt19937_64 rng(2);
  std::uniform_int_distribution<std::size_t> pick(0, n_pts - 1);
  std::normal_distribution<float> g(0.0f, 1e-4f * diag);
  qs.resize(3 * n_queries);
  for (std::size_t i = 0; i < n_queries; ++i) {
    std::size_t j = pick(rng);
    for (int d = 0; d < 3; ++d) qs[3 * i + d] = pts[3 * j + d] + g(rng);
  }
  return true;
}

}  // namespace bhcl::bench
