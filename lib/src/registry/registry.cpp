// The method registry (blockhash_cl/factory.hpp): the one place that knows every method. Each
// method describes itself in its own folder (lib/src/<method>/options.cpp: its option table,
// capabilities and maker); the list below is all the registry adds.
#include "blockhash_cl/factory.hpp"

#include "blockhash_cl/config.hpp"
#include "blockhash_cl/error.hpp"

namespace bhcl {
namespace bruteforce { MethodInfo describe(); }
namespace kdtree { MethodInfo describe(); }
#if BHCL_HAVE_FLANN
namespace flann { MethodInfo describe(); }
#endif
namespace blockhash { MethodInfo describe(); }

const std::vector<MethodInfo>& methods() {
  static const std::vector<MethodInfo> all = {
      bruteforce::describe(),
      kdtree::describe(),
#if BHCL_HAVE_FLANN
      flann::describe(),
#endif
      blockhash::describe(),
  };
  return all;
}

std::vector<std::string> method_names() {
  std::vector<std::string> names;
  for (const auto& m : methods()) names.push_back(m.name);
  return names;
}

std::vector<std::string> exact_method_names() {
  std::vector<std::string> names;
  for (const auto& m : methods())
    if (m.exact) names.push_back(m.name);
  return names;
}

std::string default_truth_method() {
  for (const auto& m : methods())
    if (m.exact && !m.on_device) return m.name;  // flann: the fastest exact method on a CPU
  return "kdtree";
}

const MethodInfo& method_info(const std::string& name) {
  for (const auto& m : methods())
    if (m.name == name) return m;
  std::string known;
  for (const auto& m : methods()) known += (known.empty() ? "" : ", ") + m.name;
  throw Error("unknown method '" + name + "' (known: " + known + ")");
}

std::unique_ptr<Index> make_index(const std::string& method, std::shared_ptr<Runtime> runtime,
                                  const float* points, std::size_t n_points,
                                  const MethodOptions& options) {
  const MethodInfo& m = method_info(method);
  if ((!options.load_index().empty() || !options.save_index().empty()) && !m.saves)
    throw Error("--save-index / --load-index: method '" + method + "' does not save its index (block hashing does)");
  return m.make(std::move(runtime), points, n_points, options);
}

void prepare_knn(const std::string& method, const Runtime& rt, const MethodOptions& options,
                 const SearchParams& search) {
  const MethodInfo& m = method_info(method);
  if (m.prepare_knn) m.prepare_knn(rt, options, search);
}

}  // namespace bhcl
