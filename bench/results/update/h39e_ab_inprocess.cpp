// h39e: in-process A/B of a temporary switch in the library (an environment variable read where the two arms
// differ; the switches are not committed: the arms were the grid rebuild's records pass for the new points against
// writing them straight into the arrays (H39E_DIRECT), and the rebuild from cell order against the bucket passes
// (H39E_NOCELLS)). Per round both arms, their order alternating: a 1M uniform grid built, 25 % more inserted (one
// rebuild across the band); the medians of the rebuild's placement time (BlockHashBuildInfo::t_scatter), of the
// update's wall time, and of the per-round ratios (wall and process CPU; set / unset).
//   g++ -O2 -std=c++17 -DCL_HPP_MINIMUM_OPENCL_VERSION=120 -DCL_HPP_TARGET_OPENCL_VERSION=120 \
//     -DCL_TARGET_OPENCL_VERSION=120 -Ilib/include -Ilib/data/include -I$B/generated/include h39e_ab_inprocess.cpp \
//     $B/lib/libblockhash_cl.a $B/libbhcl_data.a $B/lib/libblockhash_cl.a -lOpenCL -llz4 -lpthread -o ab
//   POCL_MAX_PTHREAD_COUNT=2 ./ab VARIABLE ROUNDS
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <vector>
#include <ctime>
static double cpu(){timespec t; clock_gettime(CLOCK_PROCESS_CPUTIME_ID,&t); return t.tv_sec+1e-9*t.tv_nsec;}
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/runtime.hpp"
using namespace bhcl;
static double now(){return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();}
int main(int argc,char**argv){
  const char* var=argv[1]; int rounds=atoi(argv[2]); size_t N=1000000, m=N/4;
  auto rt=default_runtime();
  std::vector<float> all=datasets::by_name("uniform",N+m,1);
  std::vector<double> sc[2], up[2], cu[2], ratio, cr;
  for(int r=0;r<rounds;r++) for(int a=0;a<2;a++){
    int arm=(r&1)?1-a:a;
    if(arm) setenv(var,"1",1); else unsetenv(var);
    auto ix=make_index("blockhash",rt,all.data(),N);
    double t0=now(), c0=cpu(); ix->insert(all.data()+3*N,m); double tu=now()-t0, tc=cpu()-c0; cu[arm].push_back(tc);
    auto* bh=dynamic_cast<BlockHashIndex*>(ix.get());
    sc[arm].push_back(bh->info().t_scatter); up[arm].push_back(tu);
  }
  for(int a=0;a<2;a++){ auto s=sc[a], u=up[a]; std::sort(s.begin(),s.end()); std::sort(u.begin(),u.end());
    printf("%s=%d scatter median %.4f update median %.4f\n",var,a,s[s.size()/2],u[u.size()/2]); }
  for(size_t i=0;i<sc[0].size();i++) ratio.push_back(up[1][i]/up[0][i]); std::sort(ratio.begin(),ratio.end());
  for(size_t i=0;i<cu[0].size();i++) cr.push_back(cu[1][i]/cu[0][i]); std::sort(cr.begin(),cr.end());
  printf("per-round update cpu ratio (set/unset) median %.3f  [%.3f .. %.3f]\n",cr[cr.size()/2],cr[cr.size()/4],cr[3*cr.size()/4]);
  printf("per-round update ratio (set/unset) median %.3f  [%.3f .. %.3f]\n",ratio[ratio.size()/2],ratio[ratio.size()/4],ratio[3*ratio.size()/4]);
}
