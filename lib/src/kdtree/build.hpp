// The kd-tree's host build, apart from the index so that tests can compare its arrays.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "kdtree_layout.h"

namespace bhcl::detail {

struct KdTreeArrays {
  std::vector<bhcl_kd_node> nodes;  // depth-first: left child = next node, inner a = right child
  std::vector<std::uint32_t> perm;  // leaf order -> caller's index
  std::size_t leaves = 0;
  int depth = 0;  // inner nodes on the longest root-to-leaf path
};

// Median splits on the widest dimension of each node's points (xyz: n x 3 floats), at most `leaf`
// points per leaf, on `threads` host threads (0: all hardware threads). The arrays are the same,
// byte for byte, whatever the thread count.
KdTreeArrays build_kdtree(const float* xyz, std::size_t n, std::size_t leaf, unsigned threads);

}  // namespace bhcl::detail
