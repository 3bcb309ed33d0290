// The method registry (blockhash_cl/factory.hpp): one entry per method.
#include "blockhash_cl/factory.hpp"

#include <algorithm>
#include <limits>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/bruteforce.hpp"
#include "blockhash_cl/config.hpp"
#include "blockhash_cl/error.hpp"
#if BHCL_HAVE_FLANN
#include "blockhash_cl/flann_index.hpp"
#endif
#include "blockhash_cl/kdtree.hpp"

namespace bhcl {
namespace {

using Kind = OptionInfo::Kind;

OptionInfo integer(std::string name, std::string help, std::string def, long long lo, long long hi,
                   void (*set)(MethodOptions&, const std::string&, long long)) {
  OptionInfo o;
  o.name = std::move(name);
  o.help = std::move(help);
  o.def = std::move(def);
  o.kind = Kind::Integer;
  o.lo = lo;
  o.hi = hi;
  o.set = set;
  return o;
}

OptionInfo text(std::string name, std::string help, Kind kind, std::vector<std::string> choices,
                std::string def, void (*set)(MethodOptions&, const std::string&, long long)) {
  OptionInfo o;
  o.name = std::move(name);
  o.help = std::move(help);
  o.def = std::move(def);
  o.kind = kind;
  o.choices = std::move(choices);
  o.set = set;
  return o;
}

const std::vector<std::string> kDeviceSearch = {"local-size", "max-batch"};

std::unique_ptr<Index> make_blockhash(std::shared_ptr<Runtime> runtime, const float* points,
                                      std::size_t n_points, const MethodOptions& options) {
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

MethodInfo blockhash_entry() {
  MethodInfo m;
  m.name = "blockhash";
  m.summary = "block hashing (Ma & McCool 2002): approximate, examines at most A*k points per query";
  m.exact = false;
  m.on_device = true;
  m.saves = true;
  m.build_options = {
      text("preset", "parameter preset", Kind::Choice, {"auto", "paper"}, "auto",
           [](MethodOptions& o, const std::string& v, long long) { o.preset = v; }),
      integer("L", "hash tables (-1: the preset decides)", "-1", -1, 1 << 16,
              [](MethodOptions& o, const std::string&, long long v) { o.L = int(v); }),
      integer("P", "thresholds per dimension (-1: the preset decides)", "-1", -1, 1024,
              [](MethodOptions& o, const std::string&, long long v) { o.P = int(v); }),
      integer("B", "block references per bucket (-1: the preset decides)", "-1", -1, 1 << 16,
              [](MethodOptions& o, const std::string&, long long v) { o.B = int(v); }),
      integer("X", "points per block (-1: the preset decides)", "-1", -1, 16,
              [](MethodOptions& o, const std::string&, long long v) { o.X = int(v); }),
      integer("seed", "seed of the threshold jitter", "1", 0, std::numeric_limits<long long>::max(),
              [](MethodOptions& o, const std::string&, long long v) { o.seed = std::uint64_t(v); }),
      text("load-index", "load this saved index instead of building", Kind::File, {}, "",
           [](MethodOptions& o, const std::string& v, long long) { o.load_index = v; }),
      text("save-index", "save the built index to this file", Kind::File, {}, "",
           [](MethodOptions& o, const std::string& v, long long) { o.save_index = v; }),
  };
  m.search_options = {"A", "recall", "probes", "local-size", "max-batch"};
  m.make = make_blockhash;
  return m;
}

MethodInfo bruteforce_entry() {
  MethodInfo m;
  m.name = "bruteforce";
  m.summary = "exact: every point against every query (a tiled kernel)";
  m.exact = true;
  m.search_options = kDeviceSearch;
  m.make = [](std::shared_ptr<Runtime> rt, const float* p, std::size_t n,
              const MethodOptions&) -> std::unique_ptr<Index> {
    return std::make_unique<BruteForceIndex>(std::move(rt), p, n);
  };
  return m;
}

MethodInfo kdtree_entry() {
  MethodInfo m;
  m.name = "kdtree";
  m.summary = "exact: a balanced kd-tree built on the host, searched by a stackful kernel";
  m.exact = true;
  m.build_options = {
      integer("leaf-size", "most points per leaf (-1: 16)", "-1", -1, 1024,
              [](MethodOptions& o, const std::string&, long long v) { o.leaf_size = int(v); }),
  };
  m.search_options = kDeviceSearch;
  m.make = [](std::shared_ptr<Runtime> rt, const float* p, std::size_t n,
              const MethodOptions& o) -> std::unique_ptr<Index> {
    KdTreeParams kp;
    if (o.leaf_size >= 0) kp.leaf_size = o.leaf_size;
    return std::make_unique<KdTreeIndex>(std::move(rt), p, n, kp);
  };
  return m;
}

#if BHCL_HAVE_FLANN
MethodInfo flann_entry() {
  MethodInfo m;
  m.name = "flann";
  m.summary = "exact: FLANN's single kd-tree searched exactly on host threads";
  m.exact = true;
  m.on_device = false;
  m.build_options = {
      integer("threads", "host threads (0: all hardware threads)", "0", 0, 1 << 16,
              [](MethodOptions& o, const std::string&, long long v) { o.threads = int(v); }),
  };
  m.make = [](std::shared_ptr<Runtime> rt, const float* p, std::size_t n,
              const MethodOptions& o) -> std::unique_ptr<Index> {
    FlannParams fp;
    fp.threads = o.threads;
    return std::make_unique<FlannIndex>(std::move(rt), p, n, fp);
  };
  return m;
}
#endif

}  // namespace

const std::vector<MethodInfo>& methods() {
  static const std::vector<MethodInfo> all = {
      bruteforce_entry(), kdtree_entry(),
#if BHCL_HAVE_FLANN
      flann_entry(),
#endif
      blockhash_entry()};
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
  if ((!options.load_index.empty() || !options.save_index.empty()) && !m.saves)
    throw Error("--save-index / --load-index: only block-hash indexes are saved (method '" + method + "')");
  return m.make(std::move(runtime), points, n_points, options);
}

}  // namespace bhcl
