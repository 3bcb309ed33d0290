// The method registry: one description per method (its name, whether it is exact, where it
// answers, whether it saves, its build options with help text and ranges, and how to make it).
// It drives make_index, the bhcl tool's options and help, eval's exact-truth check, the tests that
// run over every (exact) method, the stress suite and the benchmark loops: adding a method is one
// entry in lib/src/core/factory.cpp.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

// Build options of every method; each method reads the fields its registry entry lists.
// -1 / empty means "the method's default".
struct MethodOptions {
  std::string preset;       // blockhash: "auto" (default) or "paper"
  int L = -1, P = -1, B = -1, X = -1;
  int leaf_size = -1;       // kdtree: most points per leaf (-1: KdTreeParams' default)
  int threads = 0;          // host methods (flann): 0 = all hardware threads
  std::string load_index;   // load a saved index instead of building
  std::string save_index;   // save the built index
  std::uint64_t seed = 1;
};

// One build option as the command line and the help show it.
struct OptionInfo {
  enum class Kind { Integer, Choice, File };
  std::string name;  // without "--", e.g. "L"
  std::string help;  // its meaning, without the method name or the range (the tool adds them)
  std::string def;   // the default as shown ("-1" where -1 means "derive")
  Kind kind = Kind::Integer;
  long long lo = 0, hi = 0;          // Integer: the accepted range (values outside are refused)
  std::vector<std::string> choices;  // Choice: the accepted values
  // Stores a value already checked against the range or choices into `o`.
  void (*set)(MethodOptions& o, const std::string& text, long long value) = nullptr;
};

struct MethodInfo {
  std::string name;     // "bruteforce", "kdtree", "flann", "blockhash"
  std::string summary;  // one line for --help
  bool exact = false;   // returns the true k nearest under the contract
  bool on_device = true;  // answers with an OpenCL kernel (false: on the host, e.g. FLANN)
  bool saves = false;     // --save-index / --load-index
  std::vector<OptionInfo> build_options;
  // The method-specific search options it reads, by command-line name ("A", "recall", "probes",
  // "local-size", "max-batch"); k and max-radius apply to every method.
  std::vector<std::string> search_options;
  // Builds (or loads) the index; throws bhcl::Error for bad points or options.
  std::unique_ptr<Index> (*make)(std::shared_ptr<Runtime> runtime, const float* points,
                                 std::size_t n_points, const MethodOptions& options) = nullptr;
};

// Every method compiled into this library, in display order (FLANN only when built with it).
const std::vector<MethodInfo>& methods();
// The entry of `name`; throws bhcl::Error for an unknown method, listing the known ones.
const MethodInfo& method_info(const std::string& name);
// Names of methods(), and of the exact ones, in display order.
std::vector<std::string> method_names();
std::vector<std::string> exact_method_names();
// The exact method that gives the true neighbours by default (eval, benchmarks): the fastest one
// built in (flann when present, else kdtree).
std::string default_truth_method();

// Builds an index of any method by name (method_info(method).make). Throws bhcl::Error for an
// unknown method, bad points, or --save-index/--load-index on a method that does not save.
std::unique_ptr<Index> make_index(const std::string& method, std::shared_ptr<Runtime> runtime,
                                  const float* points, std::size_t n_points,
                                  const MethodOptions& options = {});

}  // namespace bhcl
