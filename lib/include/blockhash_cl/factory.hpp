// Builds an index of any method by name, for the bhcl tool, the benchmark and the renderer.
#pragma once

#include <cstddef>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

// Build options of every method; each method reads the fields it knows and ignores the rest.
// -1 / empty means "the method's default".
struct MethodOptions {
  std::string preset;       // blockhash: "auto" (default) or "paper"
  int L = -1, P = -1, B = -1, X = -1;
  int threads = 0;          // host methods (flann): 0 = all hardware threads
  std::string load_index;   // load a saved index instead of building
  std::string save_index;   // save the built index
  std::uint64_t seed = 1;
};

// Names accepted by make_index, in display order.
std::vector<std::string> method_names();

// Throws bhcl::Error for an unknown method (listing the known ones) or bad points.
std::unique_ptr<Index> make_index(const std::string& method, std::shared_ptr<Runtime> runtime,
                                  const float* points, std::size_t n_points,
                                  const MethodOptions& options = {});

}  // namespace bhcl
