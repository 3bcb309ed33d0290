// The callgrind harness of bench/results/far/block_planes_callgrind.txt (run by callgrind_harness.sh).
// callgrind harness: the grid's host reference (the kernel's traversal) on far_bench's two clusters.
// Since its data moved into two_clusters_grid.hpp (shared with perfect_bound_ceiling.cpp) the count
// at k = 10 reads 46,505,124 where block_planes_callgrind.txt has 46,522,141 for the same traversal
// (the same points examined): the heap's layout moved, and with it the alignment paths of the
// per-query fills (8.5 instructions a query).
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>
#include "two_clusters_grid.hpp"
using namespace bhcl::blockhash;
extern "C" __attribute__((noinline)) void run_query(const Grid& g, const std::vector<float>& q, int k, bhcl::KnnResult& out,
                                                    std::vector<std::int32_t>* ex) {
  reference_query_grid(g, q.data(), q.size() / 3, k, INFINITY, 0xffffffffu, grid_traversal(true), out, ex, 1);
}
int main(int argc, char** argv) {
  int k = argc > 1 ? atoi(argv[1]) : 10;
  size_t nq = argc > 2 ? atoi(argv[2]) : 2000;
  std::vector<float> pts, q;
  two_clusters(nq, pts, q);
  Grid g;
  build_clusters_grid(pts, argc > 3 ? atof(argv[3]) : 24, g);
  bhcl::KnnResult out; std::vector<std::int32_t> ex;
  run_query(g, q, k, out, &ex);
  double s = 0; for (auto e : ex) s += e;
  printf("grid %u x %u x %u h %g examined/query %.1f d0 %g\n", g.geom.nx, g.geom.ny, g.geom.nz, g.geom.h, s / nq, out.dist2[0]);
}
