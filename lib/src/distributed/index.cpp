// DistributedIndex: the build (keys, splitters, the exchange of points, the local index and the
// shared boxes) and the two-phase kNN query (owner, then the ranks the ball meets, then the
// merge). Radius search: radius.cpp.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <numeric>
#include <sstream>

#include "blockhash_cl/distributed.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/numbers.hpp"
#include "distributed/agreement.hpp"
#include "distributed/mpi_util.hpp"
#include "distributed/shard.hpp"
#include "distributed/wire.hpp"

namespace bhcl {

using distributed::Composite;
using distributed::exchange;
using distributed::Stopwatch;
using namespace distributed::wire;

namespace {

// A result row on the wire: k global ids (int64), k squared distances, the count and the points
// examined.
std::size_t row_bytes(int k) { return static_cast<std::size_t>(k) * 12 + 8; }

// Row q of a local answer (local ids) packed with the shard's global ids.
void pack_row(unsigned char* dst, const KnnResult& r, std::size_t q, int k, const std::vector<std::int64_t>& global) {
  const std::size_t kk = static_cast<std::size_t>(k);
  for (std::size_t j = 0; j < kk; ++j) {
    const std::int32_t id = r.ids[q * kk + j];
    const std::int64_t g = id >= 0 ? global[static_cast<std::size_t>(id)] : -1;
    std::memcpy(dst + 8 * j, &g, 8);
  }
  std::memcpy(dst + kk * 8, &r.dist2[q * kk], kk * 4);
  const std::int32_t tail[2] = {r.counts[q], r.examined.empty() ? 0 : r.examined[q]};
  std::memcpy(dst + kk * 12, tail, 8);
}

// Merges the row `src` (on the wire) into row q of `out` (both sorted by (distance, id)): the k
// best of both. An id in both (the owner's second answer repeats points of its first) is the same
// point with the same distance and is taken once. The order of merging does not matter: (distance,
// id) is a total order.
void merge_row(KnnResult64& out, std::size_t q, const unsigned char* src, int k,
               std::vector<std::int64_t>& ids_tmp, std::vector<float>& d2_tmp) {
  const std::size_t kk = static_cast<std::size_t>(k);
  std::int32_t tail[2];
  std::memcpy(tail, src + kk * 12, 8);
  const int cb = tail[0];
  if (!out.examined.empty()) out.examined[q] += tail[1];
  if (cb <= 0) return;
  std::int64_t* ia = &out.ids[q * kk];
  float* da = &out.dist2[q * kk];
  const int ca = out.counts[q];
  ids_tmp.resize(kk);
  d2_tmp.resize(kk);
  std::memcpy(ids_tmp.data(), src, kk * 8);
  std::memcpy(d2_tmp.data(), src + kk * 8, kk * 4);
  std::vector<std::int64_t> mi(kk, -1);
  std::vector<float> md(kk, std::numeric_limits<float>::infinity());
  int a = 0, b = 0, m = 0;
  while (m < k && (a < ca || b < cb)) {
    if (a < ca && b < cb && ia[a] == ids_tmp[b]) ++b;  // the same point: keep a's copy
    const bool take_a =
        b >= cb || (a < ca && (da[a] < d2_tmp[b] || (da[a] == d2_tmp[b] && ia[a] < ids_tmp[b])));
    if (take_a) mi[m] = ia[a], md[m] = da[a], ++a;
    else mi[m] = ids_tmp[b], md[m] = d2_tmp[b], ++b;
    ++m;
  }
  std::copy(mi.begin(), mi.end(), ia);
  std::copy(md.begin(), md.end(), da);
  out.counts[q] = m;
}

// The owner's rows (`back`, on the wire, in the order of `routes`) as each query's first row.
void take_owner_rows(KnnResult64& out, const std::vector<Route>& routes, const std::vector<unsigned char>& back,
                     int k, bool count_examined) {
  const std::size_t kk = static_cast<std::size_t>(k), rb = row_bytes(k);
  for (std::size_t j = 0; j < routes.size(); ++j) {
    const std::size_t i = routes[j].query;
    const unsigned char* src = &back[j * rb];
    std::memcpy(&out.ids[i * kk], src, kk * 8);
    std::memcpy(&out.dist2[i * kk], src + kk * 8, kk * 4);
    std::int32_t tail[2];
    std::memcpy(tail, src + kk * 12, 8);
    out.counts[i] = tail[0];
    if (count_examined) out.examined[i] = tail[1];
  }
}

// What the round trips of one kNN call share on this rank.
struct KnnCall {
  MPI_Comm comm;
  std::size_t me;
  const Index* local;                          // this rank's index, nullptr for an empty shard
  const std::vector<std::int64_t>& shard_ids;  // its global ids
  const SearchParams& params;
  float border_A;  // approximate methods: the budget of a border query's second answer
  QueryStats& st;
  DistributedQueryStats& ds;
};

// The local index's rows for the records that came in (a record's budget class 1: with A =
// border_A), on the wire in the records' order.
std::vector<unsigned char> answer_locally(KnnCall& c, const std::vector<QueryRecord>& got) {
  const int k = c.params.k;
  const std::size_t m = got.size(), rb = row_bytes(k);
  std::vector<unsigned char> rows(m * rb, 0);
  if (m > 0 && !c.local) throw Error("queries reached a rank with an empty shard");
  for (std::int32_t cls : {0, 1}) {
    std::vector<std::size_t> which;
    for (std::size_t i = 0; i < m; ++i)
      if (got[i].budget_class == cls) which.push_back(i);
    if (which.empty()) continue;
    std::vector<float> xyz(3 * which.size());
    for (std::size_t j = 0; j < which.size(); ++j) std::memcpy(&xyz[3 * j], got[which[j]].xyz, 12);
    SearchParams p = c.params;
    if (cls == 1) p.A = c.border_A, p.recall_target = 0;
    KnnResult r;
    add_stats(c.st, c.local->query(xyz.data(), which.size(), p, r));
    for (std::size_t j = 0; j < which.size(); ++j) pack_row(&rows[which[j] * rb], r, j, k, c.shard_ids);
  }
  return rows;
}

// The rows of one round trip, in the order the records were sent, and the records that crossed
// ranks (sent to others, received from others).
struct Rows {
  std::vector<unsigned char> bytes;
  std::size_t sent = 0, received = 0;
};

// Sends the records, answers the ones that came in with the local index and sends the rows back.
// Local failures fail every rank.
Rows round_trip(KnnCall& c, const Outbox& box, const char* phase) {
  const std::size_t rb = row_bytes(c.params.k);
  std::vector<std::size_t> recv_counts, back_counts;
  const std::vector<unsigned char> in =
      exchange(c.comm, box.records.data(), box.send_counts, sizeof(QueryRecord), recv_counts, phase);
  const std::size_t m = in.size() / sizeof(QueryRecord);
  std::vector<QueryRecord> got(m);
  if (m) std::memcpy(got.data(), in.data(), in.size());
  std::vector<unsigned char> rows;
  std::string e;
  try {
    rows = answer_locally(c, got);
  } catch (const std::exception& ex) {
    e = std::string(phase) + ": " + what_of(ex);
  }
  mpi_agree(c.comm, e, std::string(kWhat) + "::query");
  c.ds.answered += m;
  Rows back;
  back.sent = to_others(box.send_counts, c.me);
  back.received = to_others(recv_counts, c.me);
  back.bytes = exchange(c.comm, rows.data(), recv_counts, rb, back_counts, phase);
  c.ds.bytes_sent += back.sent * sizeof(QueryRecord) + back.received * rb;
  c.ds.bytes_received += back.received * sizeof(QueryRecord) + back.sent * rb;
  return back;
}

// The cell side a grid build reports (block hashing's build_used "cell_size", written with 17
// digits: it reads back exactly), 0 for an index that reports none.
double reported_cell_side(const Index* index) {
  if (!index) return 0;
  for (const auto& [name, value] : index->build_used())
    if (name == "cell_size") {
      double v = 0;
      return detail::parse_double(value, v) == detail::NumberParse::Ok ? v : 0.0;
    }
  return 0;
}

// The largest extent over the three axes of the points xyz (0 for none).
double largest_extent(const std::vector<float>& xyz) {
  const std::size_t m = xyz.size() / 3;
  double extent = 0;
  for (int d = 0; d < 3 && m > 0; ++d) {
    float lo = xyz[static_cast<std::size_t>(d)], hi = lo;
    for (std::size_t i = 0; i < m; ++i) {
      lo = std::min(lo, xyz[3 * i + d]);
      hi = std::max(hi, xyz[3 * i + d]);
    }
    extent = std::max(extent, double(hi) - double(lo));
  }
  return extent;
}

// Parameters: checked on every rank, agreed, so that a rank with other parameters fails all.
// Returns the method's description.
const MethodInfo& check_build_params(MPI_Comm comm, const Runtime* runtime, const float* points, std::size_t n,
                                     const DistributedBuildParams& params) {
  std::string err;
  const MethodInfo* info = nullptr;
  try {
    info = &method_info(params.method);
    if (!params.options.load_index().empty() || !params.options.save_index().empty())
      throw Error("load_index / save_index are not supported: each rank builds its shard's index");
    if (!(params.border_factor >= 1 && params.border_factor <= 1024))
      throw Error("border_factor must be in [1, 1024], got " + std::to_string(params.border_factor));
    if (params.boxes_per_rank < 1 || params.boxes_per_rank > 1024)
      throw Error("boxes_per_rank must be in [1, 1024], got " + std::to_string(params.boxes_per_rank));
    if (n > 0 && points == nullptr) throw Error("points is null with n = " + std::to_string(n));
    if (!runtime) throw Error("runtime is null");
    if (std::isnan(params.deadline_s) || std::isinf(params.deadline_s))
      throw Error("deadline_s must be finite (0: no deadline, negative: BHCL_MPI_DEADLINE_S), got " +
                  std::to_string(params.deadline_s));
    if (params.deadline_s < 0)
      if (const std::string e = distributed::deadline_env_error(); !e.empty()) throw Error(e);
    if (params.id_base < 0 || params.id_base > (std::int64_t(1) << 62))
      throw Error("id_base must be in [0, 2^62], got " + std::to_string(params.id_base));
  } catch (const std::exception& e) {
    err = what_of(e);
  }
  mpi_agree(comm, err, kWhat);
  distributed::agree_parameters(comm, distributed::build_parameters(params), kWhat);
  return *info;  // set: a rank whose method_info threw failed mpi_agree
}

// This rank's points as records in the order of `sorted` (its composites, ascending), cut into
// runs by the splitters: send_counts[r] of them for rank r's shard.
std::vector<PointRecord> records_by_shard(const std::vector<Composite>& sorted, const std::vector<Composite>& split,
                                          const float* points, std::uint64_t offset,
                                          std::vector<std::size_t>& send_counts) {
  const std::size_t R = split.size(), n = sorted.size();
  send_counts.assign(R, 0);
  std::vector<PointRecord> out(n);
  std::size_t pos = 0;
  for (std::size_t r = 0; r < R; ++r) {
    const std::size_t end =
        r + 1 < R ? static_cast<std::size_t>(std::lower_bound(sorted.begin(), sorted.end(), split[r + 1]) -
                                             sorted.begin())
                  : n;
    send_counts[r] = end - pos;
    for (; pos < end; ++pos) {
      const std::uint64_t g = distributed::position_of(sorted[pos]);
      const float* p = points + 3 * (g - offset);
      out[pos] = {{p[0], p[1], p[2]}, 0, g};
    }
  }
  return out;
}

}  // namespace

// This rank's shard after the exchange: its points, each with its place over all ranks (its
// global id less id_base), in the order they came in.
struct DistributedIndex::Shard {
  std::vector<PointRecord> points;
};

DistributedIndex::DistributedIndex(MPI_Comm comm, std::shared_ptr<Runtime> runtime, const float* points,
                                   std::size_t n, const DistributedBuildParams& params) {
  Stopwatch wall;
  MPI_Comm_dup(comm, &comm_);
  if (params.deadline_s >= 0 && std::isfinite(params.deadline_s)) distributed::set_deadline(comm_, params.deadline_s);
  try {
    MPI_Comm_rank(comm_, &rank_);
    MPI_Comm_size(comm_, &ranks_);
    const MethodInfo& info = check_build_params(comm_, runtime.get(), points, n, params);
    method_ = info.name;
    exact_ = info.exact;
    border_factor_ = params.border_factor;
    boxes_per_rank_ = params.boxes_per_rank;
    id_base_ = params.id_base;
    const std::uint64_t offset = number_points(points, n);
    id_bound_ = id_base_ + static_cast<std::int64_t>(n_global_);

    Stopwatch shard_clock;
    Shard shard = shard_points(points, n, offset);
    share_boxes(shard, params.boxes_per_rank);
    build_stats_.shard_s = shard_clock.seconds();

    std::vector<float> xyz = global_order(std::move(shard));
    Stopwatch build_clock;
    build_local(runtime, xyz, params.options);
    agree_global_cell_side(runtime, xyz, params.options);
    build_stats_.build_s = build_clock.seconds();
    shard_xyz_ = std::move(xyz);  // kept: a remove recomputes the boxes of the live points
    build_stats_.wall_s = wall.seconds();
  } catch (...) {
    local_.reset();
    MPI_Comm_free(&comm_);
    throw;
  }
}

// Global indices: this rank's part follows the parts of lower ranks. Sets n_global_ and returns
// this rank's offset; throws on every rank for no points, too many, or a NaN/Inf point.
std::uint64_t DistributedIndex::number_points(const float* points, std::size_t n) {
  const std::size_t R = static_cast<std::size_t>(ranks_);
  std::uint64_t n_local = n, offset = 0, total = 0;
  MPI_Exscan(&n_local, &offset, 1, MPI_UINT64_T, MPI_SUM, comm_);
  if (rank_ == 0) offset = 0;  // MPI leaves rank 0's result undefined
  MPI_Allreduce(&n_local, &total, 1, MPI_UINT64_T, MPI_SUM, comm_);
  // The same totals on every rank, so every rank throws here or none does.
  if (total == 0) throw Error(std::string(kWhat) + ": no points on any rank");
  // Global ids are int64; a shard is one local index, whose ids are int32 (2^31 - 2 points).
  if (total > distributed::kMaxPoints)
    throw Error(std::string(kWhat) + ": " + std::to_string(total) + " points in all: at most 2^40 - 1");
  if (const std::uint64_t largest = (total + R - 1) / R; largest > 0x7ffffffeu)
    throw Error(std::string(kWhat) + ": " + std::to_string(total) + " points over " + std::to_string(R) +
                " ranks make shards of up to " + std::to_string(largest) +
                " points, past one index's int32 id range (2^31 - 2 points): use at least " +
                std::to_string((total + 0x7ffffffdu) / 0x7ffffffeu) + " ranks");
  n_global_ = static_cast<std::size_t>(total);
  mpi_agree(comm_, distributed::nonfinite_point(points, n, id_base_ + static_cast<std::int64_t>(offset), "points"),
            kWhat);
  return offset;
}

// Keys over the global box; the global order is by (key, global index), cut by the splitters into
// the ranks' shards, each point sent to its own.
DistributedIndex::Shard DistributedIndex::shard_points(const float* points, std::size_t n, std::uint64_t offset) {
  const std::size_t R = static_cast<std::size_t>(ranks_);
  const std::size_t me = static_cast<std::size_t>(rank_);
  const std::uint64_t total = n_global_;
  const blockhash::Quantiser q = distributed::global_quantiser(comm_, points, n);
  for (int d = 0; d < 3; ++d) origin_[d] = q.origin[d];
  scale_ = q.scale;
  std::vector<Composite> sorted(n);
  for (std::size_t i = 0; i < n; ++i)
    sorted[i] = distributed::composite(distributed::hilbert_key(q, points + 3 * i), offset + i);
  std::sort(sorted.begin(), sorted.end());
  const std::vector<Composite> split = distributed::find_splitters(comm_, sorted, total);

  // Every rank derives every shard's size and first key from the splitters alone.
  shard_sizes_.resize(R);
  first_keys_.resize(R);
  for (std::size_t r = 0; r < R; ++r) {
    shard_sizes_[r] = (total * (r + 1)) / R - (total * r) / R;
    first_keys_[r] = distributed::key_of(split[r]);
    if (shard_sizes_[r] > 0) nonempty_.push_back(static_cast<int>(r));
  }

  // Send each point to the shard holding its composite: runs of the sorted local array.
  std::vector<std::size_t> send_counts, recv_counts;
  std::vector<PointRecord> out_points = records_by_shard(sorted, split, points, offset, send_counts);
  std::vector<Composite>().swap(sorted);
  std::vector<unsigned char> raw = exchange(comm_, out_points.data(), send_counts,
                                            sizeof(PointRecord), recv_counts, "sharding the points");
  std::vector<PointRecord>().swap(out_points);
  const std::size_t m = raw.size() / sizeof(PointRecord);
  Shard shard;
  shard.points.resize(m);
  if (m) std::memcpy(shard.points.data(), raw.data(), raw.size());
  std::vector<unsigned char>().swap(raw);
  // The splitters promised this size; a mismatch is a bug here, reported rather than hung on.
  std::string err;
  if (m != shard_sizes_[me])
    err = "internal error: the shard holds " + std::to_string(m) + " points, the splitters promised " +
          std::to_string(shard_sizes_[me]);
  mpi_agree(comm_, err, kWhat);
  build_stats_.n_global = n_global_;
  build_stats_.n_input = n;
  build_stats_.shard_points = m;
  build_stats_.points_sent = n - send_counts[me];
  build_stats_.points_received = m - recv_counts[me];
  build_stats_.shard_points_all.assign(shard_sizes_.begin(), shard_sizes_.end());
  const double mean = double(total) / double(R);
  build_stats_.balance = double(*std::max_element(shard_sizes_.begin(), shard_sizes_.end())) / mean;
  return shard;
}

// The shared boxes: consecutive runs of the shard in Hilbert order (the key order the ranks cut
// by, so the runs are compact pieces of the curve). Each point's run is kept in its record's pad
// (global_order keeps it per local id: a remove recomputes the boxes of the runs it touched),
// and each run's first key (an inserted point joins the run its key falls in).
void DistributedIndex::share_boxes(Shard& shard, int boxes_per_rank) {
  const std::size_t m = shard.points.size();
  std::vector<float> xyz(3 * m);
  std::vector<std::pair<Composite, std::size_t>> order(m);
  for (std::size_t i = 0; i < m; ++i)
    order[i] = {distributed::composite(key_of(shard.points[i].xyz), shard.points[i].position), i};
  std::sort(order.begin(), order.end());
  for (std::size_t i = 0; i < m; ++i) std::memcpy(&xyz[3 * i], shard.points[order[i].second].xyz, 12);
  const std::size_t B = static_cast<std::size_t>(boxes_per_rank);
  my_boxes_ = distributed::run_boxes(xyz.data(), m, B);
  const std::size_t runs = my_boxes_.size();
  run_first_keys_.assign(runs, 0);
  for (std::size_t j = 0; j < runs; ++j) {
    const std::size_t first = j * m / runs, end = (j + 1) * m / runs;
    run_first_keys_[j] = distributed::key_of(order[first].first);
    for (std::size_t i = first; i < end; ++i) shard.points[order[i].second].pad = static_cast<std::uint32_t>(j);
  }
  shard_live_ = m;
  publish_boxes();
}

void DistributedIndex::publish_boxes() {
  const std::size_t R = static_cast<std::size_t>(ranks_);
  const std::size_t B = static_cast<std::size_t>(boxes_per_rank_);
  // Fixed B slots per rank: a run's box (empty, lo > hi, when its points are all removed), NaN
  // for the slots past the rank's runs (fewer points than B).
  std::vector<float> slots(B * 6, std::numeric_limits<float>::quiet_NaN()), all(R * B * 6);
  for (std::size_t j = 0; j < my_boxes_.size(); ++j) {
    std::memcpy(&slots[6 * j], my_boxes_[j].lo, 12);
    std::memcpy(&slots[6 * j + 3], my_boxes_[j].hi, 12);
  }
  MPI_Allgather(slots.data(), static_cast<int>(B * 6), MPI_FLOAT, all.data(), static_cast<int>(B * 6), MPI_FLOAT,
                comm_);
  const std::uint64_t live = shard_live_;
  shard_sizes_.assign(R, 0);
  MPI_Allgather(&live, 1, MPI_UINT64_T, shard_sizes_.data(), 1, MPI_UINT64_T, comm_);
  boxes_.assign(R, {});
  rank_box_.resize(R);
  nonempty_.clear();
  for (std::size_t r = 0; r < R; ++r) {
    if (shard_sizes_[r] > 0) nonempty_.push_back(static_cast<int>(r));
    for (std::size_t j = 0; j < B; ++j) {
      ShardBox b;
      std::memcpy(b.lo, &all[(r * B + j) * 6], 12);
      std::memcpy(b.hi, &all[(r * B + j) * 6 + 3], 12);
      // NaN: no run; lo > hi: a run with no live point. Neither can hold a point.
      if (std::isnan(b.lo[0]) || b.lo[0] > b.hi[0]) continue;
      boxes_[r].push_back(b);
    }
    rank_box_[r] = distributed::union_box(boxes_[r]);
  }
}

// The shard in global-index order, the order of the local index: a row's ties then go to the
// lower local index, which is the lower global index, as in one process. Sets shard_ids_ and
// returns the points in that order.
std::vector<float> DistributedIndex::global_order(Shard shard) {
  std::vector<PointRecord>& points = shard.points;
  const std::size_t m = points.size();
  std::sort(points.begin(), points.end(),
            [](const PointRecord& a, const PointRecord& b) { return a.position < b.position; });
  std::vector<float> xyz(3 * m);
  shard_ids_.resize(m);
  shard_run_.resize(m);
  shard_removed_.assign(m, false);
  for (std::size_t i = 0; i < m; ++i) {
    shard_ids_[i] = id_base_ + static_cast<std::int64_t>(points[i].position);
    shard_run_[i] = static_cast<std::uint16_t>(points[i].pad);
    std::memcpy(&xyz[3 * i], points[i].xyz, 12);
  }
  return xyz;
}

void DistributedIndex::build_local(const std::shared_ptr<Runtime>& runtime, const std::vector<float>& xyz,
                                   const MethodOptions& options) {
  const std::size_t m = xyz.size() / 3;
  std::string err;
  try {
    if (m > 0) local_ = make_index(method_, runtime, xyz.data(), m, options);
  } catch (const std::exception& e) {
    err = "building the local " + method_ + " index of " + std::to_string(m) + " points: " + what_of(e);
  }
  mpi_agree(comm_, err, kWhat);
}

// Block hashing's grid: the cell side one process would choose for ALL the points, not each
// shard's own. The grid picks its side h so that the point-weighted mean population of a
// point's cell is target_cell_points: a shard of density rho_r picks h_r with h_r^3 rho_r =
// target, one process over every shard h = (sum_r w_r h_r^-3)^(-1/3), w_r the shard's share
// of the points. Each shard is rebuilt with that side (a grid build is a fraction of the
// sharding's cost), so that a budget A means on every shard what it means in one process.
// Not done when the caller set cell-size, or where a shard's extent is outside
// [2^-40, 2^40] (its index coordinates are then rescaled, knn.hpp, and sides do not compare).
void DistributedIndex::agree_global_cell_side(const std::shared_ptr<Runtime>& runtime, const std::vector<float>& xyz,
                                              const MethodOptions& options) {
  if (options.has("cell-size")) return;
  const std::size_t m = xyz.size() / 3;
  const double side = reported_cell_side(local_.get());
  const double extent = largest_extent(xyz);
  const bool comparable = extent == 0 || (extent >= std::ldexp(1.0, -40) && extent <= std::ldexp(1.0, 40));
  double mine[3] = {0, 0, 0}, sum[3] = {0, 0, 0};  // sum of m h^-3, of m, shards that cannot join
  if (side > 0 && comparable)
    mine[0] = double(m) / std::pow(side, 3.0), mine[1] = double(m);
  else if (m > 0)
    mine[2] = 1;
  MPI_Allreduce(mine, sum, 3, MPI_DOUBLE, MPI_SUM, comm_);
  if (sum[2] != 0 || !(sum[0] > 0)) return;
  const double h = std::cbrt(sum[1] / sum[0]);
  std::string err;
  try {
    if (m > 0 && std::fabs(h / side - 1.0) > 1e-9) {
      MethodOptions o = options;
      o.set("cell-size", detail::format_general(h, 17));
      local_ = make_index(method_, runtime, xyz.data(), m, o);
    }
  } catch (const std::exception& e) {
    err = "rebuilding the local blockhash index with the global cell side " + std::to_string(h) + ": " + what_of(e);
  }
  mpi_agree(comm_, err, kWhat);
}

DistributedIndex::~DistributedIndex() {
  int finalized = 0;
  MPI_Finalized(&finalized);
  if (!finalized && comm_ != MPI_COMM_NULL) MPI_Comm_free(&comm_);
}

std::uint64_t DistributedIndex::key_of(const float xyz[3]) const {
  blockhash::Quantiser q;
  q.bits = distributed::kKeyBits;
  for (int d = 0; d < 3; ++d) q.origin[d] = origin_[d];
  q.scale = scale_;
  return distributed::hilbert_key(q, xyz);
}

int DistributedIndex::owner_of(const float xyz[3]) const { return owner_of_key(key_of(xyz)); }

int DistributedIndex::owner_of_key(std::uint64_t key) const {
  // The last non-empty shard starting at or before the key (a key shared by two shards goes to
  // the later one, which holds points of that key); keys before every shard go to the first.
  // A shard emptied by removes is skipped: its range falls to the previous non-empty shard.
  int owner = nonempty_.front();
  for (int r : nonempty_)
    if (first_keys_[static_cast<std::size_t>(r)] <= key) owner = r;
  return owner;
}

void DistributedIndex::route_to_owners(const float* queries, std::size_t n, QueryStats& st,
                                       DistributedQueryStats& ds) const {
  ds.ranks_visited.assign(n, 0);
  ds.owner.assign(n, -1);
  for (std::size_t i = 0; i < n; ++i) {
    const float* q = queries + 3 * i;
    if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) {
      ++st.nonfinite_queries;
      continue;
    }
    ds.owner[i] = owner_of(q);
    ds.ranks_visited[i] = 1;
  }
}

