// Block hashing, grid layout: the host reference of blockhash_grid_knn.cl. The traversal is the
// kernel's own (kernels/grid_search.h); only the top-k list is the scalar one, which keeps the
// same k nearest by (distance, index) as the kernel's register list, so the rows are identical.
#include <cmath>

#include "blockhash/grid.hpp"
#include "blockhash_cl/error.hpp"
#include "core/parallel.hpp"

namespace bhcl::blockhash {
namespace {

struct RefTopK {
  std::vector<float> d;
  std::vector<std::int32_t> i;
  std::uint32_t k = 0, n = 0;
  float max_r2 = INFINITY;
  float bound() const { return std::fmin(max_r2, d[k - 1]); }
};

inline void ref_scan(RefTopK* t, float qx, float qy, float qz, const float* px, const float* py,
                     const float* pz, const std::int32_t* pid, std::uint32_t a, std::uint32_t b) {
  for (std::uint32_t p = a; p < b; ++p) {
    float d = bhcl_dist2_xyz(qx, qy, qz, px[p], py[p], pz[p]);
    if (d <= t->bound() && bhcl_topk_accepts(t->d.data(), t->i.data(), t->k, d, pid[p]))
      t->n = bhcl_topk_push(t->d.data(), t->i.data(), t->k, t->n, d, pid[p]);
  }
}

}  // namespace
}  // namespace bhcl::blockhash

#define BHCL_GRID_STATE bhcl::blockhash::RefTopK
#define BHCL_GRID_BOUND(st) ((st)->bound())
#define BHCL_GRID_SCAN(st, a, b) bhcl::blockhash::ref_scan(st, qx, qy, qz, px, py, pz, pid, a, b)
#include "grid_search.h"

namespace bhcl::blockhash {

GridTraversal grid_traversal(bool cpu) {
  return cpu ? GridTraversal{32u, BHCL_GRID_FINE_RINGS, BHCL_GRID_WALKBUF} : GridTraversal{0u, BHCL_GRID_FINE_RINGS, 0u};
}

void reference_query_grid(const Grid& g, const float* queries, std::size_t n, int k, float max_r2,
                          std::uint32_t budget, const GridTraversal& form, KnnResult& out,
                          std::vector<std::int32_t>* examined, unsigned threads) {
  if (form.row_cap > BHCL_GRID_ROWBUF)
    throw Error("blockhash grid reference: row_cap " + std::to_string(form.row_cap) + " above " + std::to_string(BHCL_GRID_ROWBUF));
  if (form.walk_cap > BHCL_GRID_WALKBUF)
    throw Error("blockhash grid reference: walk_cap " + std::to_string(form.walk_cap) + " above " + std::to_string(BHCL_GRID_WALKBUF));
  if (g.occ.size() != grid_occupancy_bytes(g.geom))
    throw Error("blockhash grid reference: the occupancy pyramid is not built");
  out.resize(n, k);
  if (examined) examined->assign(n, 0);
  detail::parallel_for(
      n,
      [&](std::size_t b, std::size_t e) {
        RefTopK t;
        t.k = static_cast<std::uint32_t>(k);
        t.d.resize(k);
        t.i.resize(k);
        for (std::size_t q = b; q < e; ++q) {
          std::fill(t.d.begin(), t.d.end(), INFINITY);
          std::fill(t.i.begin(), t.i.end(), BHCL_EMPTY_SLOT_ID);
          t.n = 0;
          t.max_r2 = max_r2;
          const float qx = queries[3 * q], qy = queries[3 * q + 1], qz = queries[3 * q + 2];
          std::uint32_t ex = 0;
          if (std::isfinite(qx) && std::isfinite(qy) && std::isfinite(qz))
            ex = bhcl_grid_search(g.starts.data(), g.x.data(), g.y.data(), g.z.data(), g.ids.data(),
                                  g.occ.data(), g.geom, g.dbox, qx, qy, qz, budget, form.row_cap, form.fine_rings, form.walk_cap,
                                  static_cast<std::uint32_t>(k), &t);
          std::int32_t found = 0;
          for (int j = 0; j < k; ++j) {
            const std::size_t o = q * std::size_t(k) + std::size_t(j);
            const bool empty = t.i[j] == BHCL_EMPTY_SLOT_ID;
            out.ids[o] = empty ? BHCL_MISSING_ID : t.i[j];
            out.dist2[o] = empty ? INFINITY : t.d[j];
            found += empty ? 0 : 1;
          }
          out.counts[q] = found;
          if (examined) (*examined)[q] = static_cast<std::int32_t>(ex);
        }
      },
      threads, 256);
}

}  // namespace bhcl::blockhash
