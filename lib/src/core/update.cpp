// Index::insert / Index::remove (issue 23): the checks, the stable ids and the lock every method
// shares. The structures change in each method's insert_points / remove_points.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <mutex>
#include <string>
#include <vector>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/knn.hpp"

namespace bhcl {
namespace {
// The indexes this thread holds a read lock on: a query that queries its own index (the recall
// tuning of block hashing) must not take the shared lock twice, which a writer waiting in
// between would deadlock on some implementations.
thread_local std::vector<const Index*> t_read_locked;
constexpr std::size_t kMaxIds = 0x7ffffffe;  // ids are int32; 0x7fffffff marks an empty slot

// Writer preference. std::shared_mutex (glibc's rwlock) prefers readers: with queries arriving
// back to back an update could wait for ever (measured: 0.7 s per update against two query
// threads). A writer holds its index's gate while it waits for the lock, and a reader passes the
// gate before it takes the lock, so readers arriving after a waiting writer queue behind it.
// The gates are a fixed table striped by the index's address (no per-index member: the header's
// layout is kept); two indexes sharing a stripe only share the short gate passage. A reader that
// already holds some index's read lock skips the gate (it takes the lock directly; reader
// preference lets it in past a waiting writer), so no lock holder ever waits on a gate: no cycle.
std::mutex& gate(const Index* ix) {
  static std::mutex gates[64];
  return gates[(reinterpret_cast<std::uintptr_t>(ix) >> 6) % 64];
}
}  // namespace

Index::ReadLock::ReadLock(const Index& ix) : ix_(&ix) {
  if (std::find(t_read_locked.begin(), t_read_locked.end(), ix_) != t_read_locked.end()) return;
  if (t_read_locked.empty()) {
    std::lock_guard<std::mutex> g(gate(ix_));
    ix_->update_mutex_.lock_shared();
  } else {
    ix_->update_mutex_.lock_shared();
  }
  t_read_locked.push_back(ix_);
  held_ = true;
}

Index::ReadLock::~ReadLock() {
  if (!held_) return;
  t_read_locked.erase(std::find(t_read_locked.begin(), t_read_locked.end(), ix_));
  ix_->update_mutex_.unlock_shared();
}

void Index::set_size(std::size_t n) {
  n_points_ = n;
  id_bound_ = static_cast<std::int32_t>(std::min(n, kMaxIds));
  removed_.clear();
  removed_n_ = 0;
}

bool Index::contains(std::int32_t id) const {
  std::shared_lock<std::shared_mutex> lock(update_mutex_);
  return id >= 0 && id < id_bound_ && (removed_.empty() || !removed_[std::size_t(id)]);
}

void Index::set_id_state(std::int32_t bound, const std::vector<std::int32_t>& live) {
  id_bound_ = bound;
  removed_.assign(std::size_t(bound), true);
  for (std::int32_t id : live) removed_[std::size_t(id)] = false;
  removed_n_ = std::size_t(bound) - live.size();
  n_points_ = live.size();
}

void Index::insert_points(const float*, const float*, std::size_t, std::int32_t) {
  throw Error(method() + ": this index does not support insert");
}

void Index::remove_points(const std::int32_t*, std::size_t) {
  throw Error(method() + ": this index does not support remove");
}

std::int32_t Index::insert(const float* points, std::size_t n) {
  if (n == 0) throw Error(method() + ": insert: no points (n = 0)");
  if (!points) throw Error(method() + ": insert: the point array is null");
  validate_points(points, n, "inserted points");  // names the first non-finite point
  std::lock_guard<std::mutex> turn(gate(this));  // writer preference (see gate())
  std::unique_lock<std::shared_mutex> lock(update_mutex_);
  if (std::size_t(id_bound_) + n > kMaxIds)
    throw Error(method() + ": insert of " + std::to_string(n) + " points would pass the int32 id range (" +
                std::to_string(id_bound_) + " ids issued, at most " + std::to_string(kMaxIds) + ")");
  // The structure's coordinates (the build's power-of-two scale, kept: the structure is not
  // rescaled by an update). A point that the scale sends out of the float range is refused.
  std::vector<float> storage;
  const float* scaled = to_structure(points, n, storage);
  for (std::size_t i = 0; i < 3 * n && scale_exp_ != 0; ++i)
    if (!std::isfinite(scaled[i]) || std::fabs(scaled[i]) >= std::ldexp(1.0f, 126))
      throw Error(method() + ": insert: inserted point " + std::to_string(i / 3) +
                  " lies outside the float range of the index's coordinates (scale 2^" +
                  std::to_string(scale_exp_) + "); build a fresh index");
  const std::int32_t first = id_bound_;
  // The base's state first (the methods' rebuilds read caller_points()), undone if the method throws.
  const std::size_t had = caller_points_.size();
  const bool keep_points = exact() && !caller_points_.empty();
  if (keep_points) {
    // Past the room: a fresh build's room (an eighth) over the result, not vector's doubling (a
    // block of a fresh build's size comes from memory a freed index left; a doubled one faults in
    // fresh pages, which cost more than the build: bruteforce.cpp's insert_points).
    const std::size_t need = caller_points_.size() + 3 * n;
    if (need > caller_points_.capacity())
      caller_points_.reserve(std::max(need + need / 8, caller_points_.capacity() + caller_points_.capacity() / 8));
    caller_points_.insert(caller_points_.end(), points, points + 3 * n);
  }
  if (!removed_.empty()) removed_.resize(std::size_t(first) + n, false);
  id_bound_ = first + static_cast<std::int32_t>(n);
  try {
    insert_points(points, scaled, n, first);
  } catch (...) {
    if (keep_points) caller_points_.resize(had);
    if (!removed_.empty()) removed_.resize(std::size_t(first));
    id_bound_ = first;
    throw;
  }
  n_points_ += n;
  return first;
}

void Index::remove(const std::int32_t* ids, std::size_t n) {
  if (n == 0) throw Error(method() + ": remove: no ids (n = 0)");
  if (!ids) throw Error(method() + ": remove: the id array is null");
  std::lock_guard<std::mutex> turn(gate(this));  // writer preference (see gate())
  std::unique_lock<std::shared_mutex> lock(update_mutex_);
  for (std::size_t i = 0; i < n; ++i) {
    const std::int32_t id = ids[i];
    if (id < 0 || id >= id_bound_)
      throw Error(method() + ": remove: id " + std::to_string(id) + " (entry " + std::to_string(i) +
                  ") is outside the issued ids [0, " + std::to_string(id_bound_) + ")");
    if (!removed_.empty() && removed_[std::size_t(id)])
      throw Error(method() + ": remove: id " + std::to_string(id) + " (entry " + std::to_string(i) +
                  ") was already removed");
  }
  // The ids ascending, each once. Many ids (a share of the issued ones): marks over the id range,
  // O(n + range), where a sort of 100k ids took as long as the rest of a grid remove.
  std::vector<std::int32_t> sorted;
  auto twice = [&](std::int32_t id) {
    const std::size_t at = std::size_t(std::find(ids, ids + n, id) - ids);
    const std::size_t again = std::size_t(std::find(ids + at + 1, ids + n, id) - ids);
    throw Error(method() + ": remove: id " + std::to_string(id) + " appears twice (entries " +
                std::to_string(at) + " and " + std::to_string(again) + ")");
  };
  if (n * 16 >= std::size_t(id_bound_)) {
    // A bit per id, read back a word at a time (a byte per id and a branch on each cost 1.5 ms
    // of a 10 % remove at 1M, perf: the branch mispredicts on the scattered marks).
    std::vector<std::uint64_t> mark((std::size_t(id_bound_) + 63) / 64, 0);
    std::int32_t dup = -1;
    for (std::size_t i = 0; i < n; ++i) {
      const std::size_t id = std::size_t(ids[i]);
      const std::uint64_t bit = std::uint64_t(1) << (id % 64);
      if ((mark[id / 64] & bit) && (dup < 0 || ids[i] < dup)) dup = ids[i];  // the smallest, as the sort reported
      mark[id / 64] |= bit;
    }
    if (dup >= 0) twice(dup);
    sorted.resize(n);
    std::size_t at = 0;
    for (std::size_t w = 0; w < mark.size(); ++w)
      for (std::uint64_t bits = mark[w]; bits; bits &= bits - 1)
        sorted[at++] = static_cast<std::int32_t>(64 * w + std::size_t(__builtin_ctzll(bits)));
  } else {
    sorted.assign(ids, ids + n);
    std::sort(sorted.begin(), sorted.end());
    for (std::size_t i = 1; i < n; ++i)
      if (sorted[i] == sorted[i - 1]) twice(sorted[i]);
  }
  if (n >= n_points_)
    throw Error(method() + ": remove: removing all " + std::to_string(n_points_) +
                " live points would leave the index empty (an index holds at least one point)");
  if (removed_.empty()) removed_.assign(std::size_t(id_bound_), false);
  for (std::int32_t id : sorted) removed_[std::size_t(id)] = true;
  // Exact methods: the double-precision fallback scans caller_points_; NaN is never within any
  // radius there (its comparisons are false), so a removed point drops out of it.
  std::vector<float> saved;
  const bool keep_points = exact() && !caller_points_.empty();
  if (keep_points) {
    saved.resize(3 * n);
    // Each id's row is a cache miss (a tenth of 1M ids: 43 % of a brute-force remove, perf); a
    // prefetch some ids ahead overlaps them.
    constexpr std::size_t kAhead = 64;
    float* cp = caller_points_.data();
    for (std::size_t i = 0; i < n; ++i) {
      if (i + kAhead < n) __builtin_prefetch(cp + 3 * std::size_t(sorted[i + kAhead]), 1);
      float* c = cp + 3 * std::size_t(sorted[i]);
      for (int d = 0; d < 3; ++d) {
        saved[3 * i + std::size_t(d)] = c[d];
        c[d] = NAN;
      }
    }
  }
  try {
    remove_points(sorted.data(), n);
  } catch (...) {
    for (std::size_t i = 0; i < n; ++i) {
      removed_[std::size_t(sorted[i])] = false;
      if (keep_points)
        for (int d = 0; d < 3; ++d) caller_points_[3 * std::size_t(sorted[i]) + d] = saved[3 * i + d];
    }
    throw;
  }
  removed_n_ += n;
  n_points_ -= n;
}

}  // namespace bhcl
