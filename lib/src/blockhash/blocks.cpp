// Stage 2 of the block-hash build: the Hilbert-sorted points cut into blocks of X (the bulk load
// of a compacted B+ tree's leaf level), each with its bounding box.
#include <algorithm>
#include <cmath>
#include <cstring>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"

namespace bhcl::blockhash {

void make_blocks(const float* xyz, const std::vector<std::int32_t>& order, int X,
                 std::vector<bhcl_bh_block>& blocks, std::vector<bhcl_bh_box>& boxes) {
  if (X < 1 || X > BHCL_BH_BLOCK_SLOTS)
    throw Error("blockhash: X must be in [1, " + std::to_string(BHCL_BH_BLOCK_SLOTS) + "], got " +
                std::to_string(X));
  const std::size_t n = order.size();
  const std::size_t nb = (n + X - 1) / X;
  blocks.assign(nb, bhcl_bh_block{});
  boxes.assign(nb, bhcl_bh_box{});
  for (std::size_t b = 0; b < nb; ++b)
    fill_block(xyz, order, b * X, std::min(n, b * X + X), blocks[b], boxes[b]);
}

void fill_block(const float* xyz, const std::vector<std::int32_t>& order, std::size_t first,
                std::size_t end, bhcl_bh_block& blk, bhcl_bh_box& box) {
  // Unused slots: id -1 and NaN coordinates, never read by a scalar scan (the box's count bounds
  // it) and never within any bound of a vector scan.
  for (int j = 0; j < BHCL_BH_BLOCK_SLOTS; ++j) {
    blk.x[j] = blk.y[j] = blk.z[j] = NAN;
    blk.id[j] = -1;
  }
  box.lo_x = box.lo_y = box.lo_z = INFINITY;
  box.hi_x = box.hi_y = box.hi_z = -INFINITY;
  box.count = static_cast<std::int32_t>(end - first);
  box.first = static_cast<std::int32_t>(first);
  for (std::size_t i = first; i < end; ++i) {
    const float* p = xyz + 3 * static_cast<std::size_t>(order[i]);
    int j = static_cast<int>(i - first);
    blk.x[j] = p[0];
    blk.y[j] = p[1];
    blk.z[j] = p[2];
    blk.id[j] = order[i];
    box.lo_x = std::min(box.lo_x, p[0]);
    box.lo_y = std::min(box.lo_y, p[1]);
    box.lo_z = std::min(box.lo_z, p[2]);
    box.hi_x = std::max(box.hi_x, p[0]);
    box.hi_y = std::max(box.hi_y, p[1]);
    box.hi_z = std::max(box.hi_z, p[2]);
  }
}

}  // namespace bhcl::blockhash
