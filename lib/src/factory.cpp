#include "blockhash_cl/factory.hpp"

#include "blockhash_cl/bruteforce.hpp"
#include "blockhash_cl/error.hpp"

namespace bhcl {

std::vector<std::string> method_names() { return {"bruteforce"}; }

std::unique_ptr<Index> make_index(const std::string& method, std::shared_ptr<Runtime> runtime,
                                  const float* points, std::size_t n_points,
                                  const MethodOptions& options) {
  (void)options;
  if (method == "bruteforce")
    return std::make_unique<BruteForceIndex>(std::move(runtime), points, n_points);
  std::string known;
  for (const auto& m : method_names()) known += (known.empty() ? "" : ", ") + m;
  throw Error("unknown method '" + method + "' (known: " + known + ")");
}

}  // namespace bhcl
