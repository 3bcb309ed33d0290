// The Hilbert order's two sorts on the same keys, interleaved rounds in one process (issue 37):
// order_by_buckets (the library's) against order_by_merge (the per-thread radix sorts and merge it
// replaced, kept for n >= 2^31). Keys: 1M Cornell queries' order permuted by a multiplicative hash.
//   g++ -std=c++17 -O3 -Ilib/include -Ilib/src -Ikernels bench/results/e2e/query_order_sort_ab.cpp lib/src/sfc/hilbert.cpp -o /tmp/sort_ab -lpthread
//   /tmp/sort_ab   (reads /tmp/h37w_data/cornell_q1m.npy: make_dataset's 1M Cornell queries)
// Builds against the sources of commit 3608be4 (git worktree add /tmp/qo 3608be4; the internal
// sorters' signatures changed since); kept as the record of that A/B.
// Result (AVX-512 EPYC, 2 threads, load 11): median ms: full order 132.1  bucket sort 59.7  radix+merge 83.6
#include "core/query_order.cpp"
#include <chrono>
#include <cstdio>
#include <random>
#include <algorithm>
using namespace bhcl::detail;
int main(int argc, char** argv) {
  std::size_t n = 1000000;
  std::vector<float> q(3*n);
  FILE* f = fopen("/tmp/h37w_data/cornell_q1m.npy","rb"); fseek(f,128,SEEK_SET); fread(q.data(),4,3*n,f); fclose(f);
  // keys as hilbert_query_order makes them, then each sorter, interleaved rounds
  auto t = [](){return std::chrono::steady_clock::now();};
  std::vector<double> rb, rm, rfull;
  for (int r=0;r<7;++r){
    auto t0=t(); auto o=hilbert_query_order(q.data(), n); auto t1=t();
    rfull.push_back(std::chrono::duration<double,std::milli>(t1-t0).count());
    std::vector<std::uint64_t> keys(n); for(std::size_t i=0;i<n;++i) keys[i]=(std::uint64_t(o[i])*2654435761u)&((1ull<<48)-1);
    auto t2=t(); auto a=order_by_buckets(keys,2); auto t3=t(); auto b=order_by_merge(keys,2,(n+1)/2); auto t4=t();
    rb.push_back(std::chrono::duration<double,std::milli>(t3-t2).count()); rm.push_back(std::chrono::duration<double,std::milli>(t4-t3).count());
    if (a!=b) { puts("MISMATCH"); return 1; }
  }
  std::sort(rb.begin(),rb.end()); std::sort(rm.begin(),rm.end()); std::sort(rfull.begin(),rfull.end());
  printf("median ms: full order %.1f  bucket sort %.1f  radix+merge %.1f\n", rfull[3], rb[3], rm[3]);
}
