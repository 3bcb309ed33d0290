// The update counters of a block-hash index (BlockHashBuildInfo): an update's full builds (the
// grid's rebuilds, every L-table update) reset the build info, and these survive them.
#pragma once

#include <cstddef>

#include "blockhash_cl/blockhash.hpp"

namespace bhcl::blockhash {

struct UpdateCounters {
  std::size_t merges, compactions, update_rebuilds, retunes;
  double t_update;
  explicit UpdateCounters(const BlockHashBuildInfo& in)
      : merges(in.merges), compactions(in.compactions), update_rebuilds(in.update_rebuilds),
        retunes(in.retunes), t_update(in.t_update) {}
  void put(BlockHashBuildInfo& in) const {
    in.merges = merges;
    in.compactions = compactions;
    in.update_rebuilds = update_rebuilds;
    in.retunes = retunes;
    in.t_update = t_update;
  }
};

}  // namespace bhcl::blockhash
