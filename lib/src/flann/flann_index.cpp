// FLANN as an exact host baseline, mapped to the result contract (see flann_index.hpp).
#include "blockhash_cl/flann_index.hpp"

#include <flann/flann.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <limits>
#include <mutex>
#include <thread>
#include <tuple>
#include <vector>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/reference.hpp"
#include "core/parallel.hpp"
#include "bhcl_arith.h"

#include "blockhash_cl/config.hpp"

#if !BHCL_HAVE_FLANN
#error "flann_index.cpp is compiled only with the FLANN component: see the top-level CMakeLists.txt"
#endif

namespace bhcl {
namespace {

using FlannTree = flann::KDTreeSingleIndex<flann::L2_Simple<float>>;

// The k smallest (distance, index) pairs under the contract's order, fed by FLANN's traversal.
// Coincident points: FLANN's tree holds one representative per group of identical points, and
// a representative's hit stands for its members (the caller's indices, ascending).
struct Groups {
  std::vector<std::int64_t> begin;    // unique point u's members: members[begin[u] .. begin[u+1])
  std::vector<std::int32_t> members;
  bool empty() const { return begin.empty(); }
};

// One FLANN tree over a run of the index's local point numbers [offset, offset + n): the main tree
// of the last full build, or the delta tree over the points inserted since (FLANN's
// KDTreeSingleIndex::addPoints rebuilds the whole tree on every call, so the wrapper keeps the
// new points in a tree of their own until they pass a share of the main one).
struct FlannPart {
  std::vector<float> points;  // kept for FLANN (it keeps row pointers) and for recomputing distances
  std::unique_ptr<FlannTree> tree;
  // Coincident points (a bounded-work guard): FLANN visits every point that ties the k-th
  // distance, so 2M identical points cost a full scan per query (11x brute force). When the
  // points hold duplicates the tree is built over one representative per group instead.
  std::vector<float> unique_points;
  Groups groups;
  bool recompute = false;  // FLANN's distances differ from the contract's: recompute them
  std::size_t offset = 0;
  std::size_t n() const { return points.size() / 3; }
};

class ExactResultSet : public flann::ResultSet<float> {
 public:
  // dead: a removed mark per local point number (null: none removed).
  ExactResultSet(int k, float r2, const std::uint8_t* dead) : k_(k), r2_(r2), dead_(dead) {
    d_.resize(static_cast<std::size_t>(k));
    id_.resize(static_cast<std::size_t>(k));
  }

  void reset(const float* query) {
    q_ = query;
    size_ = 0;
    worst_ = slack(r2_);
  }
  // The tree whose hits follow (the list carries over from the previous part's).
  void use(const FlannPart& p) {
    points_ = p.points.data();
    recompute_ = p.recompute;
    groups_ = p.groups.empty() ? nullptr : &p.groups;
    offset_ = static_cast<std::int32_t>(p.offset);
  }

  bool full() const override { return size_ == k_; }

  // FLANN's L2_Simple evaluates the contract's expression, ((0 + dx*dx) + dy*dy) + dz*dz with
  // d = q - p, in this file's unfused float arithmetic, so its distance is the contract's bit for
  // bit; FlannIndex checks that at build time and recomputes when it is not (`recompute`).
  // Recomputing always would cost a cache miss per accepted candidate on the caller's array.
  void addPoint(float dist, std::size_t index) override {
    if (groups_) {
      // A representative: its members share the distance; the first rejected ends the group
      // (ascending indices rank after it), so a group costs at most k + 1 insertions.
      const std::int64_t b = groups_->begin[index], e = groups_->begin[index + 1];
      const float d = recompute_ ? reference::dist2_float(points_ + 3 * std::size_t(groups_->members[b]), q_) : dist;
      for (std::int64_t j = b; j < e; ++j)
        if (!add(d, offset_ + groups_->members[static_cast<std::size_t>(j)])) break;
      return;
    }
    add(recompute_ ? reference::dist2_float(points_ + 3 * index, q_) : dist, offset_ + static_cast<std::int32_t>(index));
  }

