// An index spanning several OpenCL devices in one process (e.g. the CPU through PoCL and a GPU,
// or several GPUs): each device holds its own copy of the structure, a host-array batch is split
// among them in proportion to their measured throughput, the parts run concurrently (one host
// thread per device, each on its device's own queue), and the rows come back in the caller's
// order. Results equal the single-device results bit for bit: every copy is built by the same
// method from the same points with the same options, and the contract makes a row independent of
// the batch it was answered in (knn.hpp).
#pragma once

#include <cstddef>
#include <functional>
#include <memory>
#include <mutex>
#include <shared_mutex>
#include <string>
#include <vector>

#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/knn.hpp"
#include "blockhash_cl/runtime.hpp"

namespace bhcl {

// Per device, what one call did.
struct DeviceShare {
  std::string device;      // DeviceInfo::summary()
  std::size_t queries = 0;  // queries this device answered
  double weight = 0;        // the share of the batch it was given, in [0, 1]
  QueryStats stats;         // its own call's stats (query_s: its kernels)
};

class MultiDeviceIndex final : public SearchIndex {
 public:
  // Builds `method` over the points on every runtime (one copy each, built concurrently: block
  // hashing builds its structure on the host once per device). Throws bhcl::Error for an empty
  // list, a null runtime, or whatever a single build throws (naming the device).
  MultiDeviceIndex(std::vector<std::shared_ptr<Runtime>> runtimes, const std::string& method,
                   const float* points, std::size_t n_points, const MethodOptions& options = {});

  // Host arrays, under the library's contract (knn.hpp). The batch is cut into one contiguous
  // part per device, sized by the current weights (equal at first, then each device's queries
  // per second measured on the previous calls, from its part's wall time without compiles).
  // Parts run concurrently; out gets every row in the caller's order. The returned stats sum the
  // parts, except query_s: the slowest part's wall time (compiles excluded), the batch's critical
  // path; `shares` gets each device's part with its own stats. A device that fails makes the call throw, naming it.
  QueryStats query(const float* queries, std::size_t n, const SearchParams& params, KnnResult& out,
                   std::vector<DeviceShare>* shares) const;
  QueryStats query(const float* queries, std::size_t n, const SearchParams& params,
                   KnnResult& out) const override {
    return query(queries, n, params, out, nullptr);
  }
  // Radius search, split and merged the same way (RadiusResult's slices in the caller's order).
  QueryStats radius_search(const float* queries, std::size_t n, float r, const RadiusParams& params,
                           RadiusResult& out, std::vector<DeviceShare>* shares) const;
  QueryStats radius_search(const float* queries, std::size_t n, float r, const RadiusParams& params,
                           RadiusResult& out) const override {
    return radius_search(queries, n, r, params, out, nullptr);
  }

  // Updates (Index::insert/remove, same ids and errors) applied to every device's copy; exclusive
  // with this index's queries (a std::shared_mutex), so a query never sees the copies differ.
  // A failure on one device leaves the copies differing: the call throws naming the device, and
  // the index must be rebuilt.
  std::int32_t insert(const float* points, std::size_t n);
  void remove(const std::int32_t* ids, std::size_t n);
  std::int32_t id_bound() const { return indexes_.front()->id_bound(); }

  std::size_t devices() const { return indexes_.size(); }
  const Index& index(std::size_t device) const { return *indexes_.at(device); }
  std::string method() const override { return indexes_.front()->method(); }
  bool exact() const override { return indexes_.front()->exact(); }
  std::size_t size() const override { return indexes_.front()->size(); }
  // The copies are built alike, so the first one answers for all: the batch's parameters (block
  // hashing tunes A on a sample of the batch, as one device would), the recall tuning and the
  // build's and a query's reports.
  SearchParams params_for_batch(const float* queries, std::size_t n, const SearchParams& params,
                                BatchTuning* info = nullptr) const override {
    return indexes_.front()->params_for_batch(queries, n, params, info);
  }
  std::optional<RecallTuning> recall_tuning(const SearchParams& params) const override {
    return indexes_.front()->recall_tuning(params);
  }
  UsedFields build_used() const override { return indexes_.front()->build_used(); }
  UsedFields search_used(const SearchParams& params) const override { return indexes_.front()->search_used(params); }
  // The current split: one weight per device, summing to 1.
  std::vector<double> weights() const;
  // Fixes the split (e.g. from a known device ratio); the weights are normalised. Later calls
  // keep adapting from there. Throws for a wrong count or a negative/zero-sum list.
  void set_weights(const std::vector<double>& w);

 private:
  // Parts of n by the current weights: first[d] .. first[d + 1].
  std::vector<std::size_t> split(std::size_t n) const;
  // Moves the weights to adapted_weights() of this call's parts.
  void learn(const std::vector<std::size_t>& counts, const std::vector<double>& seconds) const;
  // One batch over every device (kNN and radius alike), under the shared lock: run(d, first, m)
  // answers queries [first, first + m) on device d (all devices at once), then merge(d, first)
  // takes device d's part, in device order; the stats summed, the shares listed, the split learnt.
  QueryStats on_devices(std::size_t n, const std::function<QueryStats(std::size_t, std::size_t, std::size_t)>& run,
                        const std::function<void(std::size_t, std::size_t)>& merge,
                        std::vector<DeviceShare>* shares) const;

  std::vector<std::unique_ptr<Index>> indexes_;
  mutable std::shared_mutex update_mutex_;  // queries shared, insert/remove exclusive
  // Writer preference (see Index's gate in lib/src/core/update.cpp): an update holds it while it
  // waits for the lock, a query passes it before taking the lock.
  mutable std::mutex update_gate_;
  mutable std::mutex weights_mutex_;
  mutable std::vector<double> weights_;
};

// The split's learning rule, apart so that it is testable without timing a machine: the devices'
// throughput on one call (counts[d] queries in seconds[d]; parts under 256 queries or untimed are
// left out and keep their weight), and new weights that mix half of the old ones with half of the
// measured shares, so that one noisy call does not swing the split. The result sums as `old` does.
std::vector<double> adapted_weights(const std::vector<double>& old, const std::vector<std::size_t>& counts,
                                    const std::vector<double>& seconds);

// Parses a --device list ("pocl,nvidia", "0:0,1:0"): comma-separated specs, each as Runtime
// takes it. Throws bhcl::Error for an empty entry.
std::vector<std::string> split_device_list(const std::string& list);

}  // namespace bhcl
