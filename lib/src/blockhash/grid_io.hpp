// Save / load of a grid index with the state its updates leave (Index::insert/remove, issue 23):
// the id bound, the holes of removed points and the update counters (grid file version 3).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "blockhash/grid.hpp"

namespace bhcl::blockhash {

struct GridIdState {
  // One past the largest id issued; the file's ids are the live ids (sparse in [0, id_bound)) and
  // holes (BHCL_EMPTY_SLOT_ID at +inf). Files before version 3: n_points (ids 0 .. N - 1).
  std::int64_t id_bound = -1;  // save: -1 means n_points
  // Derived on load: live ids and hole slots among the grid's n_points.
  std::size_t live = 0, holes = 0;
  // The mean cell population of the last tuned build (the update's retune band; 0: the current).
  double tuned_mean = 0;
  std::uint64_t merges = 0, compactions = 0, update_rebuilds = 0, retunes = 0;
};

void save_grid(const GridFile& f, const GridIdState& ids, const std::string& path);
GridFile load_grid(const std::string& path, GridIdState* ids);
// verify_checksum false: for the fuzz target (tests/fuzz/fuzz_grid_load.cpp), whose inputs then
// reach the field and structure checks behind the checksum.
GridFile parse_grid(const std::string& data, const std::string& what, GridIdState* ids,
                    bool verify_checksum = true);

}  // namespace bhcl::blockhash