  // Point i of the current part, its distance computed (the linear scan).
  void add_scanned(std::size_t i) { add(reference::dist2_float(points_ + 3 * i, q_), offset_ + static_cast<std::int32_t>(i)); }

  // False when the rank rejects it (a removed point is skipped, not rejected: a group goes on).
  bool add(float d, std::int32_t id) {
    if (dead_ && dead_[std::size_t(id)]) return true;
    if (!(d <= r2_)) return false;
    const auto k = static_cast<bhcl_u32>(k_);
    if (size_ == k_ && !bhcl_topk_accepts(d_.data(), id_.data(), k, d, id)) return false;
    size_ = static_cast<int>(bhcl_topk_push(d_.data(), id_.data(), k, static_cast<bhcl_u32>(size_), d, id));
    if (size_ == k_) worst_ = slack(std::min(r2_, d_[k_ - 1]));
    return true;
  }

  // FLANN prunes a cell when its (incrementally summed, rounded) lower bound exceeds this, and
  // takes a leaf point only when its distance is strictly below it. Its cell bound gathers about
  // two roundings (2^-24 relative each) per tree level; a relative margin of 2^-10 covers that
  // for trees thousands of levels deep, and the absolute one keeps ties at distance 0
  // (duplicates) in. The margin only adds work; the list itself keeps the exact k.
  float worstDist() const override { return worst_; }

  int size() const { return size_; }
  float d(int j) const { return d_[j]; }
  std::int32_t id(int j) const { return id_[j]; }

 private:
  static float slack(float b) { return b + b * (1.0f / 1024.0f) + 1e-30f; }

  const float* points_ = nullptr;
  const float* q_ = nullptr;
  int k_;
  float r2_;
  const std::uint8_t* dead_;
  bool recompute_ = false;
  const Groups* groups_ = nullptr;
  std::int32_t offset_ = 0;
  int size_ = 0;
  float worst_ = 0.0f;
  std::vector<float> d_;
  std::vector<std::int32_t> id_;
};

// Runs `work` (which grabs chunks of queries from `next` until it passes n) on `threads` host
// threads, inline for one; the first exception stops the others and is rethrown here.
template <typename Work>
void run_workers(std::size_t threads, std::atomic<std::size_t>& next, std::size_t n, Work& work) {
  // parallel.hpp: every worker joined, the first exception rethrown; a failing worker stops the others.
  detail::parallel_for(threads, [&](std::size_t, std::size_t) {
    try {
      work();
    } catch (...) {
      next = n;
      throw;
    }
  }, static_cast<unsigned>(threads), 1);
}

// Every point within r2 under the contract's distance, fed by FLANN's traversal (radius search).
class RadiusCollectSet : public flann::ResultSet<float> {
 public:
  RadiusCollectSet(float r2, const std::uint8_t* dead) : r2_(r2), worst_(r2 + r2 * (1.0f / 1024.0f) + 1e-30f), dead_(dead) {}
  void reset(const float* query) {
    q_ = query;
    found_.clear();
  }
  void use(const FlannPart& p) {
    points_ = p.points.data();
    recompute_ = p.recompute;
    groups_ = p.groups.empty() ? nullptr : &p.groups;
    offset_ = static_cast<std::int32_t>(p.offset);
  }
  bool full() const override { return true; }
  void addPoint(float dist, std::size_t index) override {
    if (groups_) {  // a representative of coincident points: every member
      const std::int64_t b = groups_->begin[index], e = groups_->begin[index + 1];
      const float d = recompute_ ? reference::dist2_float(points_ + 3 * std::size_t(groups_->members[b]), q_) : dist;
      if (d <= r2_)
        for (std::int64_t j = b; j < e; ++j) keep(d, offset_ + groups_->members[static_cast<std::size_t>(j)]);
      return;
    }
    const float d = recompute_ ? reference::dist2_float(points_ + 3 * index, q_) : dist;
    if (d <= r2_) keep(d, offset_ + static_cast<std::int32_t>(index));
  }
  // Point i of the current part (the linear scan), not a representative.
  void add_scanned(std::size_t i) {
    const float d = reference::dist2_float(points_ + 3 * i, q_);
    if (d <= r2_) keep(d, offset_ + static_cast<std::int32_t>(i));
  }
  // The same slack as ExactResultSet: FLANN's rounded cell bounds never prune a point within r2.
  float worstDist() const override { return worst_; }
  // In the parts' order (local numbers ascending within a distance only after the caller's sort).
  const std::vector<std::pair<float, std::int32_t>>& found() const { return found_; }

