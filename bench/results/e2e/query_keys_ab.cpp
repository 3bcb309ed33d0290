// The Hilbert query order's keys and whole order, one source against another (issue 37): the
// file named by QO_SRC included whole; prints, per round, the whole order's time on the library's
// threads (first call of the process, then warm) and the keys' pass alone on one thread.
//   git show a165a2a:lib/src/core/query_order.cpp > /tmp/qo_old.cpp
//   g++ -std=c++17 -O3 -DNDEBUG -DQO_SRC='"/tmp/qo_old.cpp"' -Ilib/include -Ilib/src -Ikernels \
//       bench/results/e2e/query_keys_ab.cpp lib/src/sfc/hilbert.cpp -o /tmp/A -lpthread
//   (B: -DQO_SRC='"core/query_order.cpp"'), then A and B alternating: /tmp/A Q.npy [n]
//   (Q.npy: make_dataset's 1M Cornell queries; n: the first n of them). Results: query_keys.md.
#include QO_SRC
#include <chrono>
#include <cstdio>
#include <algorithm>
using namespace bhcl::detail;
static double ms(std::chrono::steady_clock::time_point a){return std::chrono::duration<double,std::milli>(std::chrono::steady_clock::now()-a).count();}
int main(int argc, char** argv) {
  std::size_t n = argc>2? atol(argv[2]) : 1000000;
  std::vector<float> q(3*1000000);
  FILE* f = fopen(argv[1],"rb"); fseek(f,128,SEEK_SET); fread(q.data(),4,3*1000000,f); fclose(f);
  bhcl::sfc::Quantiser qz; qz.bits=16; qz.origin[0]=-1;qz.origin[1]=-1;qz.origin[2]=-1; qz.scale=65536.0/3;
  std::vector<Key> keys(n);
  for (int r=0;r<7;++r){
    auto t0=std::chrono::steady_clock::now();
    auto o=hilbert_query_order_fresh(q.data(), n, nullptr, nullptr);
    double full=ms(t0);
    t0=std::chrono::steady_clock::now();
    hilbert_keys_of_range(q.data(),0,n,qz,Key(1)<<48,keys.data());
    double k1=ms(t0);
    printf("full %.2f ms  keys(1 thread) %.2f ms\n", full, k1);
  }
}
