// Page-cache population of a fallocated, mapped file, with and without MADV_HUGEPAGE, against
// anonymous memory (issue 37, write_paths_ab.txt section C).  g++ -O2 pbench.cpp -o pbench; ./pbench MB
// (writes /tmp/h37_data/pb.bin).
#include <fcntl.h>
#include <sys/mman.h>
#include <unistd.h>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
using C = std::chrono::steady_clock;
double s(C::time_point t){return std::chrono::duration<double>(C::now()-t).count()*1e3;}
int main(int argc,char**argv){
  size_t bytes = size_t(atoi(argv[1]))<<20; const char* path="/tmp/h37_data/pb.bin";
  for (int huge=0; huge<2; ++huge) for (int r=0;r<2;++r){
    unlink(path);
    int fd=open(path,O_RDWR|O_CREAT|O_TRUNC,0644); fallocate(fd,0,0,bytes);
    char* m=(char*)mmap(nullptr,bytes,PROT_READ|PROT_WRITE,MAP_SHARED,fd,0);
    auto t=C::now(); int h = huge ? madvise(m,bytes,MADV_HUGEPAGE) : 0;
    int p = madvise(m,bytes,MADV_POPULATE_WRITE); double pop=s(t); t=C::now();
    memset(m,1,bytes); double w=s(t); t=C::now(); munmap(m,bytes); double um=s(t);
    printf("huge %d(%d) populate %d: %.1f ms, then memset %.1f ms, munmap %.1f\n", huge, h, p, pop, w, um);
    close(fd);
  }
  unlink(path);
  // anon for comparison
  for (int r=0;r<2;++r){ auto t=C::now(); char* a=(char*)malloc(bytes); memset(a,1,bytes); printf("anon malloc+memset %.1f ms\n", s(t)); free(a);}
}