void DistributedIndex::ranks_meeting(const float q[3], double bound, int skip, std::vector<int>& out) const {
  out.clear();
  for (int r : nonempty_) {
    if (r == skip) continue;
    const std::size_t rr = static_cast<std::size_t>(r);
    if (!distributed::box_may_hold(rank_box_[rr], q, bound)) continue;
    for (const ShardBox& b : boxes_[rr])
      if (distributed::box_may_hold(b, q, bound)) {
        out.push_back(r);
        break;
      }
  }
}

void DistributedIndex::require_int32_ids(const char* call) const {
  // id_bound() is the same on every rank: every rank throws here or none does.
  if (!ids_fit_int32())
    throw Error(std::string(kWhat) + "::" + call + ": the global ids reach " + std::to_string(id_bound() - 1) +
                " (id_base " + std::to_string(id_base_) + " + " + std::to_string(id_bound_ - id_base_) +
                " ids issued), past int32: pass a " + (call[0] == 'q' ? "KnnResult64" : "RadiusResult64") +
                " (int64 ids)");
}

QueryStats DistributedIndex::query(const float* queries, std::size_t n, const SearchParams& params,
                                   KnnResult& out, DistributedQueryStats* stats) const {
  require_int32_ids("query");
  KnnResult64 wide;
  const QueryStats st = query(queries, n, params, wide, stats);
  out.n = wide.n;
  out.k = wide.k;
  out.ids.assign(wide.ids.begin(), wide.ids.end());  // every id fits: checked above
  out.dist2 = std::move(wide.dist2);
  out.counts = std::move(wide.counts);
  out.examined = std::move(wide.examined);
  return st;
}

