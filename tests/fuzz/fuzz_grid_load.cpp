// libFuzzer target: parsing a saved grid-layout block-hash index (grid_io.cpp) must accept or
// reject any bytes with bhcl::Error, never crash, read out of bounds or allocate by a field the
// file does not back (issue 38: an id bound of 2^31 - 2 made an 8 GiB table). The checksum test
// is off so that inputs reach the field and structure checks behind it. Whatever is accepted must
// hold what the search relies on: the directory spans the slots without decreasing, each live id
// in [0, id bound) once, and every live point inside its cell's slabs (the search's bound).
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <set>
#include <string>

#include "blockhash/grid_io.hpp"
#include "blockhash_cl/error.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  try {
    bhcl::blockhash::GridIdState st;
    const auto f = bhcl::blockhash::parse_grid(std::string(reinterpret_cast<const char*>(data), size),
                                               "fuzz input", &st, false);
    const bhcl::blockhash::Grid& g = f.grid;
    const std::size_t nc = g.ncells();
    if (g.start(0) != 0 || g.start(nc) != g.n_points) std::abort();
    for (std::size_t c = 0; c < nc; ++c)
      if (g.start(c) > g.start(c + 1)) std::abort();
    std::set<std::int32_t> ids;
    for (std::size_t i = 0; i < g.n_points; ++i) {
      const std::int32_t id = g.ids[i];
      if (id == BHCL_EMPTY_SLOT_ID) continue;
      if (id < 0 || id >= st.id_bound || !ids.insert(id).second) std::abort();
      const float p[3] = {g.x[i], g.y[i], g.z[i]};
      const float o[3] = {g.geom.ox, g.geom.oy, g.geom.oz};
      const std::uint32_t n[3] = {g.geom.nx, g.geom.ny, g.geom.nz};
      for (int d = 0; d < 3; ++d) {
        const std::uint32_t cell = bhcl_grid_cell(p[d], o[d], g.geom.inv_h, n[d]);
        if (bhcl_grid_slabs(p[d], o[d], g.geom.h, g.geom.margin, cell, cell) > 0.0f) std::abort();
      }
    }
    if (ids.size() != st.live) std::abort();
  } catch (const bhcl::Error&) {
  }
  return 0;
}
