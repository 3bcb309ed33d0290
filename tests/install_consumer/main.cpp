// Uses the installed library: a block-hash index answers a query batch; exits non-zero if not.
#include <blockhash_cl/blockhash_cl.hpp>
#include <cstdio>
int main() {
  auto rt = std::make_shared<bhcl::Runtime>();
  auto pts = bhcl::datasets::uniform(1000, 1);
  auto qs = bhcl::datasets::uniform(10, 2);
  bhcl::BlockHashIndex index(rt, pts.data(), 1000, bhcl::BlockHashBuildParams{});
  bhcl::SearchParams p; p.k = 5;
  auto r = index.query(qs, p);
  std::printf("install_consumer: first neighbour of query 0: %d (d2 %g)\n", r.id(0, 0), r.d2(0, 0));
  return r.counts[0] == 5 && r.id(0, 0) >= 0 ? 0 : 1;
}
