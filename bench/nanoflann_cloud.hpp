// nanoflann's adaptors over a flat n x 3 float vector, for the benchmarks that run nanoflann beside
// block hashing (mapping_bench, update_bench). BHCL_HAVE_NANOFLANN says whether the header is
// there (Debian: libnanoflann-dev); without it the benchmarks skip nanoflann's rows.
#pragma once

#include <cstddef>
#include <vector>

#if __has_include(<nanoflann.hpp>)
#include <nanoflann.hpp>
#define BHCL_HAVE_NANOFLANN 1
#else
#define BHCL_HAVE_NANOFLANN 0
#endif

#if BHCL_HAVE_NANOFLANN
namespace bhcl::bench {

// The first n points of *p as nanoflann's dataset. The adaptors keep a reference to it and read
// points by index, so raising n after an insert makes the new points visible to addPoints.
struct Cloud {
  const std::vector<float>* p = nullptr;
  std::size_t n = 0;  // points visible to the adaptor
  std::size_t kdtree_get_point_count() const { return n; }
  float kdtree_get_pt(std::size_t i, std::size_t d) const { return (*p)[3 * i + d]; }
  template <class B>
  bool kdtree_get_bbox(B&) const { return false; }
};
using NfMetric = nanoflann::L2_Simple_Adaptor<float, Cloud>;
using NfStatic = nanoflann::KDTreeSingleIndexAdaptor<NfMetric, Cloud, 3>;
using NfDynamic = nanoflann::KDTreeSingleIndexDynamicAdaptor<NfMetric, Cloud, 3>;

}  // namespace bhcl::bench
#endif
