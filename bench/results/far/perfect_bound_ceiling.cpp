// The ceiling of any first bound for the far walk (issue 36, session 10): two clusters (far_bench's,
// 60000 points, 2000 queries between them), the host reference of the grid's traversal run per
// query with max_r2 = the query's exact k-th distance (the tightest bound any seeding could give)
// against max_r2 = inf. Build and count as callgrind_harness.sh does:
//   clang++-15 -std=c++17 -O2 -march=haswell -gdwarf-4 -Ilib/src -Ilib/include -Ikernels -Ibuild/lib -Ibuild/lib/include \
//     bench/results/far/perfect_bound_ceiling.cpp lib/src/blockhash/grid_query_ref.cpp -o /tmp/pb build/lib/libblockhash_cl.a -lOpenCL -lpthread
//   for m in 0 1; do valgrind --tool=callgrind --toggle-collect='run_q*' --callgrind-out-file=/dev/null /tmp/pb 10 2000 $m; done
// Result at e25ca3e (k = 10): inf 49,057,746 instructions, examined 27.5 a query; exact bound 41,368,585 (-15.7 %,
// about -17 % of the traversal without the per-call overhead), examined 15.8; rows identical. So a
// neighbour's answer as a first bound (a leader / follower dispatch) could save at most ~1/6 there.
#include <cstdio>
#include <cstdlib>
#include <cmath>
#include <random>
#include <vector>
#include "two_clusters_grid.hpp"
using namespace bhcl::blockhash;
extern "C" __attribute__((noinline)) void run_q(const Grid& g, const float* q, int k, float r2, bhcl::KnnResult& out, std::vector<std::int32_t>* ex) {
  reference_query_grid(g, q, 1, k, r2, 0xffffffffu, grid_traversal(true), out, ex, 1);
}
int main(int argc, char** argv) {
  int k = atoi(argv[1]); size_t nq = atoi(argv[2]); int mode = atoi(argv[3]);
  std::vector<float> pts, q;
  two_clusters(nq, pts, q);
  Grid g;
  build_clusters_grid(pts, 24, g);
  bhcl::KnnResult truth; std::vector<std::int32_t> ex;
  reference_query_grid(g, q.data(), nq, k, INFINITY, 0xffffffffu, grid_traversal(true), truth, &ex, 1);
  double s = 0; long diff = 0;
  for (size_t i = 0; i < nq; ++i) {
    float r2 = INFINITY;
    if (mode == 1) r2 = std::nextafter(truth.dist2[i * k + k - 1], INFINITY);
    bhcl::KnnResult o; std::vector<std::int32_t> e;
    run_q(g, &q[3*i], k, r2, o, &e);
    s += e[0];
    for (int j = 0; j < k; ++j) diff += o.ids[j] != truth.ids[i*k+j];
  }
  printf("mode %d examined/query %.1f diff %ld\n", mode, s / nq, diff);
}
