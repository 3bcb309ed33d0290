// make_dataset: writes a benchmark data set and its queries as NPY (N x 3 float32), exactly as the
// C++ benchmarks load them (bench_util.hpp's load_set), so that bench/python_bench.py measures the
// Python packages on the same points and queries.
#include <cstdio>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"
#include "bench_cli.hpp"
#include "bench_util.hpp"

int main(int argc, char** argv) {
  std::string data = "cornell", out_points, out_queries, data_dir;
  std::size_t N = 1000000, queries = 100000;
  bhcl::bench::BenchCli cli("make_dataset", "Write a benchmark data set and its queries as NPY files");
  cli.data_dir(data_dir);
  cli.text("data", data, "the set: bunny, dragon, autzen (files) or uniform, clustered, duplicates, cornell (generated)", "NAME")
      ->required();
  cli.integer("N", N, "points (file sets: the first N; 0: all)", 0, 2147483646.0);
  cli.queries(queries);
  cli.text("out-points", out_points, "write the points here (.npy)", "FILE")->required();
  cli.text("out-queries", out_queries, "write the queries here (.npy)", "FILE")->required();
  cli.parse(argc, argv);
  try {
    std::vector<float> pts, qs;
    if (!bhcl::bench::load_set(data_dir, data, N, queries, pts, qs)) return 1;
    bhcl::write_npy_file(out_points, pts.data(), pts.size() / 3, 3);
    bhcl::write_npy_file(out_queries, qs.data(), qs.size() / 3, 3);
    std::printf("make_dataset: %s: %zu points -> %s, %zu queries -> %s\n", data.c_str(), pts.size() / 3,
                out_points.c_str(), qs.size() / 3, out_queries.c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "make_dataset: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
