// ikd-Tree (FAST-LIO2's incremental k-d tree, github.com/hku-mars/ikd-Tree, GPL-2.0) as a baseline
// of mapping_bench (issue 39), behind an interface of our own: its header puts `using namespace
// std` and PCL's point types into every file that includes it, so only ikdtree_baseline.cpp does.
// Built only when CMake is given its source folder (-DBHCL_IKDTREE_DIR=<...>/ikd-Tree) and finds
// PCL's headers and Eigen (Debian: libpcl-dev, libeigen3-dev); BHCL_HAVE_IKDTREE says so.
#pragma once

#include <cstddef>
#include <memory>
#include <vector>

namespace bhcl::bench {

class IkdTree {
 public:
  IkdTree();
  ~IkdTree();
  IkdTree(const IkdTree&) = delete;
  IkdTree& operator=(const IkdTree&) = delete;

  void build(const float* xyz, std::size_t n);
  // Appends n points as they are (no downsampling: the map must hold what the others hold).
  void add(const float* xyz, std::size_t n);
  // Deletes the points at these coordinates (ikd-Tree deletes by coordinates, not by id).
  void remove(const float* xyz, std::size_t n);
  // The k nearest of each query on `threads` host threads over ranges of queries: their
  // coordinates (n x k x 3), squared distances (n x k, ascending) and counts (n).
  void query(const std::vector<float>& qs, int k, int threads, std::vector<float>& xyz, std::vector<float>& dist2,
             std::vector<int>& counts);
  std::size_t size();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace bhcl::bench