 private:
  void keep(float d, std::int32_t id) {
    if (!(dead_ && dead_[std::size_t(id)])) found_.emplace_back(d, id);
  }
  const float* points_ = nullptr;
  const float* q_ = nullptr;
  float r2_, worst_;
  const std::uint8_t* dead_;
  bool recompute_ = false;
  const Groups* groups_ = nullptr;
  std::int32_t offset_ = 0;
  std::vector<std::pair<float, std::int32_t>> found_;
};

// Groups identical points when there are many (a sample of 4096 points holding duplicates):
// `unique` gets one representative per group, in the order of first occurrence, and `groups` the
// members of each, ascending. Returns false (nothing filled) for point sets without duplicates
// in the sample, which are searched as they are.
bool group_coincident(const std::vector<float>& pts, std::vector<float>& unique, Groups& groups) {
  const std::size_t n = pts.size() / 3;
  if (n < 2) return false;
  auto key = [&](std::size_t i) { return std::make_tuple(pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]); };
  {
    const std::size_t step = std::max<std::size_t>(1, n / 4096);
    std::vector<std::tuple<float, float, float>> sample;
    for (std::size_t i = 0; i < n; i += step) sample.push_back(key(i));
    std::sort(sample.begin(), sample.end());
    if (std::adjacent_find(sample.begin(), sample.end()) == sample.end()) return false;
  }
  std::vector<std::int32_t> order(n);
  for (std::size_t i = 0; i < n; ++i) order[i] = static_cast<std::int32_t>(i);
  std::stable_sort(order.begin(), order.end(), [&](std::int32_t a, std::int32_t b) { return key(a) < key(b); });
  // Groups in the order of their first (lowest) member.
  std::vector<std::pair<std::int32_t, std::size_t>> firsts;  // (lowest member, start in order)
  for (std::size_t i = 0; i < n; ++i)
    if (i == 0 || key(order[i]) != key(order[i - 1])) firsts.emplace_back(order[i], i);
  if (firsts.size() == n) return false;
  std::vector<std::size_t> ends(firsts.size());
  for (std::size_t g = 0; g < firsts.size(); ++g) ends[g] = g + 1 < firsts.size() ? firsts[g + 1].second : n;
  std::vector<std::size_t> by_first(firsts.size());
  for (std::size_t g = 0; g < by_first.size(); ++g) by_first[g] = g;
  std::sort(by_first.begin(), by_first.end(), [&](std::size_t a, std::size_t b) { return firsts[a].first < firsts[b].first; });
  unique.clear();
  unique.reserve(3 * firsts.size());
  groups.begin.assign(1, 0);
  groups.members.clear();
  groups.members.reserve(n);
  for (std::size_t g : by_first) {
    const std::int32_t rep = firsts[g].first;
    unique.insert(unique.end(), pts.begin() + 3 * std::size_t(rep), pts.begin() + 3 * std::size_t(rep) + 3);
    for (std::size_t i = firsts[g].second; i < ends[g]; ++i) groups.members.push_back(order[i]);  // ascending (stable)
    groups.begin.push_back(static_cast<std::int64_t>(groups.members.size()));
  }
  return true;
}

}  // namespace

