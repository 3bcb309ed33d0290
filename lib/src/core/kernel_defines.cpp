// The kernels' defines, one row each (kernel_defines.hpp). A row's kernels are the .cl files whose
// source, includes expanded, reads the define; tests/kernel_defines_tests.cpp checks the rows
// against the sources.
#include "core/kernel_defines.hpp"

#include <algorithm>
#include <cerrno>
#include <cstdlib>
#include <sstream>

#include "blockhash_cl/error.hpp"

namespace bhcl::detail {
namespace {

using K = KernelDefine;
constexpr long long kU32 = 0xffffffffLL;

const char* const kKnn[] = {"blockhash_grid_knn.cl", "blockhash_knn.cl", "bruteforce_knn.cl", "kdtree_knn.cl"};
const char* const kRadius[] = {"blockhash_grid_radius.cl", "blockhash_radius.cl", "bruteforce_radius.cl",
                               "kdtree_radius.cl"};

// The files, each with the same default.
std::vector<K::Reader> with(std::initializer_list<const char*> files, const char* fallback) {
  std::vector<K::Reader> r;
  for (const char* f : files) r.push_back({f, fallback});
  return r;
}

std::vector<KernelDefine> make_table() {
  std::vector<K::Reader> every;  // knn_common.h, which radius_common.h includes too
  for (const char* f : kKnn) every.push_back({f, "32"});
  for (const char* f : kRadius) every.push_back({f, "32"});
  const auto grid = [](const char* fallback) { return with({"blockhash_grid_knn.cl"}, fallback); };
  const auto grid_both = [](const char* fallback) {
    return with({"blockhash_grid_knn.cl", "blockhash_grid_radius.cl"}, fallback);
  };
  const auto blocks = [](const char* fallback) {
    return with({"blockhash_knn.cl", "blockhash_radius.cl"}, fallback);
  };
  return {
      {"BHCL_KMAX", K::Structural, 1, 256, "the longest list a kNN kernel variant keeps (k <= it)", every},
      // The grid (blockhash_grid_*.cl, grid_search.h).
      {"BHCL_GRID_VTOPK", K::Tuning, 0, 1, "1: the top-k list in vector registers (k <= 64; CPU devices)", grid("0")},
      {"BHCL_GRID_PREFETCH", K::Tuning, 0, 2, "prefetch the home cell's rows d work-items ahead (2: clang's builtin)",
       grid("0")},
      {"BHCL_GRID_PREFETCH_DIR", K::Tuning, 0, 1, "1: also the directory entry, 2d ahead", grid("1")},
      {"BHCL_GRID_PREFETCH_RING", K::Tuning, 0, 1, "1: the 9 rows around the home cell, not only its own", grid("1")},
      {"BHCL_GRID_PREFETCH_IDS", K::Tuning, 0, 1, "1: the ids' first lines with the points'", grid("1")},
      {"BHCL_GRID_PREFETCH_LINES", K::Tuning, 0, 16, "64-byte lines of each row's first points asked for", grid("2")},
      {"BHCL_GRID_ROWCAP", K::Tuning, 0, 256, "runs of a ring gathered and scanned nearest first (0: as met)", grid("0")},
      {"BHCL_GRID_WALKCAP", K::Tuning, 0, 64, "far walk's best-first queue of pyramid nodes (0: depth-first)",
       grid("0")},
      {"BHCL_GRID_WALKBUF", K::Structural, 1, 64, "the far walk's queue (the kNN kernel's from BHCL_GRID_WALKCAP)",
       grid_both("32")},
      {"BHCL_GRID_WALK_DESCEND", K::Experiment, 0, 1,
       "1: the best-first walk descends into a node's nearest child, the others queued (0: all queued; the host reference follows 1)", grid_both("1")},
      {"BHCL_GRID_WALK_DF_LEVEL", K::Experiment, 1, 16,
       "pyramid nodes of this level or below are walked depth-first when the best-first walk pops them (the host reference follows 2)",
       grid_both("2u")},
      {"BHCL_GRID_HOME_SKIP", K::Experiment, 0, 2,
       "an empty home 4^3 block walks at once: 2 after ring 0 (the home cell empty), 1 before the rings, 0 never (the host reference follows 2)",
       grid_both("2")},
      {"BHCL_GRID_TBOX", K::Experiment, 0, 1,
       "1: the far walk clips a node's slabs to the points' box of it or of its level-2 ancestor (0: to the points' box of the grid; the host reference follows 1)",
       grid_both("1")},
      {"BHCL_GRID_BLOCK_ROWS", K::Experiment, 0, 1,
       "1: the best-first walk scans a level-2 node (4^3 cells) by its rows (0: child by child; the host reference follows 1)",
       grid_both("1")},
      {"BHCL_GRID_SHORT_RUN", K::Tuning, 0, 1024,
       "the far walk's runs of this many points or fewer scanned one point at a time by the register list (0: all 16 lanes at a time)",
       grid("4u")},
      {"BHCL_GRID_FILLSORT", K::Tuning, 0, 1, "1: the register list filled unordered, then sorted once", grid("(VR > 1)")},
      {"BHCL_GRID_SORT_CALL", K::Tuning, 0, 1, "1: the fill's sorting network in one function", grid("1")},
      {"BHCL_GRID_NEAR", K::Tuning, 0, 16,
       "the rings' slab distances within this many cells of the query's cell made once per query (0: per row)",
       {{"blockhash_grid_knn.cl", "(BHCL_GRID_ROWCAP > 0 ? 3 : 0)"}, {"blockhash_grid_radius.cl", "0"}}},
      {"BHCL_GRID_REDUCE", K::Tuning, 0, 1,
       "1: a lane test of the register list's scan by clang's vector reduction where it has one (0: OpenCL's any())",
       grid("1")},
      {"BHCL_GRID_FINE_RINGS", K::Tuning, 0, kU32,
       "rings searched before the occupancy pyramid's walk (0xffffffff: the rings alone)", grid_both("2u")},
      {"BHCL_GRID_RING_SLACK", K::Tuning, 0, 1024, "past them, rings go on while the stop is this many rings away",
       grid_both("2u")},
      {"BHCL_GRID_RING_CAP", K::Tuning, 0, 1024, "for at most this many more rings", grid_both("6u")},
      {"BHCL_GRID_ROWBUF", K::Structural, 1, 256, "the gathered runs' buffer (the kNN kernel's from BHCL_GRID_ROWCAP)",
       grid_both("32")},
      // The L tables (blockhash_common.h and its two kernels).
      {"BHCL_BH_L", K::Structural, 1, 64, "hash tables (the build's L)", blocks("4")},
      {"BHCL_BH_DIRECT", K::Structural, 0, 1, "1: direct addressing of every cell (the build's)", blocks("0")},
      {"BHCL_BH_MAXKEEP", K::Structural, 1, 4096, "blocks a query keeps (from k and X)",
       with({"blockhash_knn.cl"}, "128")},
      {"BHCL_BH_BOXSKIP", K::Structural, 0, 1, "the build's bounding-box skip", with({"blockhash_knn.cl"}, "1")},
      {"BHCL_BH_BOXORDER", K::Structural, 0, 1, "the build's box-ordered scan", with({"blockhash_knn.cl"}, "0")},
      {"BHCL_BH_SCANCAP", K::Structural, 1, 4096, "blocks a query scans (from k and X)",
       with({"blockhash_knn.cl", "blockhash_radius.cl"}, "128")},
      // The kd-tree.
      {"BHCL_KD_STACK", K::Structural, 1, 256, "the traversal stack (from the tree's depth)",
       with({"kdtree_knn.cl", "kdtree_radius.cl"}, "32")},
  };
}

const char* kind_name(KernelDefine::Kind k) {
  return k == K::Structural ? "structural" : k == K::Tuning ? "tuning" : "experiment";
}

std::string readers_of(const KernelDefine& d) {
  std::string s;
  for (const K::Reader& r : d.readers) s += (s.empty() ? "" : ", ") + std::string(r.kernel);
  return s;
}

// The settable defines, for the message of an unknown name.
std::string settable_names() {
  std::string s;
  for (const KernelDefine& d : kernel_define_table())
    if (d.kind != K::Structural) s += (s.empty() ? "" : ", ") + std::string(d.name);
  return s;
}

long long parse_value(const KernelDefine& d, const std::string& text) {
  errno = 0;
  char* end = nullptr;
  const long long v = std::strtoll(text.c_str(), &end, 0);  // decimal, 0x hex or 0 octal, as C
  if (text.empty() || errno || *end != '\0' || v < d.lo || v > d.hi)
    throw Error("kernel_defines: " + std::string(d.name) + "=" + text + " is not an integer in [" +
                std::to_string(d.lo) + ", " + std::to_string(d.hi) + "] (" + d.help + ")");
  return v;
}

}  // namespace

bool KernelDefine::read_by(const std::string& kernel) const {
  return std::any_of(readers.begin(), readers.end(), [&](const Reader& r) { return kernel == r.kernel; });
}

const std::vector<KernelDefine>& kernel_define_table() {
  static const std::vector<KernelDefine> table = make_table();
  return table;
}

const KernelDefine* find_kernel_define(const std::string& name) {
  for (const KernelDefine& d : kernel_define_table())
    if (name == d.name) return &d;
  return nullptr;
}

std::vector<CallerDefine> parse_kernel_defines(const std::string& defines) {
  std::vector<CallerDefine> out;
  std::istringstream is(defines);
  std::string tok;
  while (is >> tok) {
    if (tok.size() <= 2 || tok.compare(0, 2, "-D") != 0)
      throw Error("kernel_defines: '" + tok + "' is not a -DNAME[=VALUE] define");
    const std::size_t eq = tok.find('=');
    const std::string name = tok.substr(2, eq == std::string::npos ? std::string::npos : eq - 2);
    const std::string value = eq == std::string::npos ? "1" : tok.substr(eq + 1);
    const KernelDefine* d = find_kernel_define(name);
    if (!d)
      throw Error("kernel_defines: no kernel reads " + name + " (a caller may set: " + settable_names() + ")");
    if (d->kind == K::Structural)
      throw Error("kernel_defines: " + name + " is set by the library from the index (" + d->help +
                  "); a caller cannot set it");
    out.push_back({d, value, parse_value(*d, value)});
  }
  return out;
}

std::string kernel_build_options(const std::string& file, const DefineValues& library,
                                 const std::string& caller_defines) {
  std::string options;
  const std::vector<CallerDefine> caller = parse_kernel_defines(caller_defines);
  for (const auto& [name, value] : library) {
    const KernelDefine* d = find_kernel_define(name);
    if (!d || !d->read_by(file))
      throw Error("internal error: the library sets " + std::string(name) + ", which " + file +
                  " does not read (kernel_defines.cpp's table)");
    // A define the caller sets too is the caller's alone: two -D of one name build as the last,
    // but clang warns of the redefinition ("N warnings generated" on PoCL's stderr).
    const std::string n = name;  // (a structured binding: not capturable in C++17)
    if (std::any_of(caller.begin(), caller.end(), [&](const CallerDefine& c) { return c.define->name == n; }))
      continue;
    options += (options.empty() ? "-D" : " -D") + std::string(name) + "=" + std::to_string(value);
  }
  for (const CallerDefine& c : caller) {
    const KernelDefine& d = *c.define;
    if (!d.read_by(file))
      throw Error("kernel_defines: " + std::string(d.name) + " (" + kind_name(d.kind) + ") is not read by " + file +
                  ", the kernel this query builds (it is read by " + readers_of(d) + ")");
    options += (options.empty() ? "-D" : " -D") + std::string(d.name) + "=" + c.text;
  }
  return options;
}

std::uint32_t caller_define_value(const std::string& caller_defines, const std::string& name,
                                  std::uint32_t fallback) {
  std::uint32_t v = fallback;
  for (const CallerDefine& c : parse_kernel_defines(caller_defines))
    if (name == c.define->name) v = static_cast<std::uint32_t>(c.value);
  return v;
}

}  // namespace bhcl::detail
