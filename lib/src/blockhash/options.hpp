// Block hashing's one table of options (options.cpp): the build fields of BlockHashBuildParams,
// the search fields of SearchParams and RadiusParams it reads, with their ranges.
#pragma once

#include <vector>

#include "blockhash_cl/options.hpp"

namespace bhcl::blockhash {

const std::vector<OptionInfo>& option_table();

}  // namespace bhcl::blockhash
