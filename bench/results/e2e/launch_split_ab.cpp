// One launch against launches under PoCL's 65535-item small-grid limit (max_batch = 65472), interleaved, one process.
// Build: g++ -std=c++17 -O2 -Ilib/include -Ibuild/generated/include bench/results/e2e/launch_split_ab.cpp -o /tmp/launch_ab build/lib/libblockhash_cl.a -lOpenCL -llz4 -lflann_cpp -lpthread
// Run: POCL_MAX_PTHREAD_COUNT=2 /tmp/launch_ab 1000000 10   (and 50). Built at e25ca3e (before the quirk; after it both arms split).
// Result (AVX-512 AMD EPYC, 2 threads, load 3-4.8, 2026-12-05 04:10-04:18 UTC, uniform 1M points and 1M queries, 7 rounds):
//   k = 10: one / split kernel 1.054, wall 1.044 (split faster); k = 50: 1.003 / 1.004; rows equal.
//   Two clusters (far_bench's, 60000 points, 100k queries between them, k = 10, 15 rounds, the same program with its data
//   swapped, load ~1.2): one / split (2 launches) kernel 0.979, wall 0.980 (split 2 % slower). Within noise both ways.
#include <blockhash_cl/blockhash_cl.hpp>
#include <algorithm>
#include <cstdio>
#include <random>
using namespace bhcl;
int main(int argc, char** argv) {
  size_t n = 1000000, nq = argc > 1 ? atoi(argv[1]) : 1000000; int k = argc > 2 ? atoi(argv[2]) : 10;
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  std::vector<float> pts(3 * n), q(3 * nq);
  for (auto& v : pts) v = u(rng);
  for (auto& v : q) v = u(rng);
  auto rt = std::make_shared<Runtime>();
  auto ix = make_index("blockhash", rt, pts.data(), n);
  SearchParams a; a.k = k; SearchParams b = a; b.max_batch = 65472;
  KnnResult ra, rb;
  ix->query(q.data(), nq, a, ra); ix->query(q.data(), nq, b, rb);
  printf("rows equal %d\n", int(ra.ids == rb.ids && ra.dist2 == rb.dist2));
  std::vector<double> rk, rw;
  for (int r = 0; r < 7; ++r) {
    QueryStats sa = ix->query(q.data(), nq, a, ra);
    QueryStats sb = ix->query(q.data(), nq, b, rb);
    rk.push_back(sa.query_s / sb.query_s); rw.push_back(sa.wall_s / sb.wall_s);
    printf("one launch kernel %.4f wall %.4f | %zu launches kernel %.4f wall %.4f\n", sa.query_s, sa.wall_s, sb.batches, sb.query_s, sb.wall_s);
  }
  std::sort(rk.begin(), rk.end()); std::sort(rw.begin(), rw.end());
  printf("median one/split: kernel %.3f wall %.3f\n", rk[3], rw[3]);
}
