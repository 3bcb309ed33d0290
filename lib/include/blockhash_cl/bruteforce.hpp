// Exact kNN by brute force on the OpenCL device: every query scans every point. O(N) per query;
// the reference that the other device methods are tested against, and the fastest exact method
// for small N.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

class BruteForceIndex : public Index {
 public:
  // points: N x 3 floats (copied to the device). Throws for N == 0 or non-finite points.
  BruteForceIndex(std::shared_ptr<Runtime> runtime, const float* points, std::size_t n_points);

  std::string method() const override { return "bruteforce"; }
  bool exact() const override { return true; }
  // The device array (none of its own where the device reads the host array in place).
  std::size_t memory_bytes() const override;
  // The caller's points (the double-precision fallback) and the host mirror host_.
  // The exact methods' copy of the caller's points and the host array (holes included).
  std::size_t host_bytes() const override { return size() * 3 * sizeof(float) + host_.size() * 16; }

 protected:
  BHCL_INDEX_DEVICE_HOOKS
  BHCL_INDEX_UPDATE_HOOKS

 private:
  struct HostPoint {
    float x, y, z;
    std::int32_t id;
  };
  void upload_from(std::size_t from, bool fresh);
  void upload_removed();
  std::vector<HostPoint> host_;  // the device array: ascending ids
  cl::Buffer points_;  // float4 per point, w = the point's id (int bits)
  std::size_t cap_bytes_ = 0;
  std::size_t holes_ = 0;  // removed points still stored (skipped by their marks) until a compaction
  // The removed ids' marks the kernels read (Index::removed_words): a view, or a copy of the
  // first removed_words_ words; null while no id was removed.
  cl::Buffer removed_;
  std::size_t removed_words_ = 0, removed_cap_bytes_ = 0;
};

}  // namespace bhcl
