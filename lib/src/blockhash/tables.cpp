// Stage 4 of the block-hash build: L tables of buckets. For each point and table, the point's
// block goes into the bucket of the point's cell, once. A bucket keeps at most B blocks:
//   paper (drop new):       the first B in insertion (= Hilbert = block) order;
//   auto (keep top count):  the B blocks holding most of the cell's points (ties: lower block).
// Q = B - #blocks_inserted - #overflows, counted per distinct block.
#include <algorithm>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"

namespace bhcl::blockhash {

// (cell key << 32 | block) of every stride-th sorted point for the thresholds thr[0..2], sorted.
std::vector<std::uint64_t> cell_block_pairs(const Structure& s, const float* const thr[3],
                                            std::uint32_t P, std::size_t stride) {
  std::vector<std::uint64_t> pairs;
  pairs.reserve(s.n_points / stride + 1);
  const std::uint32_t side = P + 1;
  const std::size_t X = static_cast<std::size_t>(s.info.X);
  for (std::size_t i = 0; i < s.n_points; i += stride) {
    float p[3];
    s.point(i, p);
    std::uint32_t h[3];
    for (int d = 0; d < 3; ++d) h[d] = hash_coord(thr[d], P, p[d]);
    std::uint32_t key = (h[0] * side + h[1]) * side + h[2];
    pairs.push_back((std::uint64_t(key) << 32) | std::uint64_t(i / X));
  }
  std::sort(pairs.begin(), pairs.end());
  return pairs;
}

// Points and distinct blocks per occupied cell, from sorted pairs.
void cell_populations(const std::vector<std::uint64_t>& pairs, std::vector<std::uint32_t>* points,
                      std::vector<std::uint32_t>* blocks) {
  for (std::size_t i = 0; i < pairs.size();) {
    std::uint32_t key = std::uint32_t(pairs[i] >> 32);
    std::uint32_t np = 0, nb = 0;
    std::uint64_t last = ~0ull;
    for (; i < pairs.size() && std::uint32_t(pairs[i] >> 32) == key; ++i) {
      ++np;
      if (pairs[i] != last) ++nb;
      last = pairs[i];
    }
    if (points) points->push_back(np);
    if (blocks) blocks->push_back(nb);
  }
}

long Structure::find_bucket(int table, std::uint32_t key) const {
  if (info.direct_addressing) {
    std::uint64_t side = std::uint64_t(info.P) + 1;
    if (key >= side * side * side) return -1;
    return static_cast<long>(std::uint64_t(table) * side * side * side + key);
  }
  auto b = keys.begin() + table_starts[table], e = keys.begin() + table_starts[table + 1];
  auto it = std::lower_bound(b, e, key);
  if (it == e || *it != key) return -1;
  return static_cast<long>(it - keys.begin());
}

TableStats build_tables(Structure& s) {
  const int L = s.info.L;
  const std::uint32_t P = static_cast<std::uint32_t>(s.info.P);
  const std::uint32_t B = static_cast<std::uint32_t>(s.info.B);
  const bool direct = s.info.direct_addressing, top = s.info.keep_top_count;
  const std::uint64_t side = std::uint64_t(P) + 1, cells = side * side * side;
  TableStats st;
  s.table_starts.assign(std::size_t(L) + 1, 0);
  s.keys.clear();
  s.buckets.clear();
  s.refs.clear();
  if (direct) {
    // The talk's layout: every cell has a bucket of B slots. Bound it before allocating.
    double bytes = double(L) * double(cells) * (sizeof(bhcl_bh_bucket) + 4.0 * B);
    if (bytes > double(1ull << 32))
      throw Error("blockhash: direct addressing of L (P+1)^3 = " + std::to_string(L) + " x " +
                  std::to_string(cells) + " buckets of B = " + std::to_string(B) +
                  " slots needs " + std::to_string(bytes / 1e9) +
                  " GB: lower P or B, or use the occupied-cell directory (auto)");
    s.buckets.assign(std::size_t(L * cells), bhcl_bh_bucket{0, 0, static_cast<std::int32_t>(B), 0});
    s.refs.assign(std::size_t(L * cells * B), -1);
    for (std::size_t c = 0; c < s.buckets.size(); ++c)
      s.buckets[c].first_ref = static_cast<std::uint32_t>(c * B);
  }
  std::vector<std::pair<std::uint32_t, std::uint32_t>> run;  // (block, points in cell)
  for (int t = 0; t < L; ++t) {
    s.table_starts[t] = static_cast<std::uint32_t>(s.keys.size());
    const float* thr[3] = {s.thr(t, 0), s.thr(t, 1), s.thr(t, 2)};
    std::vector<std::uint64_t> pairs = cell_block_pairs(s, thr, P, 1);
    for (std::size_t i = 0; i < pairs.size();) {
      std::uint32_t key = std::uint32_t(pairs[i] >> 32);
      run.clear();
      std::uint32_t np = 0;
      for (; i < pairs.size() && std::uint32_t(pairs[i] >> 32) == key; ++i) {
        std::uint32_t blk = std::uint32_t(pairs[i]);
        ++np;
        if (run.empty() || run.back().first != blk) run.emplace_back(blk, 0);
        ++run.back().second;
      }
      const std::uint32_t D = static_cast<std::uint32_t>(run.size());
      if (t == 0) {
        st.cell_points.push_back(np);
        st.cell_blocks.push_back(D);
      }
      if (top && D > B)
        std::stable_sort(run.begin(), run.end(),
                         [](const auto& a, const auto& b) { return a.second > b.second; });
      const std::uint32_t kept = std::min(D, B), overflows = D > B ? D - B : 0;
      bhcl_bh_bucket bk;
      bk.n_refs = kept;
      bk.q = static_cast<std::int32_t>(B) - static_cast<std::int32_t>(kept) -
             static_cast<std::int32_t>(overflows);
      bk.flags = overflows ? BHCL_BH_FLAG_OVERFLOWED : 0u;
      ++st.occupied_cells;
      st.overflowed += overflows ? 1 : 0;
      st.refs += kept;
      if (direct) {
        std::size_t c = std::size_t(t) * cells + key;
        bk.first_ref = s.buckets[c].first_ref;
        for (std::uint32_t j = 0; j < kept; ++j) s.refs[bk.first_ref + j] = std::int32_t(run[j].first);
        s.buckets[c] = bk;
      } else {
        if (s.refs.size() + kept > 0xffffffffull) throw Error("blockhash: more than 2^32 block references");
        bk.first_ref = static_cast<std::uint32_t>(s.refs.size());
        for (std::uint32_t j = 0; j < kept; ++j) s.refs.push_back(std::int32_t(run[j].first));
        s.keys.push_back(key);
        s.buckets.push_back(bk);
      }
    }
  }
  s.table_starts[L] = static_cast<std::uint32_t>(s.keys.size());
  return st;
}

}  // namespace bhcl::blockhash
