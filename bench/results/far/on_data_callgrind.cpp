// The grid's host reference (the kernel's traversal, kernels/grid_search.h compiled as C++) on
// queries among the points, for callgrind (on_data_callgrind.sh): issue 36's "no loss on the
// data" in a count that does not move with the machine's load. Sets: "uniform" (200k points in
// the unit cube, queries uniform in it) and "walls" (200k points on the six faces of the unit
// cube, Cornell-like; queries on the faces, jittered 1e-3 off them). Usage: PROG SET K NQ.
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <vector>
#include "blockhash/grid.hpp"
using namespace bhcl::blockhash;
extern "C" __attribute__((noinline)) void run_query(const Grid& g, const std::vector<float>& q, int k, bhcl::KnnResult& out,
                                                    std::vector<std::int32_t>* ex) {
#ifdef BHCL_OLD7F  // the tree the issue was filed on (7f729ba): no pyramid, the row cap instead of a traversal
  reference_query_grid(g, q.data(), q.size() / 3, k, INFINITY, 0xffffffffu, grid_row_cap(true), out, ex, 1);
#else
  reference_query_grid(g, q.data(), q.size() / 3, k, INFINITY, 0xffffffffu, grid_traversal(true), out, ex, 1);
#endif
}
static void on_walls(std::mt19937_64& rng, float* p, float jitter) {
  std::uniform_real_distribution<float> u(0.0f, 1.0f), j(-jitter, jitter);
  const int face = static_cast<int>(u(rng) * 6) % 6, axis = face / 2;
  for (int d = 0; d < 3; ++d) p[d] = u(rng);
  p[axis] = (face % 2 ? 1.0f : 0.0f) + j(rng);
}
int main(int argc, char** argv) {
  const char* set = argc > 1 ? argv[1] : "uniform";
  const int k = argc > 2 ? atoi(argv[2]) : 10;
  const size_t nq = argc > 3 ? atoi(argv[3]) : 2000, n = 200000;
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::vector<float> pts(3 * n), q(3 * nq);
  const bool walls = std::strcmp(set, "walls") == 0;
  for (size_t i = 0; i < n; ++i)
    if (walls) on_walls(rng, &pts[3 * i], 0.0f);
    else for (int d = 0; d < 3; ++d) pts[3 * i + d] = u(rng);
  for (size_t i = 0; i < nq; ++i)
    if (walls) on_walls(rng, &q[3 * i], 1e-3f);
    else for (int d = 0; d < 3; ++d) q[3 * i + d] = u(rng);
  GridBuildStats st;
  Grid g;
#ifdef BHCL_OLD7F
  GridBuildParams a; a.threads = 1;
  build_grid(pts.data(), n, a, g, &st);
#else
  GridInput in; in.xyz = pts.data(); in.n_aos = n;
  GridBuildArgs a; a.threads = 1;  // the build's own tuned side
  build_grid(in, a, g, &st);
  build_grid_occupancy(g, 1);
#endif
  bhcl::KnnResult out; std::vector<std::int32_t> ex;
  run_query(g, q, k, out, &ex);
  double s = 0; for (auto e : ex) s += e;
  printf("%s k %d grid %u x %u x %u h %g examined/query %.1f d0 %g\n", set, k, g.geom.nx, g.geom.ny, g.geom.nz, g.geom.h,
         s / nq, out.dist2[0]);
}
