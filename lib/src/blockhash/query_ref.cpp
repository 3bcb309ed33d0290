// The host reference of the block-hash query: the kernel's algorithm (kernels/blockhash_knn.cl)
// step for step, with the same candidates in the same order and the same float arithmetic, so the
// kernel's answers must equal it bit for bit. Keep the two in step.
#include <algorithm>
#include <cmath>
#include <thread>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/reference.hpp"
#include "core/parallel.hpp"

namespace bhcl::blockhash {
namespace {

struct BucketRef {
  std::uint32_t aq;      // |Q|
  std::uint32_t bucket;  // index into Structure::buckets
};

// Row qi of the result from the top-k list (empty slots stay -1 / +inf), and its count.
void write_row(KnnResult& out, std::size_t qi, std::uint32_t k, const std::vector<float>& bd,
               const std::vector<std::int32_t>& bi) {
  std::size_t row = qi * k;
  std::int32_t count = 0;
  for (std::uint32_t j = 0; j < k; ++j) {
    if (bi[j] == BHCL_EMPTY_SLOT_ID) continue;
    out.ids[row + j] = bi[j];
    out.dist2[row + j] = bd[j];
    ++count;
  }
  out.counts[qi] = count;
}

// Offers block b's points to the top-k list (found entries held) as the kernels' block scans do;
// returns the points examined.
std::uint32_t scan_block(const Structure& s, long b, const float* q, float r2, std::uint32_t k,
                         std::vector<float>& bd, std::vector<std::int32_t>& bi, std::uint32_t& found) {
  const bhcl_bh_block& blk = s.blocks[b];
  const std::int32_t cnt = s.boxes[b].count;
  for (std::int32_t j = 0; j < cnt; ++j) {
    const float p[3] = {blk.x[j], blk.y[j], blk.z[j]};
    float d = reference::dist2_float(p, q);
    std::int32_t id = blk.id[j];
    if (!(d <= r2)) continue;
    if (!bhcl_topk_accepts(bd.data(), bi.data(), k, d, id)) continue;
    found = bhcl_topk_push(bd.data(), bi.data(), k, found, d, id);
  }
  return static_cast<std::uint32_t>(cnt);
}

inline float box_dist2(const bhcl_bh_box& b, const float* q) { return bh_box_dist2_xyz(q[0], q[1], q[2], &b); }

// 1. of the query: the query's bucket in each table (and the near-side neighbours) into cand, in
// order of |Q|; equal |Q| keep the gathering order (table, then home, x, y, z neighbour), as the
// kernels' bh_gather_buckets.
void gather_buckets(const Structure& s, const float* q, bool probes, std::vector<BucketRef>& cand) {
  const std::uint32_t P = static_cast<std::uint32_t>(s.info.P);
  cand.clear();
  for (int t = 0; t < s.info.L; ++t) {
    std::uint32_t h[3];
    long nbr[3];
    for (int d = 0; d < 3; ++d) {
      h[d] = hash_coord(s.thr(t, d), P, q[d]);
      nbr[d] = probes ? bh_near_side(s.thr(t, d), P, h[d], q[d]) : -1;
    }
    for (int pr = 0; pr < (probes ? 4 : 1); ++pr) {
      std::uint32_t c[3] = {h[0], h[1], h[2]};
      if (pr > 0) {
        if (nbr[pr - 1] < 0) continue;
        c[pr - 1] = static_cast<std::uint32_t>(nbr[pr - 1]);
      }
      long b = s.find_bucket(t, s.cell_key(c));
      if (b < 0 || s.buckets[b].n_refs == 0) continue;  // empty buckets cannot help
      std::int32_t qv = s.buckets[b].q;
      BucketRef r{static_cast<std::uint32_t>(qv < 0 ? -qv : qv), static_cast<std::uint32_t>(b)};
      std::size_t pos = cand.size();
      cand.push_back(r);
      while (pos > 0 && cand[pos - 1].aq > r.aq) {
        cand[pos] = cand[pos - 1];
        --pos;
      }
      cand[pos] = r;
    }
  }
}

}  // namespace

void reference_query(const Structure& s, const float* queries, std::size_t n,
                     const SearchParams& params, bool probes, KnnResult& out,
                     std::vector<std::int32_t>* examined, unsigned threads) {
  const int kmax = kmax_variant(params.k);
  const std::uint32_t k = static_cast<std::uint32_t>(params.k);
  const std::uint32_t budget = BlockHashIndex::budget(params);
  const float r2 = std::isinf(params.max_radius) ? INFINITY : params.max_radius * params.max_radius;
  const std::uint32_t cap = scan_cap(kmax, s.info.X);
  const bool box_skip = s.info.box_skip, box_order = s.info.box_order;
  const std::uint32_t keep = keep_blocks(budget, kmax, s.info.X);
  const std::uint32_t seeds = seed_side(s.info.hilbert_seed, params.k, s.info.X);
  out.resize(n, params.k);
  if (examined) examined->assign(n, 0);

  auto work = [&](std::size_t begin, std::size_t end) {
    std::vector<BucketRef> cand;
    std::vector<std::int32_t> scanned;
    std::vector<std::pair<float, std::int32_t>> boxq;
    std::vector<float> bd(k);
    std::vector<std::int32_t> bi(k);
    for (std::size_t qi = begin; qi < end; ++qi) {
      const float* q = queries + 3 * qi;
      if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) continue;
      gather_buckets(s, q, probes, cand);  // 1. the query's buckets, in order of |Q|
      std::fill(bd.begin(), bd.end(), INFINITY);
      std::fill(bi.begin(), bi.end(), BHCL_EMPTY_SLOT_ID);
      std::uint32_t ex = 0;
      std::uint32_t found = 0;
      auto scan = [&](std::int32_t b) { ex += scan_block(s, b, q, r2, k, bd, bi, found); };
      if (box_order) {
        // 2a. Box order: every candidate (seeds, then the buckets' blocks) within the radius,
        //     sorted by (box distance, block); the first `keep` distinct are scanned in order
        //     until the budget is spent or a box is farther than the k-th distance.
        boxq.clear();
        if (seeds) {
          // The blocks around the query's Hilbert position: the last block whose first key is
          // <= the query's key, and `seeds` on each side.
          std::uint64_t key = query_hilbert_key(s, q);
          long j = long(std::upper_bound(s.block_keys.begin(), s.block_keys.end(), key) - s.block_keys.begin()) - 1;
          if (j < 0) j = 0;
          long a = std::max(0L, j - long(seeds)), e = std::min(long(s.blocks.size()) - 1, j + long(seeds));
          for (long b = a; b <= e; ++b) {
            float d = box_dist2(s.boxes[b], q);
            if (!(d > r2)) boxq.emplace_back(d, std::int32_t(b));
          }
        }
        for (const BucketRef& cr : cand) {
          const bhcl_bh_bucket& bk = s.buckets[cr.bucket];
          for (std::uint32_t r = 0; r < bk.n_refs; ++r) {
            std::int32_t b = s.refs[bk.first_ref + r];
            float d = box_dist2(s.boxes[b], q);
            if (!(d > r2)) boxq.emplace_back(d, b);
          }
        }
        std::sort(boxq.begin(), boxq.end());
        boxq.erase(std::unique(boxq.begin(), boxq.end()), boxq.end());
        if (boxq.size() > keep) boxq.resize(keep);
        for (const auto& [d, b] : boxq) {
          if (ex >= budget || d > bd[k - 1]) break;
          scan(b);
        }
      }
      // 2b. Bucket order: the blocks of the buckets in that order, each scanned once, until
      //     ceil(A k) points.
      scanned.clear();
      for (const BucketRef& cr : (box_order ? std::vector<BucketRef>{} : cand)) {
        const bhcl_bh_bucket& bk = s.buckets[cr.bucket];
        bool done = false;
        for (std::uint32_t r = 0; r < bk.n_refs; ++r) {
          if (ex >= budget || scanned.size() >= cap) {
            done = true;
            break;
          }
          std::int32_t b = s.refs[bk.first_ref + r];
          const bhcl_bh_box& box = s.boxes[b];
          if (box_skip) {
            float d = box_dist2(box, q);
            if (d > r2 || d > bd[k - 1]) continue;  // nothing in it can enter the list
          }
          if (std::find(scanned.begin(), scanned.end(), b) != scanned.end()) continue;
          scanned.push_back(b);
          scan(b);
        }
        if (done) break;
      }
      write_row(out, qi, k, bd, bi);
      if (examined) (*examined)[qi] = static_cast<std::int32_t>(ex);
    }
  };
  detail::parallel_for(n, work, threads, 1);
}

}  // namespace bhcl::blockhash
