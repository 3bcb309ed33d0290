// The method registry: one description per method (its name, whether it is exact, where it
// answers, whether it saves, its build options with help text and ranges, and how to make it).
// It drives make_index, the bhcl tool's options and help, eval's exact-truth check, the tests that
// run over every (exact) method, the stress suite and the benchmark loops. Each method describes
// itself in its own folder (lib/src/<method>/options.cpp: method_info()); the registry
// (lib/src/registry/registry.cpp) lists them and is the one place that includes every method.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "blockhash_cl/knn.hpp"
#include "blockhash_cl/options.hpp"

namespace bhcl {

struct MethodInfo {
  std::string name;     // "bruteforce", "kdtree", "flann", "blockhash"
  std::string summary;  // one line for --help
  bool exact = false;   // returns the true k nearest under the contract
  bool on_device = true;  // answers with an OpenCL kernel (false: on the host, e.g. FLANN)
  bool saves = false;     // --save-index / --load-index
  // Its one table of build, search and radius options (lib/src/<method>/options.cpp); k and
  // max-radius apply to every method and are no entry.
  std::vector<OptionInfo> options;
  std::vector<const OptionInfo*> build_options() const { return options_in(options, OptionInfo::Build); }
  std::vector<const OptionInfo*> search_options() const { return options_in(options, OptionInfo::Search); }
  std::vector<const OptionInfo*> radius_options() const { return options_in(options, OptionInfo::Radius); }
  // Builds (or loads) the index; throws bhcl::Error for bad points or options.
  std::unique_ptr<Index> (*make)(std::shared_ptr<Runtime> runtime, const float* points,
                                 std::size_t n_points, const MethodOptions& options) = nullptr;
  // Builds the programs a kNN query with these options will use where they do not depend on the
  // points (prepare_knn below); null: none known before the index.
  void (*prepare_knn)(const Runtime& rt, const MethodOptions& options, const SearchParams& search) = nullptr;
  // What a built index used and what a query resolves to: SearchIndex::build_used and
  // search_used, overridden by the method's class (MethodInfo only describes, it holds no hooks).
  using Used = UsedFields;
};

// The maker of a method whose index is built from (runtime, points, n, Params): the options its
// table holds written into a default Params (apply_build_options), then the index built.
template <class IndexT, class Params>
std::unique_ptr<Index> make_from_table(const std::vector<OptionInfo>& table, const char* method,
                                       std::shared_ptr<Runtime> runtime, const float* points,
                                       std::size_t n_points, const MethodOptions& options) {
  Params p;
  apply_build_options(table, options, &p, method);
  return std::make_unique<IndexT>(std::move(runtime), points, n_points, p);
}

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
// unknown method, bad points, an option the method's table does not hold or refuses, or
// --save-index/--load-index on a method that does not save.
std::unique_ptr<Index> make_index(const std::string& method, std::shared_ptr<Runtime> runtime,
                                  const float* points, std::size_t n_points,
                                  const MethodOptions& options = {});

// Builds on rt, before any index, the programs a kNN query with `search` on make_index(method,
// rt, ..., options) will use, where the method can tell them without the points (block hashing's
// grid: its program depends on the device and k); else does nothing. From the library's program
// cache this is a load of 10-30 ms, most of it PoCL reading the program's bitcode, which the first
// query otherwise pays: a tool runs it on a thread of its own while it reads its input (bhcl knn).
// Thread-safe beside a build on the same runtime. Throws what make_index would for bad options.
void prepare_knn(const std::string& method, const Runtime& rt, const MethodOptions& options,
                 const SearchParams& search);

}  // namespace bhcl
