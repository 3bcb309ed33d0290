#include "blockhash_cl/factory.hpp"

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/bruteforce.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/config.hpp"
#if BHCL_HAVE_FLANN
#include "blockhash_cl/flann_index.hpp"
#endif
#include "blockhash_cl/kdtree.hpp"

namespace bhcl {

std::vector<std::string> method_names() {
#if BHCL_HAVE_FLANN
  return {"bruteforce", "kdtree", "flann", "blockhash"};
#else
  return {"bruteforce", "kdtree", "blockhash"};
#endif
}

std::unique_ptr<Index> make_index(const std::string& method, std::shared_ptr<Runtime> runtime,
                                  const float* points, std::size_t n_points,
                                  const MethodOptions& options) {
  if ((!options.load_index.empty() || !options.save_index.empty()) && method != "blockhash")
    throw Error("--save-index / --load-index: only block-hash indexes are saved (method '" + method + "')");
  if (method == "blockhash") {
    // A saved index replaces the build (its build parameters are the saved ones).
    std::unique_ptr<BlockHashIndex> bh;
    if (!options.load_index.empty()) {
      bh = BlockHashIndex::load(std::move(runtime), options.load_index);
      if (bh->size() != n_points)
        throw Error(options.load_index + ": the saved index holds " + std::to_string(bh->size()) +
                    " points, the point set " + std::to_string(n_points));
      if (long i = bh->first_mismatch(points, n_points); i >= 0)
        throw Error(options.load_index + ": the saved index was built from other points (point " +
                    std::to_string(i) + " differs)");
    } else {
      BlockHashBuildParams bp;
      bp.preset = BlockHashBuildParams::parse_preset(options.preset);
      bp.L = options.L;
      bp.P = options.P;
      bp.B = options.B;
      bp.X = options.X;
      bp.seed = options.seed;
      bh = std::make_unique<BlockHashIndex>(std::move(runtime), points, n_points, bp);
    }
    if (!options.save_index.empty()) bh->save(options.save_index);
    return bh;
  }
  if (method == "bruteforce")
    return std::make_unique<BruteForceIndex>(std::move(runtime), points, n_points);
  if (method == "kdtree")
    return std::make_unique<KdTreeIndex>(std::move(runtime), points, n_points);
#if BHCL_HAVE_FLANN
  if (method == "flann") {
    FlannParams fp;
    fp.threads = options.threads;
    return std::make_unique<FlannIndex>(std::move(runtime), points, n_points, fp);
  }
#endif
  std::string known;
  for (const auto& m : method_names()) known += (known.empty() ? "" : ", ") + m;
  throw Error("unknown method '" + method + "' (known: " + known + ")");
}

}  // namespace bhcl
