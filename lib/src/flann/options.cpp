// The FLANN method described once: its options, capabilities and maker (the registry lists it).
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/flann_index.hpp"

namespace bhcl::flann {
namespace {

const std::vector<OptionInfo>& table() {
  static const std::vector<OptionInfo> t = {
      BHCL_BUILD_OPTION(FlannParams, threads,
                        option::integer("threads", "host threads (0: the CPUs this process may use, its affinity mask)", 0, 1 << 16, "0"))};
  return t;
}

std::unique_ptr<Index> make(std::shared_ptr<Runtime> rt, const float* p, std::size_t n, const MethodOptions& o) {
  return make_from_table<FlannIndex, FlannParams>(table(), "flann", std::move(rt), p, n, o);
}

}  // namespace

// name, summary, exact, on a device, saves, options, maker.
MethodInfo describe() {
  return {"flann", "exact: FLANN's single kd-tree searched exactly on host threads", true, false, false, table(), make};
}

}  // namespace bhcl::flann

namespace bhcl {

UsedFields FlannIndex::build_used() const { return {{"threads", std::to_string(threads())}}; }

}  // namespace bhcl
