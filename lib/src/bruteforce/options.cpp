// The brute-force method described once: its options, capabilities and maker (the registry lists it).
#include "blockhash_cl/bruteforce.hpp"
#include "blockhash_cl/factory.hpp"

namespace bhcl::bruteforce {
namespace {

std::unique_ptr<Index> make(std::shared_ptr<Runtime> rt, const float* p, std::size_t n, const MethodOptions&) {
  return std::make_unique<BruteForceIndex>(std::move(rt), p, n);
}

}  // namespace

// name, summary, exact, on a device, saves, options, maker.
MethodInfo describe() {
  return {"bruteforce", "exact: every point against every query (a tiled kernel)", true, true, false,
          device_search_options(), make};
}

}  // namespace bhcl::bruteforce