struct FlannIndex::Impl {
  FlannPart main, delta;  // local point numbers: main's 0 .. n - 1, then delta's
  // After updates: the stable id of each local point number (ascending: every delta id is newer
  // than every main one; empty: the identity).
  std::vector<std::int32_t> ext;
  std::vector<std::uint8_t> dead;  // removed local numbers, skipped by every search (empty: none)
  std::size_t n_dead = 0;
  std::int32_t id(std::int32_t i) const { return ext.empty() ? i : ext[std::size_t(i)]; }
  std::size_t stored() const { return main.n() + delta.n(); }
  int leaf_max_size = 10;
};

namespace {

// True when FLANN's L2_Simple gives the contract's float distance on sample pairs of the data
// (it should, by construction; a build with fused multiply-adds would break it).
bool flann_distance_matches(const float* pts, std::size_t n) {
  const flann::L2_Simple<float> l2;
  const std::size_t step = std::max<std::size_t>(1, n / 64);
  for (std::size_t i = 0; i < n; i += step)
    for (std::size_t j : {std::size_t(0), n / 2, n - 1}) {
      const float* p = pts + 3 * i;
      const float q[3] = {pts[3 * j] * 1.1f + 0.37f, pts[3 * j + 1] * 0.9f - 0.11f, pts[3 * j + 2] + 1.3f};
      const float a = l2(q, p, 3);
      const float b = reference::dist2_float(p, q);
      if (std::memcmp(&a, &b, sizeof a) != 0) return false;
    }
  return true;
}

}  // namespace

