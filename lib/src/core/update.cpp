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
#include "core/point_scan.hpp"

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

std::size_t words_for(std::size_t ids) { return (ids + 31) / 32; }

// A remove's ids refused (they were checked in one pass that stopped at the first bad one):
// the error the checks name, an id outside the range or already removed first (in entry order),
// else the smallest id given twice, with both entries.
// removed: the index's marks (a bit per id issued, see Index::id_removed).
[[noreturn]] void throw_bad_remove(const std::string& method, std::int32_t bound, const std::uint32_t* removed,
                                   const std::int32_t* ids, std::size_t n) {
  for (std::size_t i = 0; i < n; ++i) {
    const std::int32_t id = ids[i];
    if (id < 0 || id >= bound)
      throw Error(method + ": remove: id " + std::to_string(id) + " (entry " + std::to_string(i) +
                  ") is outside the issued ids [0, " + std::to_string(bound) + ")");
    if ((removed[std::size_t(id) >> 5] >> (id & 31)) & 1u)
      throw Error(method + ": remove: id " + std::to_string(id) + " (entry " + std::to_string(i) +
                  ") was already removed");
  }
  std::vector<std::int32_t> sorted(ids, ids + n);
  std::sort(sorted.begin(), sorted.end());
  for (std::size_t i = 1; i < n; ++i) {
    if (sorted[i] != sorted[i - 1]) continue;
    const std::size_t at = std::size_t(std::find(ids, ids + n, sorted[i]) - ids);
    const std::size_t again = std::size_t(std::find(ids + at + 1, ids + n, sorted[i]) - ids);
    throw Error(method + ": remove: id " + std::to_string(sorted[i]) + " appears twice (entries " +
                std::to_string(at) + " and " + std::to_string(again) + ")");
  }
  throw Error(method + ": remove: the ids were refused (internal)");
}

// Distinct ids ascending. Many (a share of the issued ones): a bit per id read back a word at a
// time, O(n + range), where a sort of 100k ids took as long as the rest of a grid remove (and a
// byte per id with a branch on each cost 1.5 ms of a 10 % remove at 1M: mispredicts).
std::vector<std::int32_t> ascending(const std::int32_t* ids, std::size_t n, std::int32_t bound) {
  std::vector<std::int32_t> sorted;
  if (n * 16 < std::size_t(bound)) {
    sorted.assign(ids, ids + n);
    std::sort(sorted.begin(), sorted.end());
    return sorted;
  }
  std::vector<std::uint64_t> mark((std::size_t(bound) + 63) / 64, 0);
  for (std::size_t i = 0; i < n; ++i) mark[std::size_t(ids[i]) / 64] |= std::uint64_t(1) << (ids[i] % 64);
  sorted.resize(n);
  std::size_t at = 0;
  for (std::size_t w = 0; w < mark.size(); ++w)
    for (std::uint64_t bits = mark[w]; bits; bits &= bits - 1)
      sorted[at++] = static_cast<std::int32_t>(64 * w + std::size_t(__builtin_ctzll(bits)));
  return sorted;
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
  removed_bits_.clear();
  removed_n_ = 0;
}

bool Index::contains(std::int32_t id) const {
  std::shared_lock<std::shared_mutex> lock(update_mutex_);
  return id >= 0 && id < id_bound_ && !id_removed(id);
}

void Index::set_id_state(std::int32_t bound, const std::vector<std::int32_t>& live) {
  id_bound_ = bound;
  removed_bits_.assign(words_for(std::size_t(bound)), ~0u);
  if (bound % 32) removed_bits_.back() = (1u << (bound % 32)) - 1;  // no bit past the bound
  for (std::int32_t id : live) removed_bits_[std::size_t(id) >> 5] &= ~(1u << (id & 31));
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
  // One parallel pass (the serial check per point was a fortieth of a 10 % insert at 1M); the
  // serial one only to name the first non-finite point.
  if (!detail::scan_points(points, n).finite) validate_points(points, n, "inserted points");
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
    // The build reserves room for as many points again (prepare_points); past it, twice the
    // capacity: an append, not a move of every row (issue 39: at 1M + 25 % the move faulted in
    // fresh pages and cost more than a fresh build).
    const std::size_t need = caller_points_.size() + 3 * n;
    if (need > caller_points_.capacity()) caller_points_.reserve(std::max(need, 2 * caller_points_.capacity()));
    caller_points_.insert(caller_points_.end(), points, points + 3 * n);
  }
  if (!removed_bits_.empty()) removed_bits_.resize(words_for(std::size_t(first) + n), 0);
  id_bound_ = first + static_cast<std::int32_t>(n);
  try {
    insert_points(points, scaled, n, first);
  } catch (...) {
    if (keep_points) caller_points_.resize(had);
    if (!removed_bits_.empty()) removed_bits_.resize(words_for(std::size_t(first)));
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
  mark_removed(ids, n);
  if (n >= n_points_) {
    unmark_removed(ids, n);
    throw Error(method() + ": remove: removing all " + std::to_string(n_points_) +
                " live points would leave the index empty (an index holds at least one point)");
  }
  // Only the marks change here: the exact methods' copy of the caller's points keeps the removed
  // rows (the double-precision fallback skips them by their marks; writing NaN into each row was
  // a cache miss per id, a third of a brute-force 10 % remove).
  const std::vector<std::int32_t> sorted = ascending(ids, n, id_bound_);
  try {
    remove_points(sorted.data(), n);
  } catch (...) {
    unmark_removed(ids, n);
    throw;
  }
  removed_n_ += n;
  n_points_ -= n;
}

// The checks of a remove's ids and their marks, in one pass: each id in range and not removed
// (so, as its bit is set on the way, not given twice). At the first bad id the bits set so far
// are cleared and throw_bad_remove names the error.
void Index::mark_removed(const std::int32_t* ids, std::size_t n) {
  if (removed_bits_.empty()) removed_bits_.assign(words_for(std::size_t(id_bound_)), 0);
  std::uint32_t* const bits = removed_bits_.data();
  for (std::size_t i = 0; i < n; ++i) {
    const std::int32_t id = ids[i];
    const std::uint32_t bit = 1u << (id & 31);
    if (id < 0 || id >= id_bound_ || (bits[std::size_t(id) >> 5] & bit)) {
      unmark_removed(ids, i);
      throw_bad_remove(method(), id_bound_, bits, ids, n);
    }
    bits[std::size_t(id) >> 5] |= bit;
  }
}

void Index::unmark_removed(const std::int32_t* ids, std::size_t n) {
  for (std::size_t i = 0; i < n; ++i) removed_bits_[std::size_t(ids[i]) >> 5] &= ~(1u << (ids[i] & 31));
}

}  // namespace bhcl
