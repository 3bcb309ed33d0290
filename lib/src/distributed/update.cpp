// DistributedIndex::insert / remove (issue 39): collective updates with Index::insert/remove's
// rules over the ranks' concatenated batch (distributed.hpp). The checks are made so that every
// rank reaches the same verdict: either from numbers every rank holds (the counts, the gathered
// ids and their agreed status) or through mpi_agree, so that a bad batch throws the same
// bhcl::Error on every rank and no rank is left in a collective.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <string>

#include "blockhash_cl/distributed.hpp"
#include "blockhash_cl/error.hpp"
#include "distributed/mpi_util.hpp"
#include "distributed/shard.hpp"
#include "distributed/wire.hpp"

namespace bhcl {

using distributed::exchange;
using distributed::Stopwatch;
using namespace distributed::wire;

namespace {

constexpr std::size_t kMaxShardIds = 0x7ffffffe;  // a local index's int32 ids (Index::insert's bound)

const std::string kInsert = std::string(kWhat) + "::insert";
const std::string kRemove = std::string(kWhat) + "::remove";

// "id 17 (rank 1's entry 3)": an entry of the concatenated remove batch named where its rank passed it.
std::string entry_name(std::int64_t id, std::size_t e, const std::vector<std::uint64_t>& entry_first) {
  const std::size_t r =
      static_cast<std::size_t>(std::upper_bound(entry_first.begin(), entry_first.end(), e) - entry_first.begin()) - 1;
  return "id " + std::to_string(id) + " (rank " + std::to_string(r) + "'s entry " +
         std::to_string(e - entry_first[r]) + ")";
}

void grow(ShardBox& b, const float* p) {
  for (int d = 0; d < 3; ++d) b.lo[d] = std::min(b.lo[d], p[d]), b.hi[d] = std::max(b.hi[d], p[d]);
}

ShardBox empty_box() {
  ShardBox b;
  for (int d = 0; d < 3; ++d) {
    b.lo[d] = std::numeric_limits<float>::infinity();
    b.hi[d] = -std::numeric_limits<float>::infinity();
  }
  return b;
}

// The two stages both updates run after routing, each timed into us: the local index's update,
// then the routing boxes' (changed, then published to every rank).
template <class LocalStep, class BoxStep>
void timed_stages(DistributedUpdateStats& us, LocalStep&& local_step, BoxStep&& box_step) {
  Stopwatch local;
  local_step();
  us.local_s = local.seconds();
  Stopwatch boxes;
  box_step();
  us.boxes_s = boxes.seconds();
}

}  // namespace

// The new points that came to this rank: ascending global ids, their points and Hilbert keys.
struct DistributedIndex::Incoming {
  std::vector<std::int64_t> ids;
  std::vector<float> xyz;
  std::vector<std::uint64_t> keys;
  std::uint64_t total = 0;  // the call's points over all ranks
};

std::vector<std::int64_t> DistributedIndex::shard_live_ids() const {
  std::vector<std::int64_t> out;
  out.reserve(shard_live_);
  for (std::size_t l = 0; l < shard_ids_.size(); ++l)
    if (!shard_removed_[l]) out.push_back(shard_ids_[l]);
  return out;
}

std::size_t DistributedIndex::host_bytes() const {
  return shard_ids_.capacity() * sizeof(std::int64_t) + shard_xyz_.capacity() * sizeof(float) +
         shard_run_.capacity() * sizeof(std::uint16_t) + shard_removed_.capacity() / 8;
}

// --- insert

// The counts, the id range and every rank's points checked; returns this rank's offset in the
// batch and sets `total`. The index is unchanged when it throws (on every rank alike).
std::uint64_t DistributedIndex::check_insert(const float* points, std::size_t n, std::uint64_t& total) {
  std::uint64_t n_local = n, offset = 0;
  total = 0;
  MPI_Exscan(&n_local, &offset, 1, MPI_UINT64_T, MPI_SUM, comm_);
  if (rank_ == 0) offset = 0;  // MPI leaves rank 0's result undefined
  MPI_Allreduce(&n_local, &total, 1, MPI_UINT64_T, MPI_SUM, comm_);
  // From the totals alone: every rank throws here or none does.
  if (total == 0) throw Error(kInsert + ": no points on any rank (n = 0 everywhere)");
  const std::uint64_t issued = static_cast<std::uint64_t>(id_bound_ - id_base_);
  if (issued + total > distributed::kMaxPoints)
    throw Error(kInsert + ": " + std::to_string(total) + " points after the " + std::to_string(issued) +
                " ids issued would pass 2^40 - 1 ids in all");
  std::string err;
  if (n > 0 && points == nullptr)
    err = "points is null with n = " + std::to_string(n);
  else
    err = distributed::nonfinite_point(points, n, id_bound_ + static_cast<std::int64_t>(offset), "inserted points");
  mpi_agree(comm_, err, kInsert);
  return offset;
}

// Each new point to the rank owning its key (the build's quantiser and splitters), with its
// position over all ranks; returns what came to this rank, in global-id order.
DistributedIndex::Incoming DistributedIndex::route_new_points(const float* points, std::size_t n,
                                                              std::uint64_t offset, DistributedUpdateStats& us) {
  const std::size_t R = static_cast<std::size_t>(ranks_), me = static_cast<std::size_t>(rank_);
  const std::uint64_t first_position = static_cast<std::uint64_t>(id_bound_ - id_base_) + offset;
  std::vector<int> owner(n);
  std::vector<std::size_t> send_counts(R, 0), pos(R, 0), recv_counts;
  for (std::size_t i = 0; i < n; ++i) {
    owner[i] = owner_of_key(key_of(points + 3 * i));
    ++send_counts[static_cast<std::size_t>(owner[i])];
  }
  for (std::size_t r = 1; r < R; ++r) pos[r] = pos[r - 1] + send_counts[r - 1];
  // Grouped by owner, each group in the caller's order (positions ascending).
  std::vector<PointRecord> out(n);
  for (std::size_t i = 0; i < n; ++i) {
    const float* p = points + 3 * i;
    out[pos[static_cast<std::size_t>(owner[i])]++] = {{p[0], p[1], p[2]}, 0, first_position + i};
  }
  const std::vector<unsigned char> raw =
      exchange(comm_, out.data(), send_counts, sizeof(PointRecord), recv_counts, "inserting the points");
  std::vector<PointRecord> got(raw.size() / sizeof(PointRecord));
  if (!got.empty()) std::memcpy(got.data(), raw.data(), raw.size());
  // They come grouped by source rank in rank order, each in its order: already ascending; sorted
  // all the same should a route ever reorder them (the local ids must follow the global ones).
  auto by_position = [](const PointRecord& a, const PointRecord& b) { return a.position < b.position; };
  if (!std::is_sorted(got.begin(), got.end(), by_position)) std::sort(got.begin(), got.end(), by_position);
  Incoming in;
  in.ids.resize(got.size());
  in.xyz.resize(3 * got.size());
  in.keys.resize(got.size());
  for (std::size_t j = 0; j < got.size(); ++j) {
    in.ids[j] = id_base_ + static_cast<std::int64_t>(got[j].position);
    std::memcpy(&in.xyz[3 * j], got[j].xyz, 12);
    in.keys[j] = key_of(got[j].xyz);
  }
  us.sent = n - send_counts[me];
  us.bytes_sent = us.sent * sizeof(PointRecord);
  us.bytes_received = (got.size() - recv_counts[me]) * sizeof(PointRecord);
  return in;
}

// The new points into the local index, agreed: on a failure anywhere the ranks that inserted
// remove their points again (their ids are spent) and every rank throws.
void DistributedIndex::insert_locally(const Incoming& in) {
  const std::size_t m = in.ids.size();
  std::string err;
  if (shard_ids_.size() + m > kMaxShardIds)
    err = std::to_string(m) + " points after the " + std::to_string(shard_ids_.size()) +
          " this shard's index has issued would pass its int32 ids (2^31 - 2): use more ranks or a fresh build";
  else if (m > 0 && !local_)
    err = "internal error: new points reached a rank with an empty shard";
  mpi_agree(comm_, err, kInsert);  // the checks: nothing changed yet anywhere
  const std::size_t had = shard_ids_.size();
  bool inserted = false;
  try {
    if (m > 0) {
      local_->insert(in.xyz.data(), m);
      inserted = true;
    }
  } catch (const std::exception& e) {
    err = "inserting " + std::to_string(m) + " points into the local " + method_ + " index: " + what_of(e);
  }
  // Recorded on success, and on a failure elsewhere too (the local ids were issued there).
  auto record = [&](bool removed) {
    shard_ids_.insert(shard_ids_.end(), in.ids.begin(), in.ids.end());
    shard_xyz_.insert(shard_xyz_.end(), in.xyz.begin(), in.xyz.end());
    shard_removed_.resize(had + m, removed);
  };
  try {
    mpi_agree(comm_, err, kInsert);
  } catch (...) {
    id_bound_ += static_cast<std::int64_t>(in.total);  // spent on every rank alike
    if (inserted) {
      record(true);
      shard_run_.resize(had + m, 0);
      std::vector<std::int32_t> local_ids(m);
      for (std::size_t j = 0; j < m; ++j) local_ids[j] = static_cast<std::int32_t>(had + j);
      try {
        local_->remove(local_ids.data(), m);
      } catch (const std::exception& e) {
        std::fprintf(stderr, "%s: rank %d: undoing the insert failed too (%s): rebuild the index\n",
                     kInsert.c_str(), rank_, what_of(e).c_str());
      }
    }
    throw;
  }
  if (inserted) record(false);
}

// Each new point joins the sub-run its key falls in (the last whose first key is at or before
// it), whose box grows to hold it.
void DistributedIndex::grow_boxes(const Incoming& in) {
  if (run_first_keys_.empty() && !in.ids.empty()) {
    // A rank with no sub-run (an empty shard at the build) takes points only if routing changes:
    // one run from key 0 keeps the boxes right all the same.
    run_first_keys_.push_back(0);
    my_boxes_.push_back(empty_box());
  }
  for (std::size_t j = 0; j < in.ids.size(); ++j) {
    const std::size_t at =
        static_cast<std::size_t>(std::upper_bound(run_first_keys_.begin(), run_first_keys_.end(), in.keys[j]) -
                                 run_first_keys_.begin());
    const std::size_t run = at == 0 ? 0 : at - 1;
    shard_run_.push_back(static_cast<std::uint16_t>(run));
    grow(my_boxes_[run], &in.xyz[3 * j]);
  }
  shard_live_ += in.ids.size();
}

std::int64_t DistributedIndex::insert(const float* points, std::size_t n, DistributedUpdateStats* stats) {
  Stopwatch wall;
  DistributedUpdateStats us;
  us.n_input = n;
  std::uint64_t total = 0;
  const std::uint64_t offset = check_insert(points, n, total);
  const std::int64_t mine = id_bound_ + static_cast<std::int64_t>(offset);
  us.n_global = total;
  Incoming in = route_new_points(points, n, offset, us);
  in.total = total;
  us.route_s = wall.seconds();
  timed_stages(us, [&] { insert_locally(in); }, [&] {
    grow_boxes(in);
    publish_boxes();
  });
  us.applied = in.ids.size();
  n_global_ += total;
  id_bound_ += static_cast<std::int64_t>(total);
  us.wall_s = wall.seconds();
  if (stats) *stats = us;
  return mine;
}

// --- remove

// Every rank's ids, concatenated in rank order, on every rank (entry_first[r]: rank r's first
// entry). Refused before gathering when the counts alone say the batch is wrong.
std::vector<std::int64_t> DistributedIndex::gather_ids(const std::int64_t* ids, std::size_t n,
                                                       std::vector<std::uint64_t>& entry_first) {
  const std::size_t R = static_cast<std::size_t>(ranks_);
  mpi_agree(comm_, n > 0 && ids == nullptr ? "ids is null with n = " + std::to_string(n) : std::string(), kRemove);
  std::vector<std::uint64_t> counts(R, 0);
  const std::uint64_t n_local = n;
  MPI_Allgather(&n_local, 1, MPI_UINT64_T, counts.data(), 1, MPI_UINT64_T, comm_);
  entry_first.assign(R, 0);
  std::uint64_t total = 0;
  for (std::size_t r = 0; r < R; ++r) entry_first[r] = total, total += counts[r];
  // From the counts alone: the same verdict on every rank, before the gather allocates.
  if (total == 0) throw Error(kRemove + ": no ids on any rank (n = 0 everywhere)");
  const std::uint64_t issued = static_cast<std::uint64_t>(id_bound_ - id_base_);
  if (total > issued)
    throw Error(kRemove + ": " + std::to_string(total) + " ids to remove, more than the " + std::to_string(issued) +
                " ever issued: some are repeated or outside [" + std::to_string(id_base_) + ", " +
                std::to_string(id_bound_) + ")");
  if (total > static_cast<std::uint64_t>(std::numeric_limits<int>::max()))
    throw Error(kRemove + ": " + std::to_string(total) + " ids in one call, more than one MPI call carries "
                "(2^31 - 1): remove them in parts");
  std::vector<int> rc(R), displ(R);
  for (std::size_t r = 0; r < R; ++r) rc[r] = static_cast<int>(counts[r]), displ[r] = static_cast<int>(entry_first[r]);
  std::vector<std::int64_t> all(static_cast<std::size_t>(total));
  MPI_Allgatherv(ids, static_cast<int>(n), MPI_INT64_T, all.data(), rc.data(), displ.data(), MPI_INT64_T, comm_);
  return all;
}

// Index::remove's checks over the whole batch, in its order (range, already removed, repeated,
// every point), each decided from what every rank holds alike. Returns this rank's local ids to
// remove, ascending.
std::vector<std::int32_t> DistributedIndex::check_remove(const std::vector<std::int64_t>& all,
                                                         const std::vector<std::uint64_t>& entry_first) {
  const std::size_t T = all.size();
  for (std::size_t e = 0; e < T; ++e)
    if (all[e] < id_base_ || all[e] >= id_bound_)
      throw Error(kRemove + ": " + entry_name(all[e], e, entry_first) + " is outside the issued ids [" +
                  std::to_string(id_base_) + ", " + std::to_string(id_bound_) + ")");
  // Each id's status from the rank holding it (1 live, 2 removed; 0 nowhere: spent by a failed
  // insert), agreed by a maximum over the ranks.
  std::vector<unsigned char> status(T, 0), agreed(T, 0);
  std::vector<std::int32_t> local;
  for (std::size_t e = 0; e < T; ++e) {
    const auto it = std::lower_bound(shard_ids_.begin(), shard_ids_.end(), all[e]);
    if (it == shard_ids_.end() || *it != all[e]) continue;
    const std::size_t l = static_cast<std::size_t>(it - shard_ids_.begin());
    status[e] = shard_removed_[l] ? 2 : 1;
    if (!shard_removed_[l]) local.push_back(static_cast<std::int32_t>(l));
  }
  MPI_Allreduce(status.data(), agreed.data(), static_cast<int>(T), MPI_UNSIGNED_CHAR, MPI_MAX, comm_);
  for (std::size_t e = 0; e < T; ++e)
    if (agreed[e] != 1)
      throw Error(kRemove + ": " + entry_name(all[e], e, entry_first) +
                  (agreed[e] == 2 ? " was already removed" : " was never given to a point (spent by a failed insert)"));
  // Repeats: the smallest repeated id, named by its first two entries (Index::remove's report).
  std::vector<std::int64_t> sorted(all);
  std::sort(sorted.begin(), sorted.end());
  for (std::size_t i = 1; i < T; ++i)
    if (sorted[i] == sorted[i - 1]) {
      const std::int64_t id = sorted[i];
      const std::size_t a = static_cast<std::size_t>(std::find(all.begin(), all.end(), id) - all.begin());
      const std::size_t b = static_cast<std::size_t>(std::find(all.begin() + a + 1, all.end(), id) - all.begin());
      throw Error(kRemove + ": " + entry_name(id, a, entry_first) + " appears twice (again as " +
                  entry_name(id, b, entry_first) + ")");
    }
  if (T >= n_global_)
    throw Error(kRemove + ": removing all " + std::to_string(n_global_) +
                " live points would leave the index empty (an index holds at least one point)");
  std::sort(local.begin(), local.end());
  return local;
}

// The local ids out of the local index (a shard losing its last points drops its index and
// leaves the routing), agreed: a failure here cannot be undone on the ranks that removed.
void DistributedIndex::remove_locally(const std::vector<std::int32_t>& local_ids) {
  const std::size_t m = local_ids.size();
  std::string err;
  try {
    if (m > 0 && m == shard_live_)
      local_.reset();
    else if (m > 0)
      local_->remove(local_ids.data(), m);
  } catch (const std::exception& e) {
    err = "removing " + std::to_string(m) + " points from the local " + method_ + " index: " + what_of(e);
  }
  try {
    mpi_agree(comm_, err, kRemove);
  } catch (const Error& e) {
    throw Error(std::string(e.what()) + " (the other ranks removed their points: rebuild the index)");
  }
  for (std::int32_t l : local_ids) shard_removed_[static_cast<std::size_t>(l)] = true;
  shard_live_ -= m;
}

// The boxes of the sub-runs that lost points, recomputed over their live points (one pass over
// the shard's copy of its points), so that the routing stops sending queries to emptied space.
void DistributedIndex::shrink_boxes(const std::vector<std::int32_t>& local_ids) {
  if (local_ids.empty()) return;
  std::vector<bool> touched(my_boxes_.size(), false);
  for (std::int32_t l : local_ids) touched[shard_run_[static_cast<std::size_t>(l)]] = true;
  for (std::size_t j = 0; j < my_boxes_.size(); ++j)
    if (touched[j]) my_boxes_[j] = empty_box();
  for (std::size_t l = 0; l < shard_ids_.size(); ++l)
    if (!shard_removed_[l] && touched[shard_run_[l]]) grow(my_boxes_[shard_run_[l]], &shard_xyz_[3 * l]);
}

void DistributedIndex::remove(const std::int64_t* ids, std::size_t n, DistributedUpdateStats* stats) {
  Stopwatch wall;
  DistributedUpdateStats us;
  us.n_input = n;
  std::vector<std::uint64_t> entry_first;
  const std::vector<std::int64_t> all = gather_ids(ids, n, entry_first);
  const std::vector<std::int32_t> local_ids = check_remove(all, entry_first);
  us.n_global = all.size();
  us.applied = local_ids.size();
  // The ids of this rank's input held elsewhere (every rank received every id in the gather).
  us.sent = n - static_cast<std::size_t>(std::count_if(ids, ids + n, [&](std::int64_t id) {
              return std::binary_search(shard_ids_.begin(), shard_ids_.end(), id);
            }));
  us.bytes_sent = n * sizeof(std::int64_t) * static_cast<std::size_t>(ranks_ - 1);
  us.bytes_received = (all.size() - n) * sizeof(std::int64_t);
  us.route_s = wall.seconds();
  timed_stages(us, [&] { remove_locally(local_ids); }, [&] {
    shrink_boxes(local_ids);
    publish_boxes();
  });
  n_global_ -= all.size();
  removed_n_ += all.size();
  us.wall_s = wall.seconds();
  if (stats) *stats = us;
}

}  // namespace bhcl
