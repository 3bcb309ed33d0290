// A/B of the query pipeline's Hilbert order (issue 37, session 16): this tree's
// lib/src/core/query_order.cpp against 3952b24's, one process, alternating in each round, each
// call's order checked equal; the sink gathers the queries and their rows as the pipeline's does.
//   git show 3952b24:lib/src/core/query_order.cpp > qo_new.cpp   (then the variant.inc step of
//   build.sh below: its namespace renamed bhclv)
//   ./harness QUERIES.npy N ROUNDS [FIRST]   (queries from build/bench/make_dataset)
#include "core/query_order.cpp"
#include "variant.inc"
#include <chrono>
#include <cstdio>
#include <cstring>
#include <random>
static double now_ms(){return std::chrono::duration<double,std::milli>(std::chrono::steady_clock::now().time_since_epoch()).count();}
int main(int argc, char** argv) {
  const char* path = argv[1]; std::size_t n = std::stoul(argv[2]); int rounds = argc > 3 ? atoi(argv[3]) : 9;
  std::size_t first = argc > 4 ? std::stoul(argv[4]) : 0;
  std::vector<float> all; { FILE* f=fopen(path,"rb"); fseek(f,0,SEEK_END); long sz=ftell(f); fseek(f,128,SEEK_SET); all.resize((sz-128)/4); fread(all.data(),4,all.size(),f); fclose(f);}
  const float* q = all.data() + 3*first;
  std::vector<float> dstA(3*n), dstB(3*n); std::vector<std::uint32_t> rA(n), rB(n);
  std::vector<double> ta, tb, ratio;
  for (int r=0;r<rounds;++r){
    for (int which : {r&1, 1-(r&1)}) {
      float* dst = which? dstB.data(): dstA.data(); std::uint32_t* rows = which? rB.data(): rA.data();
      static const bool nog = getenv("NOGATHER"); bhcl::detail::OrderSink sink = [&](std::size_t lo, std::size_t hi, const std::size_t* o){ if (nog) return; for(std::size_t i=lo;i<hi;++i){ const float* s=q+3*o[i]; dst[3*i]=s[0];dst[3*i+1]=s[1];dst[3*i+2]=s[2]; rows[i]=o[i];} };
      double t0=now_ms();
      std::unique_ptr<std::size_t[]> o;
      if (which) o = bhclv::detail::hilbert_query_order_fresh(q, n, nullptr, &sink);
      else o = bhcl::detail::hilbert_query_order_fresh(q, n, nullptr, &sink);
      double t=now_ms()-t0; (which?tb:ta).push_back(t);
    }
    ratio.push_back(ta.back()/tb.back());
    if (memcmp(rA.data(), rB.data(), 4*n)) { puts("ORDER MISMATCH"); return 1; }
  }
  auto med=[](std::vector<double> v){std::sort(v.begin(),v.end()); return v[v.size()/2];};
  printf("n=%zu this tree %.2f ms  3952b24 %.2f ms  median of per-round ratios (this / 3952b24) %.3f\n", n, med(ta), med(tb), med(ratio));
}
