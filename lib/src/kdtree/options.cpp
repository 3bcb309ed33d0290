// The kd-tree method described once: its options, capabilities and maker (the registry lists it).
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/kdtree.hpp"

namespace bhcl::kdtree {
namespace {

const std::vector<OptionInfo>& table() {
  static const std::vector<OptionInfo> table = [] {
    OptionInfo leaf = option::integer("leaf-size", "most points per leaf (-1: 16)", 1, 1024, "-1").or_unset();
    leaf.field = "KdTreeParams::leaf_size";
    leaf.get = &option::get<&KdTreeParams::leaf_size>;
    leaf.set = [](void* p, const OptionValue& v) {
      if (v.integer >= 0) static_cast<KdTreeParams*>(p)->leaf_size = static_cast<int>(v.integer);
    };
    std::vector<OptionInfo> t = {leaf};
    for (OptionInfo& o : device_search_options()) t.push_back(o);
    return t;
  }();
  return table;
}

std::unique_ptr<Index> make(std::shared_ptr<Runtime> rt, const float* p, std::size_t n, const MethodOptions& o) {
  return make_from_table<KdTreeIndex, KdTreeParams>(table(), "kdtree", std::move(rt), p, n, o);
}

}  // namespace

// name, summary, exact, on a device, saves, options, maker.
MethodInfo describe() {
  return {"kdtree", "exact: a balanced kd-tree built on the host, searched by a stackful kernel", true, true,
          false, table(), make};
}

}  // namespace bhcl::kdtree

namespace bhcl {

// After updates (Index::insert/remove): the holes removed points left in the leaves, the inserts
// merged into the leaves, the rebuilds (a leaf past 4x the leaf size, the set grown by half, holes
// past a quarter), the ids issued and removed. An index never updated reports nothing more.
UsedFields KdTreeIndex::build_used() const {
  if (!holes() && !update_merges() && !update_rebuilds()) return {};
  return {{"holes", std::to_string(holes())},
          {"update_merges", std::to_string(update_merges())},
          {"update_rebuilds", std::to_string(update_rebuilds())},
          {"id_bound", std::to_string(id_bound())},
          {"removed", std::to_string(removed_count())}};
}

}  // namespace bhcl
