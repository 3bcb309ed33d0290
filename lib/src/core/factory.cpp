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

// Setters for OptionInfo::set.
template <int MethodOptions::*F>
void set_int(MethodOptions& o, const std::string&, long long v) { o.*F = static_cast<int>(v); }
template <std::string MethodOptions::*F>
void set_text(MethodOptions& o, const std::string& v, long long) { o.*F = v; }
void set_seed(MethodOptions& o, const std::string&, long long v) { o.seed = static_cast<std::uint64_t>(v); }

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

MethodInfo entry(std::string name, std::string summary, bool exact, bool on_device, bool saves,
                 std::vector<std::string> search_options, decltype(MethodInfo::make) make,
                 std::vector<OptionInfo> build_options = {}) {
  MethodInfo m;
  m.name = std::move(name);
  m.summary = std::move(summary);
  m.exact = exact;
  m.on_device = on_device;
  m.saves = saves;
  m.search_options = std::move(search_options);
  m.make = make;
  m.build_options = std::move(build_options);
  return m;
}

std::unique_ptr<Index> make_bruteforce(std::shared_ptr<Runtime> rt, const float* p, std::size_t n,
                                       const MethodOptions&) {
  return std::make_unique<BruteForceIndex>(std::move(rt), p, n);
}

std::unique_ptr<Index> make_kdtree(std::shared_ptr<Runtime> rt, const float* p, std::size_t n,
                                   const MethodOptions& o) {
  KdTreeParams kp;
  if (o.leaf_size >= 0) kp.leaf_size = o.leaf_size;
  return std::make_unique<KdTreeIndex>(std::move(rt), p, n, kp);
}

#if BHCL_HAVE_FLANN
std::unique_ptr<Index> make_flann(std::shared_ptr<Runtime> rt, const float* p, std::size_t n,
                                  const MethodOptions& o) {
  FlannParams fp;
  fp.threads = o.threads;
  return std::make_unique<FlannIndex>(std::move(rt), p, n, fp);
}
#endif

}  // namespace

const std::vector<MethodInfo>& methods() {
  // name, summary, exact, on a device, saves, search options, make, build options.
  static const std::vector<MethodInfo> all = {
      entry("bruteforce", "exact: every point against every query (a tiled kernel)", true, true,
            false, kDeviceSearch, make_bruteforce),
      entry("kdtree", "exact: a balanced kd-tree built on the host, searched by a stackful kernel",
            true, true, false, kDeviceSearch, make_kdtree,
            {integer("leaf-size", "most points per leaf (-1: 16)", "-1", -1, 1024,
                     set_int<&MethodOptions::leaf_size>)}),
#if BHCL_HAVE_FLANN
      entry("flann", "exact: FLANN's single kd-tree searched exactly on host threads", true, false,
            false, {}, make_flann,
            {integer("threads", "host threads (0: all hardware threads)", "0", 0, 1 << 16,
                     set_int<&MethodOptions::threads>)}),
#endif
      entry("blockhash", "block hashing (Ma & McCool 2002): approximate, examines at most A*k points per query",
            false, true, true, {"A", "recall", "probes", "local-size", "max-batch"}, make_blockhash,
            {text("preset", "parameter preset", Kind::Choice, {"auto", "paper"}, "auto", set_text<&MethodOptions::preset>),
             integer("L", "hash tables (-1: the preset decides)", "-1", -1, 1 << 16, set_int<&MethodOptions::L>),
             integer("P", "thresholds per dimension (-1: the preset decides)", "-1", -1, 1024, set_int<&MethodOptions::P>),
             integer("B", "block references per bucket (-1: the preset decides)", "-1", -1, 1 << 16, set_int<&MethodOptions::B>),
             integer("X", "points per block (-1: the preset decides)", "-1", -1, 16, set_int<&MethodOptions::X>),
             integer("seed", "seed of the threshold jitter", "1", 0, std::numeric_limits<long long>::max(), set_seed),
             text("load-index", "load this saved index instead of building", Kind::File, {}, "", set_text<&MethodOptions::load_index>),
             text("save-index", "save the built index to this file", Kind::File, {}, "", set_text<&MethodOptions::save_index>)}),
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
  if ((!options.load_index.empty() || !options.save_index.empty()) && !m.saves)
    throw Error("--save-index / --load-index: only block-hash indexes are saved (method '" + method + "')");
  return m.make(std::move(runtime), points, n_points, options);
}

}  // namespace bhcl