FlannIndex::FlannIndex(std::shared_ptr<Runtime> runtime, const float* points,
                       std::size_t n_points, const FlannParams& params)
    : Index(std::move(runtime), n_points), impl_(std::make_unique<Impl>()) {
  auto t0 = std::chrono::steady_clock::now();
  if (!runtime_ptr()) throw Error("flann: the runtime is null (needed for the buffer-level call)");
  if (params.threads < 0) throw Error("flann: threads must be >= 0, got " + std::to_string(params.threads));
  if (params.leaf_max_size < 1)
    throw Error("flann: leaf_max_size must be >= 1, got " + std::to_string(params.leaf_max_size));
  std::vector<float> scaled;
  const float* pts = prepare_points(points, n_points, scaled);  // validates; extreme scales
  threads_ = params.threads ? params.threads : static_cast<int>(detail::available_cpus());
  impl_->leaf_max_size = params.leaf_max_size;
  build_tree(pts, n_points, {});
  set_build_seconds(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
}

namespace {

// A part's tree over pts (index coordinates, taken over: no copy), its coincident points grouped
// where there are many.
void build_part(FlannPart& part, std::vector<float> pts, int leaf_max_size) {
  const std::size_t n = pts.size() / 3;
  part.points = std::move(pts);
  const bool grouped = group_coincident(part.points, part.unique_points, part.groups);
  try {
    flann::Matrix<float> m(const_cast<float*>(grouped ? part.unique_points.data() : part.points.data()),
                           grouped ? part.unique_points.size() / 3 : n, 3);
    part.tree = std::make_unique<FlannTree>(m, flann::KDTreeSingleIndexParams(leaf_max_size, true));
    part.tree->buildIndex();
    part.recompute = !flann_distance_matches(part.points.data(), n);
  } catch (const std::exception& e) {
    throw Error(std::string("flann: building KDTreeSingleIndex failed: ") + e.what());
  }
}

}  // namespace

void FlannIndex::build_tree(const float* pts, std::size_t n_points, std::vector<std::int32_t> ext) {
  auto fresh = std::make_unique<Impl>();
  fresh->leaf_max_size = impl_->leaf_max_size;
  build_part(fresh->main, std::vector<float>(pts, pts + 3 * n_points), fresh->leaf_max_size);
  fresh->ext = std::move(ext);
  impl_ = std::move(fresh);  // only once built: a failed update leaves the index as it was
}

// A fresh tree over the live points and `m` new ones (index coordinates), ids mapped, built from
// the points the parts hold in one pass (no re-read of the caller's points, no re-scaling or
// re-validation: a fresh build does those, this does not need to). The ids stay the identity
// (ext empty, as after a fresh build) while no stored point was ever dropped. The wrapper's coincident-point
// groups are rebuilt with the tree.
void FlannIndex::rebuild_live(const std::vector<std::uint8_t>& dead, std::size_t n_dead, const float* added,
                              std::size_t m, std::int32_t first) {
  const Impl& im = *impl_;
  const std::size_t live = im.stored() - n_dead;
  const bool identity = im.ext.empty() && n_dead == 0;  // every stored point live, ids = local numbers
  std::vector<float> pts;
  std::vector<std::int32_t> ids;
  pts.reserve(3 * (live + m));
  if (!identity) ids.reserve(live + m);
  for (const FlannPart* p : {&im.main, &im.delta}) {
    const float* src = p->points.data();
    for (std::size_t i = 0; i < p->n(); ++i) {
      const std::size_t at = p->offset + i;
      if (!dead.empty() && dead[at]) continue;
      pts.insert(pts.end(), src + 3 * i, src + 3 * i + 3);
      if (!identity) ids.push_back(im.id(static_cast<std::int32_t>(at)));
    }
  }
  pts.insert(pts.end(), added, added + 3 * m);
  if (!identity)
    for (std::size_t i = 0; i < m; ++i) ids.push_back(first + static_cast<std::int32_t>(i));
  auto fresh = std::make_unique<Impl>();
  fresh->leaf_max_size = im.leaf_max_size;
  build_part(fresh->main, std::move(pts), fresh->leaf_max_size);
  fresh->ext = std::move(ids);
  impl_ = std::move(fresh);  // only once built: a failed update leaves the index as it was
}

// Updates, as FLANN's own KDTreeIndex::addPoints does them (a rebuild only past a threshold;
// its KDTreeSingleIndex, the exact tree used here, rebuilds on every addPoints, and its
// removePoint keeps a removed mark that every search skips): an insert rebuilds only the delta
// tree over the points inserted since the last full build, until they pass half of the main
// tree's (then one full build over the live points); a remove marks the points removed until a
// quarter of the stored ones are (then one full build). A full build costs what a fresh build of
// its result does (FLANN's buildIndex is nearly all of both: 1.05x measured for a 25 % insert
// when an eighth was the threshold), so the threshold is where inserts stop merging: a delta of
// half the main tree is built in about a third of a full build, and a query searches it after
// the main tree with the k-th distance found there, so it visits few of its leaves.
// bench/update_bench.cpp measures them.
void FlannIndex::insert_points(const float*, const float* scaled, std::size_t m, std::int32_t first) {
  Impl& im = *impl_;
  const std::size_t nd = im.delta.n() + m;
  if (2 * nd > im.main.n()) {
    rebuild_live(im.dead, im.n_dead, scaled, m, first);
    return;
  }
  FlannPart delta;
  std::vector<float> pts(im.delta.points);
  pts.insert(pts.end(), scaled, scaled + 3 * m);
  build_part(delta, std::move(pts), im.leaf_max_size);
  delta.offset = im.main.n();
  // Nothing of the index changed until here: a failed build leaves it as it was. An empty ext
  // (ids = local numbers: no stored point dropped since the last build, so the next id is the
  // next local number) stays empty; a map grows by the new ids.
  if (!im.ext.empty()) {
    im.ext.reserve(im.main.n() + nd);
    for (std::size_t i = 0; i < m; ++i) im.ext.push_back(first + static_cast<std::int32_t>(i));
  } else if (std::size_t(first) != im.stored()) {
    throw Error("flann: insert: id " + std::to_string(first) + " does not follow the " + std::to_string(im.stored()) +
                " stored points (internal)");
  }
  if (!im.dead.empty()) im.dead.resize(im.main.n() + nd, 0);
  im.delta = std::move(delta);
}

void FlannIndex::remove_points(const std::int32_t* ids, std::size_t n) {
  Impl& im = *impl_;
  // Local numbers first (ext ascending), so that an internal error leaves the marks as they were.
  std::vector<std::size_t> local(n);
  for (std::size_t i = 0; i < n; ++i) {
    std::size_t at = std::size_t(ids[i]);
    if (!im.ext.empty()) at = std::size_t(std::lower_bound(im.ext.begin(), im.ext.end(), ids[i]) - im.ext.begin());
    if (at >= im.stored() || im.id(static_cast<std::int32_t>(at)) != ids[i] || (!im.dead.empty() && im.dead[at]))
      throw Error("flann: remove: id " + std::to_string(ids[i]) + " is not stored (internal)");
    local[i] = at;
  }
  if (4 * (im.n_dead + n) > im.stored()) {
    // One full build over what stays (the marks on a copy: a failed build leaves the index as it was).
    std::vector<std::uint8_t> dead = im.dead;
    if (dead.empty()) dead.assign(im.stored(), 0);
    for (std::size_t at : local) dead[at] = 1;
    rebuild_live(dead, im.n_dead + n, nullptr, 0, 0);
    return;
  }
  if (im.dead.empty()) im.dead.assign(im.stored(), 0);
  for (std::size_t at : local) im.dead[at] = 1;
  im.n_dead += n;
}

FlannIndex::~FlannIndex() = default;

std::size_t FlannIndex::memory_bytes() const {
  // Host memory, all of it: FLANN's tree (its usedMemory), FLANN's reordered copy of the points
  // (12 B each) and its row-pointer array (NNIndex::points_, 8 B each, which usedMemory leaves
  // out), our points, the contract's copy of the caller's points (exact methods, 12 B each), and
  // the groups of coincident points. Checked against the process's growth (tests/python).
  // After updates: the delta tree likewise, the removed marks and the id map.
  std::size_t bytes = impl_->dead.size() + impl_->ext.size() * 4 + size() * 12;
  for (const FlannPart* p : {&impl_->main, &impl_->delta}) {
    if (!p->tree) continue;
    bytes += static_cast<std::size_t>(std::max(0, p->tree->usedMemory())) + p->n() * (12 + 8) +
             p->points.size() * sizeof(float) + p->unique_points.size() * sizeof(float) +
             p->groups.begin.size() * 8 + p->groups.members.size() * 4;
  }
  return bytes;
}

std::size_t FlannIndex::search(const float* queries, std::size_t n, const SearchParams& params,
                               std::int32_t* ids, float* dist2, std::int32_t* counts) const {
  check_params(params);
  const int k = params.k;
  const float r2 = std::isinf(params.max_radius) ? std::numeric_limits<float>::infinity()
                                                 : params.max_radius * params.max_radius;
  const Impl& im = *impl_;
  const std::size_t N = im.stored() - im.n_dead;  // live
  const int full_row = static_cast<int>(std::min<std::size_t>(N, static_cast<std::size_t>(k)));
  const std::uint8_t* dead = im.dead.empty() ? nullptr : im.dead.data();
  const flann::SearchParams fp(flann::FLANN_CHECKS_UNLIMITED, 0.0f);
  std::atomic<std::size_t> next{0}, nonfinite{0};
  constexpr std::size_t kChunk = 256;  // queries per grab: balances threads, little contention
  auto work = [&]() {
    ExactResultSet set(k, r2, dead);
    std::size_t bad = 0;
    for (;;) {
      const std::size_t begin = next.fetch_add(kChunk);
      if (begin >= n) break;
      const std::size_t end = std::min(n, begin + kChunk);
      for (std::size_t qi = begin; qi < end; ++qi) {
        const float* q = queries + 3 * qi;
        std::int32_t* row_ids = ids + qi * std::size_t(k);
        float* row_d2 = dist2 + qi * std::size_t(k);
        set.reset(q);
        if (std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2])) {
          for (const FlannPart* p : {&im.main, &im.delta})  // the list carries over
            if (p->tree) {
              set.use(*p);
              p->tree->findNeighbors(set, q, fp);
            }
          // FLANN takes a point only when its distance is below the bound, never at +inf: a row
          // short of min(k, N) with no radius to blame holds such points; a scan completes it.
          if (set.size() < full_row && std::isinf(r2)) {
            set.reset(q);
            for (const FlannPart* p : {&im.main, &im.delta}) {
              set.use(*p);
              for (std::size_t i = 0; i < p->n(); ++i) set.add_scanned(i);
            }
          }
        } else {
          ++bad;
        }
        const int c = set.size();
        for (int j = 0; j < k; ++j) {
          row_ids[j] = j < c ? im.id(set.id(j)) : -1;
          row_d2[j] = j < c ? set.d(j) : std::numeric_limits<float>::infinity();
        }
        counts[qi] = c;
      }
    }
    nonfinite += bad;
  };
  run_workers(std::min<std::size_t>(static_cast<std::size_t>(threads_), (n + kChunk - 1) / kChunk),
              next, n, work);
  return nonfinite.load();
}

