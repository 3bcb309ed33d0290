// Build stages per round (issue 36, session 13): a grid's fresh build of a generated set, R rounds in one
// process, the median wall time and the median of each stage BlockHashBuildInfo reports (tune, cells,
// bucket, sort = placement, occupancy). Usage: drv DATA N ROUNDS (DATA: cornell, uniform, clustered).
// Built against a build tree B (not part of the CMake build):
//   g++ -O2 -std=c++17 -Ilib/include -Ilib/data/include -I$B/generated/include build_stages_driver.cpp \
//     $B/lib/libblockhash_cl.a $B/libbhcl_data.a $B/lib/libblockhash_cl.a -lOpenCL -llz4 -lpthread -o drv
// Session 13 (AVX-512 EPYC, POCL_MAX_PTHREAD_COUNT=2, drv cornell 1000000 21, quiet): before (eddc578)
// sort 6.63-6.83 ms, occupancy 4.39-4.62 ms; after (4d9c462) sort 7.26-7.39 ms, occupancy 0.95-1.03 ms.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/runtime.hpp"
using namespace bhcl;
static double now(){return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();}
static double med(std::vector<double> v){std::sort(v.begin(),v.end());return v[v.size()/2];}
int main(int argc,char**argv){
  std::string data=argv[1]; size_t N=atol(argv[2]); int rounds=atoi(argv[3]);
  auto rt=default_runtime();
  std::vector<float> pts=datasets::by_name(data,N,1);
  std::vector<double> w,tu,ce,co,sc,oc;
  for(int r=0;r<rounds;r++){
    double t0=now(); auto ix=make_index("blockhash",rt,pts.data(),N); double t=now()-t0; w.push_back(t*1e3);
    auto* b=dynamic_cast<BlockHashIndex*>(ix.get()); const auto& in=b->info();
    tu.push_back(in.t_tune*1e3); ce.push_back(in.t_cells*1e3); co.push_back(in.t_count*1e3); sc.push_back(in.t_scatter*1e3); oc.push_back(in.t_occupancy*1e3);
  }
  printf("%s %zu median wall %.2f ms (min %.2f): tune %.2f cells %.2f bucket %.2f sort %.2f occupancy %.2f\n",data.c_str(),N,med(w),*std::min_element(w.begin(),w.end()),med(tu),med(ce),med(co),med(sc),med(oc));
}