// Checks the call's parameters on every rank and agrees them. Returns the budget of a border
// query's second answer (approximate methods; 0: none).
float DistributedIndex::check_knn_params(const float* queries, std::size_t n, const SearchParams& params) const {
  std::string err;
  float border_A = 0;
  try {
    kmax_variant(params.k);
    if (std::isnan(params.max_radius) || params.max_radius < 0)
      throw Error("max_radius must be >= 0 (or +inf), got " + std::to_string(params.max_radius));
    if (n > 0 && queries == nullptr) throw Error("queries is null with n = " + std::to_string(n));
    if (params.count_examined && local_ && !local_->counts_examined())
      throw Error("count_examined: method " + method_ + " does not count the points it examines");
    if (!exact_ && border_factor_ > 1 && local_) {
      // The A this rank's index answers with (the tuned one under a recall target), scaled.
      float A = params.A;
      if (const auto t = local_->recall_tuning(params)) A = t->A;
      border_A = A * border_factor_;
    }
  } catch (const std::exception& e) {
    err = what_of(e);
  }
  mpi_agree(comm_, err, std::string(kWhat) + "::query");
  // Every search parameter as rank 0's (k, the radius and count_examined shape the rows every
  // rank sends; the others what each rank's rows mean).
  distributed::agree_parameters(comm_, distributed::search_parameters(params), std::string(kWhat) + "::query");
  return border_A;
}

