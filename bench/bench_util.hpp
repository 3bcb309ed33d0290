// Helpers the benchmark programs share.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/io.hpp"

namespace bhcl::bench {

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
  float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (std::size_t i = 0; i < n_pts; ++i)
    for (int d = 0; d < 3; ++d) lo[d] = std::min(lo[d], pts[3 * i + d]), hi[d] = std::max(hi[d], pts[3 * i + d]);
  float diag = std::sqrt((hi[0] - lo[0]) * (hi[0] - lo[0]) + (hi[1] - lo[1]) * (hi[1] - lo[1]) +
                         (hi[2] - lo[2]) * (hi[2] - lo[2]));
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
