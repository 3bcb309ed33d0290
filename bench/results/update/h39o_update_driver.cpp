// h39o: one method's fresh build vs one update (update_bench's time_op), wall and process CPU time per round, for
// perf: drv METHOD {i1,i10,r10,i25} ROUNDS [N]. Built against a build tree B (not part of the CMake build):
//   g++ -O2 -g -std=c++17 -DCL_HPP_MINIMUM_OPENCL_VERSION=120 -DCL_HPP_TARGET_OPENCL_VERSION=120 -DCL_TARGET_OPENCL_VERSION=120 \
//     -Ilib/include -Ilib/data/include -I$B/generated/include h39o_update_driver.cpp $B/lib/libblockhash_cl.a \
//     $B/libbhcl_data.a $B/lib/libblockhash_cl.a -lOpenCL -llz4 -lpthread -o drv
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <numeric>
#include <random>
#include <string>
#include <vector>
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/runtime.hpp"
using namespace bhcl;
#include <ctime>
#include <unistd.h>
static double now(){return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();}
static double cpu(){timespec t; clock_gettime(CLOCK_PROCESS_CPUTIME_ID,&t); return t.tv_sec+1e-9*t.tv_nsec;}
int main(int argc,char**argv){
  std::string method=argv[1]; std::string op=argv[2]; int rounds=atoi(argv[3]); size_t N=argc>4?atol(argv[4]):1000000;
  auto rt=default_runtime();
  std::vector<float> all=datasets::by_name("uniform",N+N/4,1);
  std::vector<int> ids(N); std::iota(ids.begin(),ids.end(),0); std::shuffle(ids.begin(),ids.end(),std::mt19937_64(5));
  std::vector<int> drop(ids.begin(),ids.begin()+N/10);
  std::vector<char> gone(N,0); for(int i:drop) gone[i]=1;
  std::vector<float> kept; for(size_t i=0;i<N;i++) if(!gone[i]) kept.insert(kept.end(),&all[3*i],&all[3*i+3]);
  double frac= op=="i1"?0.01: op=="i10"?0.1: op=="r10"?0.1:0.25; bool ins=op[0]=='i';
  size_t m=size_t(frac*N);
  std::vector<double> rs, cr;
  for(int r=0;r<rounds;r++){
    double t0=now(), c0=cpu();
    auto f= ins? make_index(method,rt,all.data(),N+m): make_index(method,rt,kept.data(),kept.size()/3);
    double tf=now()-t0, cf=cpu()-c0; f.reset();
    auto ix=make_index(method,rt,all.data(),N);
    if(getenv("H39O_SLEEP")) usleep(atoi(getenv("H39O_SLEEP")));  // optional pause between the build and the update
    t0=now(); c0=cpu();
    if(ins) ix->insert(all.data()+3*N,m); else ix->remove(drop.data(),drop.size());
    double tu=now()-t0, cu=cpu()-c0;
    rs.push_back(tu/tf); cr.push_back(cu/cf);
    printf("round %d fresh %.4f update %.4f ratio %.3f   cpu fresh %.4f update %.4f ratio %.3f\n",r,tf,tu,tu/tf,cf,cu,cu/cf);
  }
  std::sort(rs.begin(),rs.end()); std::sort(cr.begin(),cr.end()); printf("median ratio %.3f cpu ratio %.3f\n",rs[rs.size()/2],cr[cr.size()/2]);
}