QueryStats DistributedIndex::query(const float* queries, std::size_t n, const SearchParams& params,
                                   KnnResult64& out, DistributedQueryStats* stats) const {
  Stopwatch wall;
  QueryStats st;
  st.n_queries = n;
  DistributedQueryStats ds;
  const std::size_t R = static_cast<std::size_t>(ranks_);
  const float border_A = check_knn_params(queries, n, params);
  KnnCall call{comm_, static_cast<std::size_t>(rank_), local_.get(), shard_ids_, params, border_A, st, ds};
  const int k = params.k;
  const std::size_t kk = static_cast<std::size_t>(k);
  out.resize(n, k);
  if (params.count_examined) out.examined.assign(n, 0);

  // Phase 1: every finite query to the rank owning its key.
  Stopwatch p1;
  route_to_owners(queries, n, st, ds);
  std::vector<Route> routes;
  for (std::size_t i = 0; i < n; ++i)
    if (ds.owner[i] >= 0) routes.push_back({ds.owner[i], 0, i});
  {
    const Rows back = round_trip(call, group_by_rank(routes, queries, R), "phase 1 (owner)");
    ds.owner_sent = back.sent;
    ds.owner_received = back.received;
    take_owner_rows(out, routes, back.bytes, k, params.count_examined);
  }
  ds.phase1_s = p1.seconds();

  // Phase 2: the ball of the owner's k-th distance (or of the radius, when the owner found fewer
  // than k) to every other rank whose boxes it meets. Approximate methods: such a border query
  // also goes back to its owner for a second answer with border_A (see distributed.hpp).
  Stopwatch p2;
  const double radius2 = std::isinf(params.max_radius)
                             ? std::numeric_limits<double>::infinity()
                             : double(params.max_radius) * double(params.max_radius);
  routes.clear();
  std::vector<int> met;
  for (std::size_t i = 0; i < n; ++i) {
    if (ds.owner[i] < 0) continue;
    const double bound = out.counts[i] >= k ? double(out.dist2[i * kk + kk - 1]) : radius2;
    ranks_meeting(queries + 3 * i, bound, ds.owner[i], met);
    if (met.empty()) continue;
    for (int r : met) routes.push_back({r, 0, i});
    if (border_A > 0) {
      routes.push_back({ds.owner[i], 1, i});
      ++ds.reanswered;
    }
    ds.ranks_visited[i] += static_cast<std::int32_t>(met.size());
    ++ds.multi_rank_queries;
  }
  {
    const Rows back = round_trip(call, group_by_rank(routes, queries, R), "phase 2 (ball)");
    ds.extra_sent = back.sent;
    ds.extra_received = back.received;
    const std::size_t rb = row_bytes(k);
    std::vector<std::int64_t> ids_tmp;
    std::vector<float> d2_tmp;
    for (std::size_t j = 0; j < routes.size(); ++j)
      merge_row(out, routes[j].query, &back.bytes[j * rb], k, ids_tmp, d2_tmp);
  }
  ds.phase2_s = p2.seconds();
  st.wall_s = wall.seconds();
  if (stats) *stats = std::move(ds);
  return st;
}

}  // namespace bhcl
