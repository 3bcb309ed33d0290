// The callgrind harness of bench/results/far/block_planes_callgrind.txt (run by callgrind_harness.sh).
// callgrind harness: the grid's host reference (the kernel's traversal) on far_bench's two clusters.
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>
#include "blockhash/grid.hpp"
using namespace bhcl::blockhash;
extern "C" __attribute__((noinline)) void run_query(const Grid& g, const std::vector<float>& q, int k, bhcl::KnnResult& out,
                                                    std::vector<std::int32_t>* ex) {
  reference_query_grid(g, q.data(), q.size() / 3, k, INFINITY, 0xffffffffu, grid_traversal(true), out, ex, 1);
}
int main(int argc, char** argv) {
  int k = argc > 1 ? atoi(argv[1]) : 10;
  size_t nq = argc > 2 ? atoi(argv[2]) : 2000;
  size_t n = 60000;
  std::mt19937_64 rng(11);
  std::normal_distribution<float> gd(0.0f, 0.01f);
  std::vector<float> pts(3 * n), q(3 * nq);
  for (size_t i = 0; i < n; ++i) { pts[3*i] = gd(rng) + (i % 2 ? 1.0f : 0.0f); pts[3*i+1] = gd(rng); pts[3*i+2] = gd(rng); }
  std::uniform_real_distribution<float> ux(0.1f, 0.9f), uyz(-0.05f, 0.05f);
  for (size_t i = 0; i < nq; ++i) q[3*i] = ux(rng), q[3*i+1] = uyz(rng), q[3*i+2] = uyz(rng);
  GridInput in; in.xyz = pts.data(); in.n_aos = n;
  GridBuildArgs a; a.target_cell_points = argc > 3 ? atof(argv[3]) : 24; a.threads = 1;
  Grid g; GridBuildStats st; build_grid(in, a, g, &st);
  build_grid_occupancy(g, 1);
  bhcl::KnnResult out; std::vector<std::int32_t> ex;
  run_query(g, q, k, out, &ex);
  double s = 0; for (auto e : ex) s += e;
  printf("grid %u x %u x %u h %g examined/query %.1f d0 %g\n", g.geom.nx, g.geom.ny, g.geom.nz, g.geom.h, s / nq, out.dist2[0]);
}
