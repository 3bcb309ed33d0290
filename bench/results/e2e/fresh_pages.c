// Issue 37: what a fresh page costs on the VM measured. Maps N MB of anonymous memory (advised
// MADV_HUGEPAGE), makes it present (MADV_POPULATE_WRITE), unmaps it, five times in a row: the
// first round takes memory the guest has not used lately, the next ones the pages just freed.
//   gcc -O2 -o fresh_pages bench/results/e2e/fresh_pages.c && ./fresh_pages 400; sleep 3; ./fresh_pages 400
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <time.h>
static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + t.tv_nsec * 1e-9;
}
static double touch(size_t mb) {
  const size_t n = mb << 20;
  char* p = mmap(0, n, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
  if (p == MAP_FAILED) return -1;
  madvise(p, n, MADV_HUGEPAGE);
  const double t = now();
  madvise(p, n, MADV_POPULATE_WRITE);
  const double s = now() - t;
  munmap(p, n);
  return s;
}
int main(int argc, char** argv) {
  const size_t mb = argc > 1 ? (size_t)atoi(argv[1]) : 400;
  for (int i = 0; i < 5; i++) printf("%zu MB: %.1f ms\n", mb, touch(mb) * 1e3);
  return 0;
}
