// Built and run by hand for bench/results/issue38/threads.txt:
//   for w in main h38; do g++ -std=c++17 -O1 -pthread -I/work/$w/lib/include threads.cpp -o t_$w && ./t_$w; done
// parallel_for with 8 threads in an address space with room for no thread stack (issue 38).
#include <sys/resource.h>
#include <unistd.h>
#include <cstdio>
#include <fstream>
#include <vector>
#include "blockhash_cl/parallel.hpp"
int main() {
  std::ifstream statm("/proc/self/statm");
  std::size_t pages = 0;
  statm >> pages;
  rlim_t lim = rlim_t(pages) * sysconf(_SC_PAGESIZE) + (4u << 20);
  rlimit rl{lim, lim};
  setrlimit(RLIMIT_AS, &rl);
  std::vector<int> hit(64, 0);
  bhcl::detail::parallel_for(64, [&](std::size_t b, std::size_t e) { for (auto i = b; i < e; ++i) hit[i]++; }, 8, 1);
  int sum = 0;
  for (int h : hit) sum += h;
  std::printf("parallel_for over 8 threads under a 4 MiB address-space margin: %d of 64 elements done once\n", sum);
}
