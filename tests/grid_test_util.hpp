// Test helpers that read the grid's internal layout (blockhash/grid.hpp): shared by the grid's
// build tests and the update tests.
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <cstring>

#include "blockhash/grid.hpp"
#include "blockhash_cl/blockhash.hpp"

namespace bhcl::test {

// The grid index's occupancy pyramid against one built afresh from its directory and points
// (build_grid_occupancy): a fresh build gathers it in its placement, an insert sets its new bits
// in place and widens its nodes' point boxes. The bits are equal, and so are the boxes while no
// hole is stored; a hole leaves its nodes' boxes as they were (loose, still holding every live
// point). exact_boxes: equal even with holes (the growth room's corners, whose nodes' boxes the
// rebuild makes again without them).
inline void require_pyramid_as_built(const BlockHashIndex& ix, bool exact_boxes = false) {
  const blockhash::Grid& g = *ix.structure().grid;
  blockhash::Grid copy = g;
  blockhash::build_grid_occupancy(copy, 1);
  REQUIRE(copy.occ.size() == g.occ.size());
  std::uint32_t top_off = 0, total = 0;
  bhcl_grid_occ_top(g.geom, &top_off, &total);
  REQUIRE(std::equal(g.occ.begin(), g.occ.begin() + total, copy.occ.begin()));
  const bool holes = ix.info().holes > 0 && !exact_boxes;
  for (std::size_t at = bhcl_grid_tbox_off(total); at + sizeof(bhcl_grid_dbox) <= g.occ.size(); at += sizeof(bhcl_grid_dbox)) {
    bhcl_grid_dbox b, fresh;
    std::memcpy(&b, g.occ.data() + at, sizeof(b));
    std::memcpy(&fresh, copy.occ.data() + at, sizeof(fresh));
    CAPTURE(at);
    if (!holes)  // by value: a fresh build's gathered boxes may keep -0 where this pass keeps +0
      REQUIRE((b.lx == fresh.lx && b.ly == fresh.ly && b.lz == fresh.lz && b.hx == fresh.hx && b.hy == fresh.hy &&
               b.hz == fresh.hz));
    if (fresh.lx <= fresh.hx)  // a node with live points: its box holds theirs
      REQUIRE((b.lx <= fresh.lx && b.ly <= fresh.ly && b.lz <= fresh.lz && b.hx >= fresh.hx && b.hy >= fresh.hy &&
               b.hz >= fresh.hz));
  }
}

}  // namespace bhcl::test