double FlannIndex::host_radius_search(const float* queries, std::size_t n, float r2,
                                      const RadiusParams&, RadiusResult& out) const {
  auto t0 = std::chrono::steady_clock::now();
  const Impl& im = *impl_;
  const std::uint8_t* dead = im.dead.empty() ? nullptr : im.dead.data();
  const flann::SearchParams fp(flann::FLANN_CHECKS_UNLIMITED, 0.0f);
  std::vector<std::vector<std::pair<float, std::int32_t>>> rows(n);
  std::atomic<std::size_t> next{0};
  constexpr std::size_t kChunk = 256;
  auto work = [&]() {
    RadiusCollectSet set(r2, dead);
    for (;;) {
      const std::size_t begin = next.fetch_add(kChunk);
      if (begin >= n) break;
      for (std::size_t qi = begin; qi < std::min(n, begin + kChunk); ++qi) {
        const float* q = queries + 3 * qi;
        if (!(std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]))) continue;
        set.reset(q);
        for (const FlannPart* p : {&im.main, &im.delta}) {
          if (!p->tree) continue;
          set.use(*p);
          if (std::isinf(r2)) {
            // FLANN takes a point only when its distance is below the bound, never at +inf.
            for (std::size_t i = 0; i < p->n(); ++i) set.add_scanned(i);
          } else {
            p->tree->findNeighbors(set, q, fp);
          }
        }
        rows[qi] = set.found();
      }
    }
  };
  run_workers(std::min<std::size_t>(static_cast<std::size_t>(threads_), (n + kChunk - 1) / kChunk),
              next, n, work);
  std::size_t total = 0;
  for (std::size_t i = 0; i < n; ++i) {
    out.offsets[i] = static_cast<std::int64_t>(total);
    total += rows[i].size();
  }
  out.offsets[n] = static_cast<std::int64_t>(total);
  out.ids.resize(total);
  out.dist2.resize(total);
  for (std::size_t i = 0; i < n; ++i) {
    std::size_t at = static_cast<std::size_t>(out.offsets[i]);
    for (const auto& [d, id] : rows[i]) {
      out.dist2[at] = d;
      out.ids[at++] = im.id(id);
    }
  }
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

double FlannIndex::host_search(const float* queries, std::size_t n, const SearchParams& params,
                               KnnResult& out) const {
  auto t0 = std::chrono::steady_clock::now();
  search(queries, n, params, out.ids.data(), out.dist2.data(), out.counts.data());
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}


}  // namespace bhcl
