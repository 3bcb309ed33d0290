// Points added and removed without a fresh build (Index::insert / Index::remove, issue 23).
// Every method after random sequences of inserts and removes against a fresh build over the live
// points (ids mapped to the stable ones): exact methods and block hashing's exact grid mode bit for
// bit, the block layouts equal to a fresh build of theirs; removed ids never returned; the errors
// for bad input; queries concurrent with updates; save and load after updates.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iterator>
#include <malloc.h>
#include <map>
#include <random>
#include <stdexcept>
#include <thread>

#include "blockhash/build.hpp"
#include "blockhash/grid.hpp"
#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/bruteforce.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/grid_index.hpp"
#include "blockhash_cl/kdtree.hpp"
#include "blockhash_cl/metrics.hpp"
#include "blockhash_cl/multi_device.hpp"
#include "grid_test_util.hpp"
#include "test_util.hpp"

using namespace bhcl;

namespace {

// The live point set the index should hold: id -> point, ascending ids.
struct Model {
  std::map<std::int32_t, std::array<float, 3>> live;
  std::int32_t next = 0;
  void add(const std::vector<float>& p) {
    for (std::size_t i = 0; i < p.size() / 3; ++i) live[next++] = {p[3 * i], p[3 * i + 1], p[3 * i + 2]};
  }
  std::vector<float> points(std::vector<std::int32_t>& ids) const {
    std::vector<float> out;
    ids.clear();
    for (const auto& [id, p] : live) {
      out.insert(out.end(), p.begin(), p.end());
      ids.push_back(id);
    }
    return out;
  }
};

std::vector<float> uniform(std::mt19937_64& rng, std::size_t n, float lo, float hi) {
  std::uniform_real_distribution<float> u(lo, hi);
  std::vector<float> p(3 * n);
  for (auto& v : p) v = u(rng);
  return p;
}

// The first n points of a case, uniform in the unit cube, already in the model.
std::vector<float> first_points(Model& m, std::mt19937_64& rng, std::size_t n) {
  std::vector<float> p0 = uniform(rng, n, 0.0f, 1.0f);
  m.add(p0);
  return p0;
}

// Block hashing over p: the one construction of a BlockHashIndex the update cases share.
std::unique_ptr<BlockHashIndex> blockhash_over(const std::vector<float>& p, const BlockHashBuildParams& bp = {}) {
  return BlockHashIndex::build(test::runtime(), p.data(), p.size() / 3, bp);
}

// method's index over the first n points of a case.
std::unique_ptr<Index> index_over(const std::string& method, Model& m, std::mt19937_64& rng, std::size_t n) {
  const std::vector<float> p0 = first_points(m, rng, n);
  return make_index(method, test::runtime(), p0.data(), n);
}

// body(method, index, model, rng) for every exact method, each from the same seeded start of n
// points (the method captured for the checks' messages).
template <class Body>
void each_exact_method(std::uint64_t seed, std::size_t n, Body&& body) {
  for (const auto& method : exact_method_names()) {
    CAPTURE(method);
    std::mt19937_64 rng(seed);
    Model m;
    auto ix = index_over(method, m, rng, n);
    body(method, *ix, m, rng);
  }
}

// The default block hashing (the grid) over the first n points of a case.
std::unique_ptr<BlockHashIndex> grid_over(Model& m, std::mt19937_64& rng, std::size_t n) {
  auto ix = blockhash_over(first_points(m, rng, n));
  REQUIRE(ix->info().grid);
  return ix;
}

// An insert into the index and the model alike: the index must issue the model's next id.
template <class Ix>
void insert_both(Ix& ix, Model& m, const std::vector<float>& p) {
  REQUIRE(ix.insert(p.data(), p.size() / 3) == m.next);
  m.add(p);
}

// A remove from the index and the model alike.
template <class Ix>
void remove_both(Ix& ix, Model& m, const std::vector<std::int32_t>& ids) {
  ix.remove(ids.data(), ids.size());
  for (std::int32_t id : ids) m.live.erase(id);
}

// A fresh brute force over the model's live points, ids mapped to the stable ones.
KnnResult fresh_answer(const Model& m, const std::vector<float>& qs, const SearchParams& sp) {
  std::vector<std::int32_t> ids;
  std::vector<float> pts = m.points(ids);
  BruteForceIndex bf(test::runtime(), pts.data(), ids.size());
  KnnResult r = bf.query(qs, sp);
  for (auto& id : r.ids)
    if (id >= 0) id = ids[std::size_t(id)];
  return r;
}

void require_no_removed(const KnnResult& r, const Model& m) {
  for (std::int32_t id : r.ids)
    if (id >= 0) REQUIRE_MESSAGE(m.live.count(id), "id " << id << " is not live");
}

// One random step on index and model: an insert (some points outside the current box) or a
// remove of random live ids.
void random_step(Index& ix, Model& m, std::mt19937_64& rng, std::size_t step) {
  if (step % 3 != 2) {
    const std::size_t n = 1 + rng() % 300;
    const float spread = step % 4 == 1 ? 1.6f : 1.0f;  // now and then past the box
    insert_both(ix, m, uniform(rng, n, -0.3f * spread, spread));
  } else {
    std::vector<std::int32_t> all;
    for (const auto& kv : m.live) all.push_back(kv.first);
    std::shuffle(all.begin(), all.end(), rng);
    all.resize(std::min<std::size_t>(all.size() - 1, 1 + rng() % 400));
    remove_both(ix, m, all);
  }
  REQUIRE(ix.size() == m.live.size());
  REQUIRE(ix.id_bound() == m.next);
}

void check_exact(const Index& ix, const Model& m, std::mt19937_64& rng) {
  std::vector<float> qs = uniform(rng, 150, -0.5f, 1.7f);
  // Queries on live points (distance-0 ties): one in 64, at most about 256 of them. Each is
  // checked against a host brute force over every live point, so an uncapped share made the
  // 200k-point tests quadratic (the largest took 300 s of the suite's 426).
  const std::size_t every = std::max<std::size_t>(64, m.live.size() / 256);
  for (const auto& kv : m.live)
    if (rng() % every == 0) qs.insert(qs.end(), kv.second.begin(), kv.second.end());
  for (int k : {1, 10, 33}) {
    for (float r : {INFINITY, 0.08f}) {
      SearchParams sp = test::knn_params(k);
      sp.max_radius = r;
      KnnResult got = ix.query(qs, sp);
      require_no_removed(got, m);
      test::require_identical(got, fresh_answer(m, qs, sp), ix.method() + " k " + std::to_string(k));
    }
  }
  // Radius search: the live points within r, stable ids.
  RadiusResult rr;
  ix.radius_search(qs.data(), qs.size() / 3, 0.1f, RadiusParams{}, rr);
  for (std::size_t q = 0; q < rr.n; ++q)
    for (std::int64_t j = rr.offsets[q]; j < rr.offsets[q + 1]; ++j) {
      const std::int32_t id = rr.ids[std::size_t(j)];
      REQUIRE(m.live.count(id));
    }
  std::size_t expect = 0;
  for (std::size_t q = 0; q < qs.size() / 3; ++q)
    for (const auto& kv : m.live) {
      float d = 0;
      for (int a = 0; a < 3; ++a) d += (qs[3 * q + a] - kv.second[a]) * (qs[3 * q + a] - kv.second[a]);
      expect += d <= 0.1f * 0.1f ? 1 : 0;
    }
  REQUIRE(rr.total() == expect);
}

}  // namespace

TEST_CASE("updates: exact methods after random inserts and removes equal a fresh build") {
  each_exact_method(7, 1500, [](const std::string&, Index& ix, Model& m, std::mt19937_64& rng) {
    for (std::size_t step = 0; step < 9; ++step) {
      CAPTURE(step);
      random_step(ix, m, rng, step);
      check_exact(ix, m, rng);
    }
    REQUIRE(!ix.contains(-1));
    REQUIRE(!ix.contains(m.next));
  });
}

// FLANN's updates (issue 39): small inserts go to a delta tree of their own and removes become
// marks every search skips, until the delta passes an eighth of the main tree or the marks a
// quarter of the stored points; the answers equal a fresh build at every step, with coincident
// points (the main tree and the delta both grouped) and removed members of a group.
TEST_CASE("updates: FLANN's delta tree and removed marks, duplicates included, equal a fresh build") {
  const std::vector<std::string> names = method_names();
  if (std::find(names.begin(), names.end(), "flann") == names.end()) return;  // built without FLANN
  std::mt19937_64 rng(39);
  Model m;
  std::vector<float> p0 = uniform(rng, 2400, 0.0f, 1.0f);
  for (std::size_t i = 0; i < 600; ++i) {  // a quarter of the points coincide with another
    const std::size_t src = rng() % 1800;
    std::copy(p0.begin() + 3 * src, p0.begin() + 3 * src + 3, p0.begin() + 3 * (1800 + i));
  }
  auto ix = make_index("flann", test::runtime(), p0.data(), 2400);
  m.add(p0);
  const std::size_t mem0 = ix->memory_bytes();
  for (int step = 0; step < 14; ++step) {
    CAPTURE(step);
    if (step % 2 == 0) {
      std::vector<float> p = uniform(rng, 40, -0.2f, 1.2f);
      for (std::size_t i = 0; i < 10; ++i) {  // duplicates of live points and among the new ones
        auto it = std::next(m.live.begin(), std::ptrdiff_t(rng() % m.live.size()));
        std::copy(it->second.begin(), it->second.end(), p.begin() + 3 * i);
      }
      std::copy(p.begin() + 30, p.begin() + 33, p.begin() + 33);
      insert_both(*ix, m, p);
    } else {
      std::vector<std::int32_t> all;
      for (const auto& kv : m.live) all.push_back(kv.first);
      std::shuffle(all.begin(), all.end(), rng);
      all.resize(90);
      remove_both(*ix, m, all);
    }
    check_exact(*ix, m, rng);
  }
  // Seven inserts of 40 into 2400 stay under an eighth: the delta holds them, and the index grew
  // by the delta's tree and the marks, not a second copy of the main tree.
  CHECK(ix->memory_bytes() < mem0 + mem0 / 2);
}

// Issue 39: brute force's removed points stay as NaN holes until an eighth of them: no search
// returns one, not even a radius whose square is +inf (every finite distance within), and k
// past the live points leaves the rest of the row empty.
TEST_CASE("updates: brute force's holes are never returned, at any radius or k") {
  std::mt19937_64 rng(392);
  Model m;
  const std::vector<float> p0 = first_points(m, rng, 400);
  BruteForceIndex ix(test::runtime(), p0.data(), 400);
  std::vector<std::int32_t> drop;
  for (std::int32_t id = 0; id < 400; id += 9) drop.push_back(id);  // 45 of 400: holes, no compaction
  remove_both(ix, m, drop);
  insert_both(ix, m, uniform(rng, 20, 0.0f, 1.0f));
  const std::vector<float> qs = uniform(rng, 40, -0.5f, 1.5f);
  RadiusResult rr;
  ix.radius_search(qs.data(), 40, 1e30f, RadiusParams{}, rr);
  for (std::size_t q = 0; q < 40; ++q) REQUIRE(std::size_t(rr.offsets[q + 1] - rr.offsets[q]) == m.live.size());
  for (std::int32_t id : rr.ids) REQUIRE(m.live.count(id));
  SearchParams sp = test::knn_params(64);
  check_exact(ix, m, rng);
  Model few;  // k above the live points: the rows end with empty entries, never a hole
  const std::vector<float> p1 = first_points(few, rng, 40);
  BruteForceIndex small(test::runtime(), p1.data(), 40);
  remove_both(small, few, {5});
  KnnResult r = small.query(qs, sp);
  for (std::size_t q = 0; q < 40; ++q) REQUIRE(r.counts[q] == 39);
  require_no_removed(r, few);
  test::require_identical(r, fresh_answer(few, qs, sp), "bruteforce k 64 over 39 live");
}

// 64 random queries at A = 2: the kernel equals the host reference and returns no removed id.
template <typename Rng>
void budget_kernel_equals_reference(const BlockHashIndex& ix, const Model& m, Rng& rng, const char* what) {
  std::vector<float> qs = uniform(rng, 64, 0.0f, 1.0f);
  SearchParams sp = test::knn_params(8);
  sp.A = 2;
  KnnResult dev = ix.query(qs, sp), ref = ix.reference_query(qs.data(), 64, sp);
  require_no_removed(dev, m);
  test::require_identical(dev, ref, what);
}

TEST_CASE("updates: block hashing's grid (exact mode) after random inserts and removes") {
  std::mt19937_64 rng(11);
  Model m;
  auto ix = grid_over(m, rng, 2000);
  for (std::size_t step = 0; step < 12; ++step) {
    CAPTURE(step);
    random_step(*ix, m, rng, step);
    test::require_pyramid_as_built(*ix);
    check_exact(*ix, m, rng);  // A = 0: the grid's exact mode
    // The host reference sees the same arrays as the kernel.
    budget_kernel_equals_reference(*ix, m, rng, "grid budget A = 2, kernel vs reference");
  }
  // A growth past twice the tuned population retunes; removes past 1/8 holes compact.
  insert_both(*ix, m, uniform(rng, 6000, 0.0f, 1.0f));
  check_exact(*ix, m, rng);
  const BlockHashBuildInfo& in = ix->info();
  MESSAGE("merges " << in.merges << " compactions " << in.compactions << " rebuilds " << in.update_rebuilds
                    << " retunes " << in.retunes << " holes " << in.holes);
  CHECK(in.merges > 0);
  CHECK(in.compactions > 0);
  CHECK(in.update_rebuilds > 0);
  CHECK(in.retunes > 0);
  // A few removes stay holes in place (no compaction) and are still never returned.
  std::vector<std::int32_t> few;
  for (const auto& kv : m.live)
    if (few.size() < 5) few.push_back(kv.first);
  const std::size_t compactions = in.compactions;
  remove_both(*ix, m, few);
  CHECK(ix->info().holes == 5);
  CHECK(ix->info().compactions == compactions);
  check_exact(*ix, m, rng);
}

TEST_CASE("updates: the grid's budget counts live points, and thinned cells retune before the holes compact") {
  std::mt19937_64 rng(5);
  Model m;
  auto ix = grid_over(m, rng, 20000);
  std::vector<std::int32_t> all(20000);
  for (std::int32_t i = 0; i < 20000; ++i) all[std::size_t(i)] = i;
  std::shuffle(all.begin(), all.end(), rng);
  // 7.5 % removed: holes in place (fewer than the 1/8 that compacts; the cells thinned to about
  // 0.93x of the tuned population, inside the band).
  std::vector<std::int32_t> drop(all.begin(), all.begin() + 1500);
  remove_both(*ix, m, drop);
  REQUIRE(ix->info().holes == 1500);
  REQUIRE(ix->info().retunes == 0);
  // The kernel's budget is A k live points: over the stored slots, A k stored / live. The host
  // reference given that budget examines exactly the slots the kernel did, and the plain A k
  // examines fewer.
  const blockhash::Grid& g = *ix->structure().grid;
  REQUIRE(g.n_points == 20000);
  CHECK(blockhash::grid_budget(16, 20000, 1500) == 18);  // ceil(16 * 20000 / 18500)
  CHECK(blockhash::grid_budget(16, 20000, 0) == 16);
  CHECK(blockhash::grid_budget(0xffffffffu, 20000, 1500) == 0xffffffffu);  // exact stays exact
  std::vector<float> qs = uniform(rng, 256, 0.0f, 1.0f);
  SearchParams sp = test::knn_params(8);
  sp.A = 2;
  sp.count_examined = true;
  KnnResult dev = ix->query(qs, sp);
  require_no_removed(dev, m);
  const bool cpu = test::runtime()->quirks().vector_scan;  // the row cap the kernel was built with
  KnnResult widened, plain;
  std::vector<std::int32_t> ex_widened, ex_plain;
  blockhash::reference_query_grid(g, qs.data(), 256, 8, INFINITY, 18, blockhash::grid_traversal(cpu), widened,
                                  &ex_widened, 0);
  blockhash::reference_query_grid(g, qs.data(), 256, 8, INFINITY, 16, blockhash::grid_traversal(cpu), plain,
                                  &ex_plain, 0);
  CHECK(dev.examined == ex_widened);
  std::size_t sum_widened = 0, sum_plain = 0;
  for (std::size_t i = 0; i < 256; ++i) sum_widened += std::size_t(ex_widened[i]), sum_plain += std::size_t(ex_plain[i]);
  CHECK(sum_widened > sum_plain);
  // Another 4 % removed: 11.5 % holes, still short of a compaction, but the cells' estimated
  // population (1 + (p - 1) 0.885) is below 0.9x of the tuned one: the side is retuned over the
  // live points, and the holes are gone.
  std::vector<std::int32_t> more(all.begin() + 1500, all.begin() + 2300);
  const std::size_t compactions = ix->info().compactions;
  remove_both(*ix, m, more);
  CHECK(ix->info().retunes == 1);
  CHECK(ix->info().holes == 0);
  CHECK(ix->info().compactions == compactions);
  CHECK(ix->size() == 17700);
  check_exact(*ix, m, rng);
  budget_kernel_equals_reference(*ix, m, rng, "grid budget A = 2 after the retune, kernel vs reference");
}

// Issue 39: an insert that crosses the retune band (900k + 100k uniform from Python: built twice,
// 3.5-4.5x a fresh build) or lands off the box makes one fresh build over the live points: the
// update's stats count one rebuild, the grid is tuned as a fresh build of the result is (its side
// from a random sample of the same points: within the tuner's tolerance, not bit for bit), and
// the answers are exact.
TEST_CASE("updates: an insert across the grid's retune band is one fresh build, equal to a fresh build of the result") {
  std::mt19937_64 rng(39);
  Model m;
  auto ix = grid_over(m, rng, 36000);
  auto fresh_of_model = [&] {
    std::vector<std::int32_t> ids;
    std::vector<float> pts = m.points(ids);
    return blockhash_over(pts);
  };
  // 5 % more: the point-weighted mean grows by about 5 %, inside the band: a merge.
  std::vector<float> more = uniform(rng, 1800, 0.02f, 0.98f);
  insert_both(*ix, m, more);
  REQUIRE(ix->info().merges == 1);
  REQUIRE(ix->info().update_rebuilds == 0);
  // Another 25 %, inside the box: past 1.1x, so the side is retuned, by one build.
  std::vector<float> cross = uniform(rng, 9900, 0.02f, 0.98f);
  insert_both(*ix, m, cross);
  CHECK(ix->info().merges == 1);
  CHECK(ix->info().update_rebuilds == 1);
  CHECK(ix->info().retunes == 1);
  {
    auto fresh = fresh_of_model();
    CHECK(ix->info().cell_size == doctest::Approx(fresh->info().cell_size).epsilon(0.05));
    CHECK(ix->info().mean_cell_points == doctest::Approx(fresh->info().mean_cell_points).epsilon(0.1));
    CHECK(double(ix->info().occupied_cells) == doctest::Approx(double(fresh->info().occupied_cells)).epsilon(0.15));
  }
  check_exact(*ix, m, rng);
  // Off the box and large (the set doubles into a neighbouring region): before, a build with the
  // side kept whose cells then fell outside the band, and a second build. Now one, as fresh.
  std::vector<float> off = uniform(rng, 49500, 0.0f, 1.0f);
  for (std::size_t i = 0; i < off.size(); i += 3) off[i] += 1.0f;
  insert_both(*ix, m, off);
  CHECK(ix->info().update_rebuilds == 2);
  {
    auto fresh = fresh_of_model();
    CHECK(ix->info().cell_size == doctest::Approx(fresh->info().cell_size).epsilon(0.05));
    CHECK(double(ix->info().occupied_cells) == doctest::Approx(double(fresh->info().occupied_cells)).epsilon(0.15));
    CHECK(ix->info().mean_cell_points == doctest::Approx(fresh->info().mean_cell_points).epsilon(0.1));
  }
  check_exact(*ix, m, rng);
  // Small, off the box and dense (5 % of the set in a cube a few cells wide): the population the
  // kept side would give is far past the band although the set grew by 5 %; before, the build
  // with the side kept was followed by a second one (counted as one rebuild). update_rebuilds
  // counts the builds themselves.
  std::vector<float> dense = uniform(rng, std::size_t(ix->size() / 20), 2.1f, 2.2f);
  const std::size_t before = ix->info().update_rebuilds;
  insert_both(*ix, m, dense);
  CHECK(ix->info().update_rebuilds == before + 1);
  {
    auto fresh = fresh_of_model();
    CHECK(ix->info().cell_size == doctest::Approx(fresh->info().cell_size).epsilon(0.05));
    CHECK(double(ix->info().occupied_cells) == doctest::Approx(double(fresh->info().occupied_cells)).epsilon(0.15));
  }
  check_exact(*ix, m, rng);
  // A large remove (past 1/8 holes and below the band): one build, no compaction before it
  // counted as a second pass over the points' structure.
  std::vector<std::int32_t> drop;
  for (const auto& kv : m.live)
    if (rng() % 2) drop.push_back(kv.first);
  const std::size_t rebuilds = ix->info().update_rebuilds;
  remove_both(*ix, m, drop);
  CHECK(ix->info().update_rebuilds == rebuilds + 1);
  CHECK(ix->info().holes == 0);
  check_exact(*ix, m, rng);
}

// Issue 39: a sensor moving on inserts past the box's edge every scan; the rebuild that takes
// such points leaves room on the side they passed (two corner points, holes after the build), so
// the next scans' points merge instead of building afresh each time; answers stay exact, the room
// is never returned, and the live points' box stays their own.
TEST_CASE("updates: the grid leaves room where inserts passed its box, so a sliding window merges") {
  std::mt19937_64 rng(391);
  Model m;
  auto ix = grid_over(m, rng, 20000);
  // Scan s: 1000 points in [0.1 s, 1 + 0.1 s] x [0, 1]^2 (0.1 of the extent past the old edge: the
  // build's slack of two cells, 0.21, is passed every other scan).
  std::size_t rebuilds = 0, merges = 0;
  for (int s = 1; s <= 6; ++s) {
    CAPTURE(s);
    std::vector<float> scan = uniform(rng, 1000, 0.0f, 1.0f);
    for (std::size_t i = 0; i < scan.size(); i += 3) scan[i] = 0.1f * float(s) + scan[i];
    const std::size_t r0 = ix->info().update_rebuilds, g0 = ix->info().merges;
    insert_both(*ix, m, scan);
    rebuilds += ix->info().update_rebuilds - r0;
    merges += ix->info().merges - g0;
    if (ix->info().update_rebuilds > r0 && rebuilds == 1) {
      CHECK(ix->info().holes == 2);  // the room's corners
      test::require_pyramid_as_built(*ix, true);  // their nodes' boxes made again without them
    }
    // The crop: the 1000 live points of smallest x leave (the population stays in the band).
    std::vector<std::pair<float, std::int32_t>> by_x;
    for (const auto& kv : m.live) by_x.emplace_back(kv.second[0], kv.first);
    std::partial_sort(by_x.begin(), by_x.begin() + 1000, by_x.end());
    std::vector<std::int32_t> drop;
    for (std::size_t i = 0; i < 1000; ++i) drop.push_back(by_x[i].second);
    const std::size_t r1 = ix->info().update_rebuilds;
    remove_both(*ix, m, drop);
    CHECK(ix->info().update_rebuilds == r1);  // holes or a compaction, no build
    check_exact(*ix, m, rng);
  }
  // The scans within the build's slack merge; the first past it rebuilds with half the extent of
  // room in +x, and the next ones land in it (one more rebuild at most: the band, as the
  // population drifts; it keeps the room). Without the room every scan past the edge rebuilt.
  CHECK(rebuilds >= 1);
  CHECK(rebuilds <= 2);
  CHECK(merges >= 4);
  CHECK(ix->size() == m.live.size());
}

TEST_CASE("updates: block hashing's two-level grid directory after random inserts and removes") {
  std::mt19937_64 rng(12);
  Model m;
  const std::vector<float> p0 = first_points(m, rng, 2000);
  BlockHashBuildParams bp;
  bp.grid_directory = 1;  // inserts inside its box merge, those past it rebuild
  auto ix = blockhash_over(p0, bp);
  REQUIRE(ix->info().grid_two_level);
  for (std::size_t step = 0; step < 8; ++step) {
    CAPTURE(step);
    random_step(*ix, m, rng, step);
    REQUIRE(ix->info().grid_two_level);
    check_exact(*ix, m, rng);
    budget_kernel_equals_reference(*ix, m, rng, "two-level grid A = 2, kernel vs reference");
  }
  // Its inserts merge inside the retune band and retune past it: grown 3x in steps of a tenth,
  // the cells stay within 1.1x of the tuned population (once, the side was never retuned there).
  const std::size_t retunes = ix->info().retunes;
  const double tuned = blockhash_over(p0, bp)->info().mean_cell_points;  // what the tuning aims at here
  for (std::size_t step = 0; step < 12; ++step) {
    CAPTURE(step);
    insert_both(*ix, m, uniform(rng, ix->size() / 10, 0.0f, 1.0f));
    // Without the band on this path the population grows with the set (3x by the end).
    CHECK(ix->info().mean_cell_points <= 1.35 * tuned);
  }
  CHECK(ix->info().retunes > retunes);
  REQUIRE(ix->info().grid_two_level);
  check_exact(*ix, m, rng);
}

TEST_CASE("updates: block hashing's block layouts equal a fresh build over the live points") {
  for (int preset = 0; preset < 2; ++preset) {
    CAPTURE(preset);
    BlockHashBuildParams bp;
    if (preset == 0) bp.grid = 0;  // auto's L tables
    else bp.preset = BlockHashBuildParams::Preset::Paper;
    std::mt19937_64 rng(5);
    Model m;
    auto ix = blockhash_over(first_points(m, rng, 1200), bp);
    REQUIRE(!ix->info().grid);
    for (std::size_t step = 0; step < 4; ++step) {
      random_step(*ix, m, rng, step);
      std::vector<std::int32_t> ids;
      std::vector<float> pts = m.points(ids);
      std::vector<float> qs = uniform(rng, 100, 0.0f, 1.0f);
      SearchParams sp = test::knn_params(10);
      KnnResult want = blockhash_over(pts, bp)->query(qs, sp), got = ix->query(qs, sp);
      for (auto& id : want.ids)
        if (id >= 0) id = ids[std::size_t(id)];
      require_no_removed(got, m);
      test::require_identical(got, want, "block layout after updates");
    }
    CHECK(ix->info().update_rebuilds == 4);
  }
}

TEST_CASE("updates: bad input is refused, naming what and where, the index unchanged") {
  for (const auto& method : method_names()) {
    CAPTURE(method);
    std::mt19937_64 rng(3);
    std::vector<float> p0 = uniform(rng, 100, 0.0f, 1.0f);
    auto ix = make_index(method, test::runtime(), p0.data(), 100);
    std::vector<float> bad = {0.5f, 0.5f, 0.5f, 0.1f, NAN, 0.2f};
    CHECK_THROWS_WITH_AS(ix->insert(bad.data(), 2), doctest::Contains("inserted points"), Error);
    CHECK_THROWS_WITH_AS(ix->insert(bad.data(), 0), doctest::Contains("no points"), Error);
    std::int32_t out[] = {3, 100};
    CHECK_THROWS_WITH_AS(ix->remove(out, 2), doctest::Contains("id 100 (entry 1) is outside"), Error);
    std::int32_t neg[] = {-1};
    CHECK_THROWS_WITH_AS(ix->remove(neg, 1), doctest::Contains("outside"), Error);
    std::int32_t dup[] = {4, 7, 4};
    CHECK_THROWS_WITH_AS(ix->remove(dup, 3), doctest::Contains("id 4 appears twice (entries 0 and 2)"), Error);
    REQUIRE(ix->size() == 100);
    std::int32_t one[] = {7};
    ix->remove(one, 1);
    CHECK_THROWS_WITH_AS(ix->remove(one, 1), doctest::Contains("id 7 (entry 0) was already removed"), Error);
    std::vector<std::int32_t> all;
    for (std::int32_t i = 0; i < 100; ++i)
      if (i != 7) all.push_back(i);
    CHECK_THROWS_WITH_AS(ix->remove(all.data(), all.size()), doctest::Contains("empty"), Error);
    REQUIRE(ix->size() == 99);
    REQUIRE(!ix->contains(7));
    REQUIRE(ix->contains(8));
    REQUIRE(ix->insert(p0.data(), 1) == 100);  // ids never reused
    REQUIRE(ix->size() == 100);
  }
}

TEST_CASE("updates: queries concurrent with inserts and removes see one state or the next") {
  for (const std::string method : {"kdtree", "blockhash"}) {
    CAPTURE(method);
    std::mt19937_64 rng(21);
    Model m;
    auto ix = index_over(method, m, rng, 3000);
    const std::vector<float> qs = uniform(rng, 200, 0.0f, 1.0f);
    SearchParams sp = test::knn_params(5);
    // The answers of every state the sequence passes through, computed beforehand.
    struct Step {
      std::vector<float> add;
      std::vector<std::int32_t> drop;
    };
    std::vector<Step> steps;
    std::vector<KnnResult> states{fresh_answer(m, qs, sp)};
    Model sim = m;
    for (int s = 0; s < 8; ++s) {
      Step st;
      if (s % 2 == 0) {
        st.add = uniform(rng, 200, 0.0f, 1.0f);
        sim.add(st.add);
      } else {
        for (const auto& kv : sim.live)
          if (rng() % 10 == 0) st.drop.push_back(kv.first);
        for (std::int32_t id : st.drop) sim.live.erase(id);
      }
      steps.push_back(st);
      states.push_back(fresh_answer(sim, qs, sp));
    }
    std::atomic<bool> done{false};
    std::atomic<int> mismatches{0}, answered{0};
    auto reader = [&]() {
      while (!done.load()) {
        KnnResult r = ix->query(qs, sp);
        bool any = false;
        for (const auto& s : states) any = any || (r.ids == s.ids && r.dist2 == s.dist2 && r.counts == s.counts);
        if (!any) ++mismatches;
        ++answered;
      }
    };
    std::thread t1(reader), t2(reader);
    for (const auto& st : steps) {
      if (!st.add.empty()) ix->insert(st.add.data(), st.add.size() / 3);
      else ix->remove(st.drop.data(), st.drop.size());
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    done = true;
    t1.join();
    t2.join();
    MESSAGE(method << ": " << answered.load() << " concurrent queries");
    CHECK(mismatches.load() == 0);
    CHECK(answered.load() > 0);
    KnnResult last = ix->query(qs, sp);
    test::require_identical(last, states.back(), "after the sequence");
  }
}

TEST_CASE("updates: the multi-device index updates every replica") {
  std::mt19937_64 rng(9);
  Model m;
  const std::vector<float> p0 = first_points(m, rng, 800);
  MultiDeviceIndex md({test::runtime(), test::runtime()}, "kdtree", p0.data(), 800);
  insert_both(md, m, uniform(rng, 100, 0.0f, 1.2f));
  remove_both(md, m, {0, 5, 850});
  REQUIRE(md.size() == m.live.size());
  std::vector<float> qs = uniform(rng, 300, 0.0f, 1.0f);
  SearchParams sp = test::knn_params(7);
  KnnResult r;
  md.query(qs.data(), 300, sp, r);
  test::require_identical(r, fresh_answer(m, qs, sp), "multi-device after updates");
}

namespace {

// A row per id issued (the point set a saved index is loaded against after updates): the live
// points at their ids, a removed id's row some other finite point (it is not compared).
std::vector<float> rows_of(const Model& m) {
  std::vector<float> rows(3 * std::size_t(m.next), 0.25f);
  for (const auto& [id, p] : m.live)
    for (int a = 0; a < 3; ++a) rows[3 * std::size_t(id) + a] = p[a];
  return rows;
}

std::vector<std::int32_t> removed_of(const Model& m) {
  std::vector<std::int32_t> out;
  for (std::int32_t id = 0; id < m.next; ++id)
    if (!m.live.count(id)) out.push_back(id);
  return out;
}

// Both indexes hold the same ids and answer alike: every id's liveness, the counts, and the rows
// of kNN (at each A given, 0: exact) and radius queries bit for bit.
void require_same_index(const Index& a, const Index& b, const Model& m, std::mt19937_64& rng,
                        std::initializer_list<double> As, const std::string& what) {
  REQUIRE(a.size() == b.size());
  REQUIRE(a.id_bound() == b.id_bound());
  REQUIRE(a.removed_count() == b.removed_count());
  REQUIRE(a.size() == m.live.size());
  for (std::int32_t id = -1; id <= m.next; ++id) REQUIRE(a.contains(id) == b.contains(id));
  std::vector<float> qs = uniform(rng, 200, -0.4f, 1.7f);
  for (double A : As)
    for (int k : {1, 10}) {
      SearchParams sp = test::knn_params(k);
      sp.A = A;
      KnnResult ra = a.query(qs, sp), rb = b.query(qs, sp);
      require_no_removed(rb, m);
      test::require_identical(rb, ra, what + " A " + std::to_string(A) + " k " + std::to_string(k));
    }
  RadiusResult x, y;
  a.radius_search(qs.data(), qs.size() / 3, 0.12f, RadiusParams{}, x);
  b.radius_search(qs.data(), qs.size() / 3, 0.12f, RadiusParams{}, y);
  REQUIRE(x.offsets == y.offsets);
  REQUIRE(x.ids == y.ids);
  REQUIRE(x.dist2 == y.dist2);
}

std::string slurp_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}
void spit_file(const std::string& path, const std::string& d) {
  std::ofstream(path, std::ios::binary).write(d.data(), std::streamsize(d.size()));
}
std::uint64_t fnv(const std::string& d, std::size_t from, std::size_t to, std::uint64_t h = 0xcbf29ce484222325ull) {
  for (std::size_t i = from; i < to; ++i) {
    h ^= static_cast<unsigned char>(d[i]);
    h *= 0x100000001b3ull;
  }
  return h;
}
template <typename T>
void poke(std::string& d, std::size_t at, T v) { std::memcpy(&d[at], &v, sizeof v); }
template <typename T>
T peek(const std::string& d, std::size_t at) {
  T v;
  std::memcpy(&v, &d[at], sizeof v);
  return v;
}
// The grid file (grid_io.cpp): version 3's header is 132 bytes, then the checksum, then the
// payload; version 2's was 84 bytes.
constexpr std::size_t kGridHeaderV3 = 132, kGridHeaderV2 = 84;
void grid_reseal(std::string& d, std::size_t header) {
  poke(d, header, fnv(d, header + 8, d.size(), fnv(d, 0, header)));
}

// The configurations of block hashing that save: the grid (direct and two-level directory), auto's
// L tables and the paper preset.
std::vector<std::pair<std::string, BlockHashBuildParams>> blockhash_configs() {
  BlockHashBuildParams grid, two, tables, paper;
  two.grid_directory = 1;
  tables.grid = 0;
  paper.preset = BlockHashBuildParams::Preset::Paper;
  return {{"grid", grid}, {"grid two-level", two}, {"auto's L tables", tables}, {"paper", paper}};
}

}  // namespace

TEST_CASE("updates: block hashing saved and loaded after random inserts and removes, every layout") {
  for (const auto& [name, bp] : blockhash_configs()) {
    CAPTURE(name);
    for (std::uint64_t seed : {21u, 22u}) {
      CAPTURE(seed);
      std::mt19937_64 rng(seed);
      Model m;
      auto ix = blockhash_over(first_points(m, rng, 1500), bp);
      const std::size_t steps = bp.preset == BlockHashBuildParams::Preset::Paper ? 3 : 6;
      for (std::size_t step = 0; step < steps; ++step) random_step(*ix, m, rng, step + seed);
      // A few removes the grid keeps as holes in place (below 1/8: no compaction).
      std::vector<std::int32_t> few;
      for (const auto& kv : m.live)
        if (few.size() < 7 && rng() % 5 == 0) few.push_back(kv.first);
      remove_both(*ix, m, few);
      REQUIRE(ix->removed_count() > 0);
      if (name == std::string("grid")) REQUIRE(ix->info().holes > 0);
      const std::string path = test::tmp_path("update_saved_" + std::to_string(seed) + ".bhi");
      ix->save(path);
      // Through the registry as bhcl --load-index and Python load it: a row per id issued.
      std::vector<float> rows = rows_of(m);
      MethodOptions lo;
      lo.set("load-index", path);
      auto loaded_any = make_index("blockhash", test::runtime(), rows.data(), std::size_t(m.next), lo);
      auto& loaded = dynamic_cast<BlockHashIndex&>(*loaded_any);
      REQUIRE(loaded.info().grid == ix->info().grid);
      if (ix->info().grid) {  // the grid file keeps the update state and counters
        REQUIRE(loaded.info().holes == ix->info().holes);
        REQUIRE(loaded.info().merges == ix->info().merges);
        REQUIRE(loaded.info().compactions == ix->info().compactions);
        REQUIRE(loaded.info().update_rebuilds == ix->info().update_rebuilds);
        REQUIRE(loaded.info().retunes == ix->info().retunes);
      }
      require_same_index(*ix, loaded, m, rng, {0.0, 2.0, 5.0}, name + " loaded");
      // The next update continues where the saved index stopped, on both alike.
      std::vector<float> more = uniform(rng, 120, 0.0f, 1.0f);
      REQUIRE(loaded.insert(more.data(), 120) == m.next);
      insert_both(*ix, m, more);
      std::vector<std::int32_t> drop;
      for (const auto& kv : m.live)
        if (drop.size() < 30 && rng() % 7 == 0) drop.push_back(kv.first);
      loaded.remove(drop.data(), drop.size());
      remove_both(*ix, m, drop);
      require_same_index(*ix, loaded, m, rng, {0.0, 2.0}, name + " loaded, then updated");
      // A live point that differs is refused; a removed id's row is not read.
      std::vector<float> wrong = rows;
      const std::int32_t live_id = m.live.begin()->first;
      wrong[3 * std::size_t(live_id)] += 0.5f;
      CHECK_THROWS_WITH_AS(make_index("blockhash", test::runtime(), wrong.data(), rows.size() / 3, lo),
                           doctest::Contains("differs"), Error);
      CHECK_THROWS_WITH_AS(make_index("blockhash", test::runtime(), rows.data(), rows.size() / 3 - 1, lo),
                           doctest::Contains("give a row for every id"), Error);
    }
  }
}

TEST_CASE("updates: a saved grid after removes: damage refused, version 2 files still load") {
  std::mt19937_64 rng(31);
  Model m;
  const std::vector<float> p0 = first_points(m, rng, 1000);
  auto ix = blockhash_over(p0);
  const std::vector<float> add = uniform(rng, 200, 0.0f, 1.0f);
  insert_both(*ix, m, add);
  remove_both(*ix, m, {3, 500, 1100, 1199});
  REQUIRE(ix->info().holes == 4);
  const std::string path = test::tmp_path("update_grid_v3.bhi"), bad = test::tmp_path("update_grid_bad.bhi");
  ix->save(path);
  const std::string good = slurp_file(path);
  REQUIRE(peek<std::uint32_t>(good, 8) == 3u);
  const std::uint64_t slots = peek<std::uint64_t>(good, 16);
  REQUIRE(slots == 1200);  // holes included
  const std::uint64_t entries = peek<std::uint64_t>(good, 76);
  const std::size_t ids_at = kGridHeaderV3 + 8 + std::size_t(entries) * 4 + std::size_t(slots) * 12;
  std::size_t hole = 0, live_at = 0;
  for (std::size_t i = 0; i < slots; ++i) {
    const auto id = peek<std::int32_t>(good, ids_at + 4 * i);
    if (id == 0x7fffffff) hole = i;
    else if (id == 7) live_at = i;
  }
  auto refused = [&](std::string d, const char* why) {
    grid_reseal(d, kGridHeaderV3);
    spit_file(bad, d);
    CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains(why), Error);
  };
  {  // an id twice
    std::string d = good;
    poke(d, ids_at + 4 * live_at, std::int32_t(8));
    refused(d, "appears twice");
  }
  {  // an id past the bound
    std::string d = good;
    poke(d, ids_at + 4 * live_at, std::int32_t(1200));
    refused(d, "outside [0, id bound");
  }
  {  // a hole with a finite point: it could be returned
    std::string d = good;
    poke(d, kGridHeaderV3 + 8 + std::size_t(entries) * 4 + 4 * hole, 0.5f);
    refused(d, "not at +inf");
  }
  {  // an id bound below the live ids
    std::string d = good;
    poke(d, kGridHeaderV2, std::uint64_t(1100));
    refused(d, "id bound");
  }
  {  // an id bound out of range
    std::string d = good;
    poke(d, kGridHeaderV2, std::uint64_t(0));
    refused(d, "id bound 0 out of range");
  }
  {  // unresealed damage: the checksum
    std::string d = good;
    d[ids_at + 4 * live_at] ^= 1;
    spit_file(bad, d);
    CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("checksum"), Error);
    spit_file(bad, good.substr(0, good.size() - 3));
    CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("truncated"), Error);
  }
  // A version 2 file (written before the id state existed) of an index never updated loads.
  auto plain = blockhash_over(p0);
  plain->save(path);
  const std::string v3 = slurp_file(path);
  std::string v2 = v3.substr(0, kGridHeaderV2) + std::string(8, '\0') + v3.substr(kGridHeaderV3 + 8);
  poke(v2, 8, std::uint32_t(2));
  grid_reseal(v2, kGridHeaderV2);
  spit_file(bad, v2);
  auto old = BlockHashIndex::load(test::runtime(), bad);
  REQUIRE(old->size() == 1000);
  REQUIRE(old->id_bound() == 1000);
  std::vector<float> qs = uniform(rng, 100, 0.0f, 1.0f);
  SearchParams sp = test::knn_params(10);
  sp.A = 2;
  test::require_identical(old->query(qs, sp), plain->query(qs, sp), "version 2 grid file");
  REQUIRE(old->insert(add.data(), 200) == 1000);
}

TEST_CASE("updates: block layouts saved after removes: sparse ids checked, version 4 files still load") {
  std::mt19937_64 rng(41);
  std::vector<float> p0 = uniform(rng, 900, 0.0f, 1.0f);
  BlockHashBuildParams bp;
  bp.grid = 0;
  auto ix = blockhash_over(p0, bp);
  const std::string path = test::tmp_path("update_blocks_v5.bhi"), bad = test::tmp_path("update_blocks_bad.bhi");
  ix->save(path);
  const std::string fresh = slurp_file(path);
  // The block layouts' header (io.cpp): version 5 is 168 bytes, the id bound at 152, the checksum
  // at 160; version 4's is 160 bytes, its checksum at 152.
  REQUIRE(peek<std::uint32_t>(fresh, 8) == 5u);
  REQUIRE(peek<std::uint64_t>(fresh, 152) == 900u);
  std::string v4 = fresh.substr(0, 152) + std::string(8, '\0') + fresh.substr(168);
  poke(v4, 8, std::uint32_t(4));
  poke(v4, 16, std::uint32_t(160));
  poke(v4, 152, fnv(v4, 160, v4.size(), fnv(v4, 0, 152)));
  spit_file(bad, v4);
  auto old = BlockHashIndex::load(test::runtime(), bad);
  std::vector<float> qs = uniform(rng, 100, 0.0f, 1.0f);
  SearchParams sp = test::knn_params(10);
  test::require_identical(old->query(qs, sp), ix->query(qs, sp), "version 4 block file");
  // After removes: the order holds sparse ids; one out of the bound or twice is refused.
  std::int32_t drop[] = {0, 450, 899};
  ix->remove(drop, 3);
  ix->save(path);
  const std::string good = slurp_file(path);
  REQUIRE(peek<std::uint64_t>(good, 152) == 900u);
  REQUIRE(peek<std::uint64_t>(good, 72) == 897u);
  auto loaded = BlockHashIndex::load(test::runtime(), path);
  REQUIRE(loaded->id_bound() == 900);
  REQUIRE(loaded->size() == 897);
  REQUIRE(!loaded->contains(450));
  REQUIRE(loaded->contains(451));
  test::require_identical(loaded->query(qs, sp), ix->query(qs, sp), "block file after removes");
  auto reseal = [&](std::string d) {
    poke(d, 160, fnv(d, 168, d.size(), fnv(d, 0, 160)));
    return d;
  };
  {
    std::string d = good;
    poke(d, 168, std::int32_t(450));  // order[0]: a removed id, now twice or out of place
    spit_file(bad, reseal(d));
    CHECK_THROWS_AS(BlockHashIndex::load(test::runtime(), bad), Error);
    poke(d, 168, std::int32_t(900));
    spit_file(bad, reseal(d));
    CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("outside [0, id bound)"), Error);
    d = good;
    poke(d, 152, std::uint64_t(800));
    spit_file(bad, reseal(d));
    CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("id bound"), Error);
  }
}

TEST_CASE("updates: exact methods restored after updates (a row per id built, the removed removed) answer as before") {
  // The way the Python package saves and pickles a kd-tree, brute force or FLANN index after
  // updates (their structures rebuild faster than they read): the rows of every id issued, a
  // removed id's row a live point, built and the removed ids removed again.
  each_exact_method(51, 1200, [](const std::string& method, Index& ix, Model& m, std::mt19937_64& rng) {
    for (std::size_t step = 0; step < 7; ++step) random_step(ix, m, rng, step);
    std::vector<float> rows = rows_of(m);
    const std::vector<std::int32_t> removed = removed_of(m);
    const auto& first_live = m.live.begin()->second;
    for (std::int32_t id : removed)
      for (int a = 0; a < 3; ++a) rows[3 * std::size_t(id) + a] = first_live[a];
    auto back = make_index(method, test::runtime(), rows.data(), std::size_t(m.next));
    back->remove(removed.data(), removed.size());
    require_same_index(ix, *back, m, rng, {0.0}, method + " restored");
    std::vector<float> more = uniform(rng, 50, 0.0f, 1.3f);
    REQUIRE(back->insert(more.data(), 50) == ix.insert(more.data(), 50));
    m.add(more);
    require_same_index(ix, *back, m, rng, {0.0}, method + " restored, then updated");
  });
}

TEST_CASE("updates: the build stats report holes, merges and rebuilds after updates") {
  std::mt19937_64 rng(61);
  std::vector<float> p0 = uniform(rng, 2000, 0.0f, 1.0f), more = uniform(rng, 100, 0.0f, 1.0f);
  std::int32_t drop[] = {1, 2, 3};
  auto field = [](const UsedFields& u, const std::string& name) {
    for (const auto& [n, v] : u)
      if (n == name) return v;
    return std::string("absent");
  };
  for (const char* method : {"kdtree", "blockhash"}) {
    CAPTURE(method);
    auto ix = make_index(method, test::runtime(), p0.data(), 2000);
    REQUIRE(field(ix->build_used(), "holes") == "absent");  // never updated: nothing more
    ix->insert(more.data(), 100);
    ix->remove(drop, 3);
    const UsedFields u = ix->build_used();
    CHECK(field(u, "holes") == "3");
    CHECK(field(u, "id_bound") == "2100");
    CHECK(field(u, "removed") == "3");
    CHECK(field(u, method == std::string("kdtree") ? "update_merges" : "merges") == "1");
    CHECK(field(u, "update_rebuilds") == "0");
  }
}

// Issue 39: params_for_batch caches its tunings and the exact kd-tree it checks them against.
// After an insert, a remove or a rebuild both belong to another point set: the next batch is
// tuned again, against the live points' exact answers with their stable ids (the tuning's recall
// is the recall its A gives on the sample, checked here against brute force over the live points).
TEST_CASE("updates: params_for_batch tunes again after every update, against the live points") {
  std::mt19937_64 rng(394);
  Model m;
  auto ix = grid_over(m, rng, 20000);
  const std::vector<float> qs = uniform(rng, 256, 0.0f, 1.0f);  // the whole batch is the sample
  SearchParams sp = test::knn_params(10);
  sp.recall_target = 0.8;
  auto tune_and_check = [&](const char* after, bool expect_cached) {
    CAPTURE(after);
    BatchTuning bt;
    const SearchParams got = ix->params_for_batch(qs.data(), qs.size() / 3, sp, &bt);
    REQUIRE(bt.tuned);
    CHECK(bt.cached == expect_cached);
    // A finite A reaches 0.8 on uniform points: an exact tree of other points (or its answers'
    // positions taken for ids) reaches it only at the exact mode.
    CHECK(std::isfinite(got.A));
    CHECK(bt.tuning.reached);
    SearchParams at = test::knn_params(10);
    at.A = got.A;
    at.sort_queries = 0;
    const KnnResult r = ix->query(qs, at);
    require_no_removed(r, m);
    SearchParams exact = test::knn_params(10);
    exact.sort_queries = 0;
    CHECK(bt.tuning.recall == doctest::Approx(evaluate_accuracy(r, fresh_answer(m, qs, exact)).recall).epsilon(1e-12));
  };
  tune_and_check("the build", false);
  tune_and_check("the build, again", true);
  // A remove of half of the points (the side retuned), then an 8 % insert (a merge).
  std::vector<std::int32_t> drop;
  for (const auto& kv : m.live)
    if (rng() % 2) drop.push_back(kv.first);
  remove_both(*ix, m, drop);
  tune_and_check("a remove", false);
  tune_and_check("a remove, again", true);
  insert_both(*ix, m, uniform(rng, ix->size() / 10, 0.0f, 1.0f));
  tune_and_check("an insert", false);
  // A rebuild over another set: ids 0 .. n - 1 again.
  m = Model{};
  std::vector<float> next = first_points(m, rng, 15000);
  ix->rebuild(next.data(), 15000);
  tune_and_check("a rebuild", false);
}

// Issue 39: inserts into the two-level directory merge (they were full builds): inserts of every
// size inside the box (one point, into segments that had none, a tenth of the set, with holes
// present) leave the answers bit-exact against brute force over the live points, the kernel
// equal to the host reference at a budget, and a saved copy (whose load checks every kernel
// invariant of the directory) answering alike.
TEST_CASE("updates: the two-level grid directory merges inserts, exact against brute force") {
  std::mt19937_64 rng(393);
  Model m;
  // Two tight clusters in the unit cube: most of the directory's segments empty.
  std::vector<float> p0 = uniform(rng, 6000, 0.1f, 0.2f);
  const std::vector<float> c2 = uniform(rng, 6000, 0.7f, 0.8f);
  p0.insert(p0.end(), c2.begin(), c2.end());
  const std::vector<float> corner = {0.0f, 0.0f, 0.0f, 1.0f, 1.0f, 1.0f};  // the box: the unit cube
  p0.insert(p0.end(), corner.begin(), corner.end());
  m.add(p0);
  BlockHashBuildParams bp;
  bp.grid_directory = 1;
  auto ix = blockhash_over(p0, bp);
  REQUIRE(ix->info().grid_two_level);
  const std::size_t rebuilds = ix->info().update_rebuilds;
  std::size_t merges = 0;
  auto insert_merged = [&](const std::vector<float>& p, const char* what) {
    CAPTURE(what);
    const std::size_t bytes = ix->info().grid_directory_bytes;
    insert_both(*ix, m, p);
    CHECK(ix->info().merges == ++merges);
    CHECK(ix->info().update_rebuilds == rebuilds);
    REQUIRE(ix->info().grid_two_level);
    CHECK(ix->info().grid_directory_bytes >= bytes);
    test::require_pyramid_as_built(*ix);
    check_exact(*ix, m, rng);
    budget_kernel_equals_reference(*ix, m, rng, "two-level merge A = 2, kernel vs reference");
  };
  insert_merged({0.15f, 0.15f, 0.15f}, "one point in a cluster");
  insert_merged({0.45f, 0.55f, 0.35f}, "one point where no segment was occupied");
  insert_merged(uniform(rng, 40, 0.45f, 0.5f), "a small cluster in empty space");
  insert_merged(uniform(rng, 400, 0.1f, 0.2f), "3 % into the first cluster");
  // Holes present: a few removes (below 1/8: kept in place), then an insert merged past them.
  std::vector<std::int32_t> drop;
  for (const auto& kv : m.live)
    if (drop.size() < 300 && rng() % 20 == 0) drop.push_back(kv.first);
  remove_both(*ix, m, drop);
  REQUIRE(ix->info().holes == drop.size());
  std::vector<float> mixed = uniform(rng, 400, 0.7f, 0.8f);
  const std::vector<float> spread = uniform(rng, 100, 0.0f, 1.0f);
  mixed.insert(mixed.end(), spread.begin(), spread.end());
  insert_merged(mixed, "4 % over a cluster and empty space, holes present");
  CHECK(ix->info().holes == drop.size());
  // Saved and loaded: the load validates the merged directory; the copy answers alike.
  const std::string path = test::tmp_path("update_two_level_merge.bhi");
  ix->save(path);
  std::vector<float> rows = rows_of(m);
  MethodOptions lo;
  lo.set("load-index", path);
  auto loaded = make_index("blockhash", test::runtime(), rows.data(), std::size_t(m.next), lo);
  require_same_index(*ix, *loaded, m, rng, {0.0, 2.0}, "two-level merged, loaded");
  std::remove(path.c_str());
  // Past the band: one fresh build, no merge.
  insert_both(*ix, m, uniform(rng, ix->size(), 0.1f, 0.2f));
  CHECK(ix->info().merges == merges);
  CHECK(ix->info().update_rebuilds == rebuilds + 1);
  check_exact(*ix, m, rng);
}

// Issue 39: a merge of more than 65536 new points takes the parallel arms of the insert (the new
// points counted and sorted by cell in two ranges with their own counts, the node boxes widened
// per range of level-2 slabs, then the widened ones carried up): the pyramid equals one built
// afresh and the answers equal brute force's. 800k uniform points and 66k more (8 %: inside the
// band, and below the eighth past which the band's sample runs).
TEST_CASE("updates: a large merge into the grid (parallel counting sort and node boxes) equals a fresh pyramid and brute force") {
  std::mt19937_64 rng(3939);
  Model m;
  BlockHashBuildParams bp;
  bp.threads = 4;  // two ranges of new points on any machine (66k / 32768), four slab ranges
  auto ix = blockhash_over(first_points(m, rng, 800000), bp);
  REQUIRE(ix->info().grid);
  REQUIRE_FALSE(ix->info().grid_two_level);
  const std::size_t rebuilds = ix->info().update_rebuilds;
  insert_both(*ix, m, uniform(rng, 66000, 0.0f, 1.0f));
  CHECK(ix->info().merges == 1);
  CHECK(ix->info().update_rebuilds == rebuilds);
  test::require_pyramid_as_built(*ix);
  std::vector<float> qs = uniform(rng, 48, -0.2f, 1.2f);
  for (std::int32_t id : {0, 799999, 800000, 832999, 865999}) {  // stored points, old and new
    const auto& p = m.live.at(id);
    qs.insert(qs.end(), p.begin(), p.end());
  }
  for (int k : {1, 16}) {
    const SearchParams sp = test::knn_params(k);
    test::require_identical(ix->query(qs, sp), fresh_answer(m, qs, sp), "grid after a large merge, k " + std::to_string(k));
  }
}

// Issue 39: a large insert that a sample shows past the band goes to one fresh build without the
// exact count of its cells; the build reads the new points where they are (ids first + i, no
// copy): one build, answers bit-exact against brute force.
TEST_CASE("updates: a large insert past the grid's band is one fresh build, exact against brute force") {
  std::mt19937_64 rng(395);
  Model m;
  // The points fill x < 0.5 of the unit cube (its corners are points too: the grid spans it).
  std::vector<float> p0 = uniform(rng, 200000, 0.0f, 1.0f);
  for (std::size_t i = 0; i < p0.size(); i += 3) p0[i] *= 0.5f;
  const std::vector<float> corners = {0.0f, 0.0f, 0.0f, 1.0f, 1.0f, 1.0f};
  p0.insert(p0.end(), corners.begin(), corners.end());
  m.add(p0);
  auto ix = blockhash_over(p0);
  REQUIRE(ix->info().grid);
  auto half = [&](std::size_t n, float x0) {
    std::vector<float> p = uniform(rng, n, 0.01f, 0.99f);
    for (std::size_t i = 0; i < p.size(); i += 3) p[i] = x0 + 0.49f * p[i];
    return p;
  };
  insert_both(*ix, m, half(80000, 0.0f));  // 40 % more where the points are
  CHECK(ix->info().update_rebuilds == 1);
  CHECK(ix->info().retunes == 1);
  CHECK(ix->info().merges == 0);
  test::require_pyramid_as_built(*ix);  // built from the old arrays' cell order (no records)
  check_exact(*ix, m, rng);
  budget_kernel_equals_reference(*ix, m, rng, "grid A = 2 after a large insert's build, kernel vs reference");
  // As many again, sparser, into the empty half: the population falls, so the insert merges.
  insert_both(*ix, m, half(70000, 0.5f));
  CHECK(ix->info().update_rebuilds == 1);
  CHECK(ix->info().merges == 1);
  check_exact(*ix, m, rng);
  // Two more, 5 % each over the whole cube: the arrays' room (an eighth, kept by the merge above)
  // takes them in place, in parallel over ranges of cells whose heads the range before overwrites.
  for (int i = 0; i < 2; ++i) {
    CAPTURE(i);
    insert_both(*ix, m, uniform(rng, 17500, 0.01f, 0.99f));
    CHECK(ix->info().update_rebuilds == 1);
    CHECK(ix->info().merges == std::size_t(2 + i));
    test::require_pyramid_as_built(*ix);
    check_exact(*ix, m, rng);
    budget_kernel_equals_reference(*ix, m, rng, "grid A = 2 after a merge in place, kernel vs reference");
  }
}

// Issue 39: a rebuild whose old points are a grid's arrays in cell order sorts them straight into
// the new arrays (the new points through records); the arrays, directory and pyramid must equal
// the bucket passes' build of the same input bit for bit, in parallel ranges (2 of old points and
// 2 of new here), without new points, and where the cells outnumber the points (then the bucket
// passes run).
TEST_CASE("updates: the grid's build from cell order equals the bucket passes' build") {
  std::mt19937_64 rng(3940);
  blockhash::GridBuildArgs args;
  args.threads = 4;
  blockhash::Grid old;
  {
    const std::vector<float> p0 = uniform(rng, 150000, 0.0f, 1.0f);
    blockhash::GridInput in;
    in.xyz = p0.data(), in.n_aos = 150000;
    blockhash::build_grid(in, args, old, nullptr);
  }
  const std::vector<float> more = uniform(rng, 40000, 0.1f, 0.9f);
  for (std::size_t extra : {40000, 0})  // new points (their records), none (a remove's rebuild)
  for (double side : {-1.0, 0.012}) {  // tuned; so small that the cells outnumber the points (direct)
    CAPTURE(extra);
    CAPTURE(side);
    args.cell_size = side;
    blockhash::GridInput in;
    in.x = old.x.data(), in.y = old.y.data(), in.z = old.z.data(), in.soa_ids = old.ids.data(), in.n_soa = old.n_points;
    const float lo[3] = {old.dbox.lx, old.dbox.ly, old.dbox.lz}, hi[3] = {old.dbox.hx, old.dbox.hy, old.dbox.hz};
    for (int d = 0; d < 3; ++d) in.soa_lo[d] = lo[d], in.soa_hi[d] = hi[d];
    in.xyz = more.data(), in.aos_first = 150000, in.n_aos = extra;
    blockhash::Grid a, b;
    blockhash::GridBuildStats sa, sb;
    blockhash::build_grid(in, args, a, &sa);
    in.soa_in_cells = true;
    blockhash::build_grid(in, args, b, &sb);
    CHECK_FALSE(sa.from_cells);
    CHECK(sb.from_cells == (side < 0));
    REQUIRE(std::memcmp(&a.geom, &b.geom, sizeof(a.geom)) == 0);
    CHECK(a.n_points == b.n_points);
    CHECK(sa.occupied == sb.occupied);
    CHECK(sa.mean_cell_points == sb.mean_cell_points);
    CHECK(std::memcmp(&a.dbox, &b.dbox, sizeof(a.dbox)) == 0);
    CHECK(std::equal(a.starts.begin(), a.starts.end(), b.starts.begin(), b.starts.end()));
    CHECK(std::equal(a.ids.begin(), a.ids.end(), b.ids.begin(), b.ids.end()));
    CHECK(std::memcmp(a.x.data(), b.x.data(), a.x.size() * 4) == 0);
    CHECK(std::memcmp(a.y.data(), b.y.data(), a.y.size() * 4) == 0);
    CHECK(std::memcmp(a.z.data(), b.z.data(), a.z.size() * 4) == 0);
    CHECK(std::equal(a.occ.begin(), a.occ.end(), b.occ.begin(), b.occ.end()));
  }
}

// Issue 39: degenerate updates of the grid, each at most one build and exact against brute force
// after it: an empty insert (refused, nothing changed); a quarter more inside the box (past the
// band: one build), then a merge in place; a remove below the band (one build, written into the
// old point arrays' memory, which holds the result with an eighth to spare); duplicates of stored
// points and one point thousands of times (ties by id); points far outside the box.
TEST_CASE("updates: degenerate grid inserts (empty, across the band, duplicates, far off the box) build at most once") {
  std::mt19937_64 rng(3939);
  Model m;
  auto ix = grid_over(m, rng, 40000);
  std::vector<float> none;
  CHECK_THROWS_WITH_AS(ix->insert(none.data(), 0), doctest::Contains("no points"), Error);
  CHECK(ix->size() == 40000);
  CHECK(ix->id_bound() == 40000);
  CHECK(ix->info().merges == 0);
  CHECK(ix->info().update_rebuilds == 0);
  // A quarter more, inside the box: past the band, one build.
  insert_both(*ix, m, uniform(rng, 10000, 0.01f, 0.99f));
  CHECK(ix->info().update_rebuilds == 1);
  CHECK(ix->info().retunes == 1);
  CHECK(ix->info().merges == 0);
  test::require_pyramid_as_built(*ix);
  check_exact(*ix, m, rng);
  // A twentieth more: merged in place (the arrays kept an eighth of room), no build.
  const float* const x_before = ix->structure().grid->x.data();
  insert_both(*ix, m, uniform(rng, 2500, 0.01f, 0.99f));
  CHECK(ix->info().update_rebuilds == 1);
  CHECK(ix->info().merges == 1);
  CHECK(ix->structure().grid->x.data() == x_before);
  test::require_pyramid_as_built(*ix);
  check_exact(*ix, m, rng);
  // Three tenths removed: below the band, one build, into the same arrays.
  std::vector<std::int32_t> drop;
  for (const auto& kv : m.live)
    if (rng() % 10 < 3) drop.push_back(kv.first);
  remove_both(*ix, m, drop);
  CHECK(ix->info().update_rebuilds == 2);
  CHECK(ix->info().retunes == 2);
  CHECK(ix->info().holes == 0);
  CHECK(ix->structure().grid->x.data() == x_before);
  test::require_pyramid_as_built(*ix);
  check_exact(*ix, m, rng);
  // Duplicates: every 20th live point again, then one stored point 3000 times (one cell far past
  // the band: one build).
  std::vector<float> dup;
  std::size_t i = 0;
  for (const auto& kv : m.live)
    if (i++ % 20 == 0) dup.insert(dup.end(), kv.second.begin(), kv.second.end());
  std::size_t r0 = ix->info().update_rebuilds;
  insert_both(*ix, m, dup);
  CHECK(ix->info().update_rebuilds <= r0 + 1);
  check_exact(*ix, m, rng);
  const std::array<float, 3> one = m.live.begin()->second;
  std::vector<float> same;
  for (int j = 0; j < 3000; ++j) same.insert(same.end(), one.begin(), one.end());
  r0 = ix->info().update_rebuilds;
  insert_both(*ix, m, same);
  CHECK(ix->info().update_rebuilds == r0 + 1);
  CHECK(ix->info().retunes >= 2);
  check_exact(*ix, m, rng);
  // Far outside the box: one build over the live points and the new ones.
  std::vector<float> far = uniform(rng, 200, 1.0e4f, 1.0e4f + 1.0f);
  r0 = ix->info().update_rebuilds;
  insert_both(*ix, m, far);
  CHECK(ix->info().update_rebuilds == r0 + 1);
  CHECK(ix->size() == m.live.size());
  check_exact(*ix, m, rng);
  budget_kernel_equals_reference(*ix, m, rng, "grid A = 2 after degenerate inserts, kernel vs reference");
}

// The grid's point box (the traversal's bound) stays the live points' own after removes that take
// points on it, as a load of the saved index computes it: a large remove finds its slots and the
// live box in one chunked pass over the stored ids (issue 39), a small one through the id -> slot
// map and a recount of the box.
TEST_CASE("updates: removes that take the grid's extreme points leave the live points' box") {
  std::mt19937_64 rng(3941);
  Model m;
  auto ix = grid_over(m, rng, 70000);  // three chunks of the pass
  auto require_live_box = [&](const char* what) {
    CAPTURE(what);
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (const auto& kv : m.live)
      for (int d = 0; d < 3; ++d) lo[d] = std::min(lo[d], kv.second[d]), hi[d] = std::max(hi[d], kv.second[d]);
    const bhcl_grid_dbox& b = ix->structure().grid->dbox;
    REQUIRE(b.lx == lo[0]);
    REQUIRE(b.ly == lo[1]);
    REQUIRE(b.lz == lo[2]);
    REQUIRE(b.hx == hi[0]);
    REQUIRE(b.hy == hi[1]);
    REQUIRE(b.hz == hi[2]);
  };
  // The ids holding the extremes of each axis, and a tenth of the others (the scan's path).
  auto extremes = [&] {
    std::vector<std::int32_t> ids;
    for (int d = 0; d < 3; ++d) {
      auto lt = [d](const auto& a, const auto& b) { return a.second[d] < b.second[d]; };
      ids.push_back(std::min_element(m.live.begin(), m.live.end(), lt)->first);
      ids.push_back(std::max_element(m.live.begin(), m.live.end(), lt)->first);
    }
    std::sort(ids.begin(), ids.end());
    ids.erase(std::unique(ids.begin(), ids.end()), ids.end());
    return ids;
  };
  const std::vector<std::int32_t> ends = extremes();
  std::vector<std::int32_t> drop = ends;
  for (const auto& kv : m.live)
    if (rng() % 10 == 0 && !std::binary_search(ends.begin(), ends.end(), kv.first)) drop.push_back(kv.first);
  remove_both(*ix, m, drop);
  REQUIRE(ix->info().holes == drop.size());  // holes in place, no compaction or build
  require_live_box("a tenth and the extremes");
  check_exact(*ix, m, rng);
  remove_both(*ix, m, extremes());  // six ids: the map's path
  require_live_box("the next extremes");
  check_exact(*ix, m, rng);
  // A fresh grid whose top plane of cells along x loses every point (the refit scans inward past
  // it) and whose low y and z sides lose their extreme point.
  Model m2;
  auto ix2 = grid_over(m2, rng, 70000);
  std::swap(m, m2);
  std::swap(ix, ix2);
  std::vector<std::pair<float, std::int32_t>> by_x;
  for (const auto& kv : m.live) by_x.emplace_back(kv.second[0], kv.first);
  std::sort(by_x.begin(), by_x.end());
  std::vector<std::int32_t> top;
  for (std::size_t i = by_x.size() - by_x.size() / 12; i < by_x.size(); ++i) top.push_back(by_x[i].second);
  const std::size_t cells_x = ix->structure().grid->geom.nx;
  REQUIRE(double(by_x.size()) / 12 > 1.2 * double(by_x.size()) / double(cells_x));  // past a plane of cells
  for (int d = 1; d < 3; ++d) {
    auto lt = [d](const auto& a, const auto& b) { return a.second[d] < b.second[d]; };
    const std::int32_t low = std::min_element(m.live.begin(), m.live.end(), lt)->first;
    if (std::find(top.begin(), top.end(), low) == top.end()) top.push_back(low);
  }
  remove_both(*ix, m, top);
  REQUIRE(ix->info().holes == top.size());
  require_live_box("the top twelfth along x and the low y and z ends");
  check_exact(*ix, m, rng);
  // An outlier far along y, then removed: the planes between it and the rest are empty, more
  // cells than points, and the box is taken from every live point instead.
  Model m3;
  std::vector<float> p3 = uniform(rng, 20000, 0.0f, 1.0f);
  p3.insert(p3.end(), {0.5f, 400.0f, 0.5f});
  m3.add(p3);
  auto ix3 = blockhash_over(p3);
  std::swap(m, m3);
  std::swap(ix, ix3);
  remove_both(*ix, m, {20000});
  require_live_box("the outlier removed");
  check_exact(*ix, m, rng);
}

// Issue 39: the cache of freed large grid blocks (lib/src/blockhash/grid_memory.cpp). Each case
// sets its own bound and empties the cache first, and restores the bound after.
namespace {

constexpr std::size_t kMiB = std::size_t(1) << 20;

struct CacheBound {
  std::size_t old;
  explicit CacheBound(std::size_t bytes) : old(blockhash::host_cache_set_limit(bytes)) { release_host_cache(); }
  ~CacheBound() { blockhash::host_cache_set_limit(old); }
};

}  // namespace

TEST_CASE("host cache: a freed large block serves the next request that fits, not a much smaller one") {
  CacheBound bound(64 * kMiB);
  REQUIRE(blockhash::host_cache_state().bytes == 0);
  void* p = blockhash::grid_allocate(6 * kMiB - 100);  // 6 MiB rounded
  std::memset(p, 1, 6 * kMiB - 100);
  blockhash::grid_deallocate(p, 6 * kMiB - 100);
  CHECK(blockhash::host_cache_state().bytes == 6 * kMiB);
  CHECK(blockhash::host_cache_state().blocks == 1);
  // 5 MiB rounds to 6: the same block back.
  void* q = blockhash::grid_allocate(5 * kMiB);
  CHECK(q == p);
  CHECK(blockhash::host_cache_state().bytes == 0);
  blockhash::grid_deallocate(q, 5 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 6 * kMiB);
  // 4 MiB: the 6 MiB block is 1.5x it, too large; a new one, the cached one kept.
  void* r = blockhash::grid_allocate(4 * kMiB);
  CHECK(r != p);
  CHECK(blockhash::host_cache_state().bytes == 6 * kMiB);
  blockhash::grid_deallocate(r, 4 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 10 * kMiB);
  CHECK(blockhash::host_cache_state().blocks == 2);
  // A block up to 1.25x the request serves it, and goes back at its own size.
  void* big = blockhash::grid_allocate(10 * kMiB);
  blockhash::grid_deallocate(big, 10 * kMiB);
  void* s = blockhash::grid_allocate(8 * kMiB);
  CHECK(s == big);
  CHECK(blockhash::host_cache_state().bytes == 10 * kMiB);
  blockhash::grid_deallocate(s, 8 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 20 * kMiB);
  // The smallest that fits: the 6 MiB block for 6 MiB, not the 10.
  void* t = blockhash::grid_allocate(6 * kMiB);
  CHECK(t == p);
  blockhash::grid_deallocate(t, 6 * kMiB);
  // Small arrays are not cached.
  void* small = blockhash::grid_allocate(kMiB);
  blockhash::grid_deallocate(small, kMiB);
  CHECK(blockhash::host_cache_state().bytes == 20 * kMiB);
  CHECK(release_host_cache() == 20 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 0);
  CHECK(blockhash::host_cache_state().blocks == 0);
  CHECK(release_host_cache() == 0);
}

TEST_CASE("host cache: the bound holds (the oldest out first), 0 caches nothing, and BHCL_HOST_CACHE_MB's values") {
  CacheBound bound(14 * kMiB);
  void* a = blockhash::grid_allocate(6 * kMiB);
  void* b = blockhash::grid_allocate(6 * kMiB);
  void* c = blockhash::grid_allocate(6 * kMiB);
  blockhash::grid_deallocate(a, 6 * kMiB);
  blockhash::grid_deallocate(b, 6 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 12 * kMiB);
  blockhash::grid_deallocate(c, 6 * kMiB);  // 18 > 14: a, the oldest, freed
  CHECK(blockhash::host_cache_state().bytes == 12 * kMiB);
  CHECK(blockhash::host_cache_state().blocks == 2);
  void* x = blockhash::grid_allocate(6 * kMiB);
  void* y = blockhash::grid_allocate(6 * kMiB);
  CHECK(((x == b && y == c) || (x == c && y == b)));
  CHECK(blockhash::host_cache_state().bytes == 0);
  void* huge = blockhash::grid_allocate(16 * kMiB);  // larger than the bound: freed, not cached
  blockhash::grid_deallocate(huge, 16 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 0);
  blockhash::grid_deallocate(x, 6 * kMiB);
  blockhash::grid_deallocate(y, 6 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 12 * kMiB);
  // A lower bound frees what is over it at once; 0 frees all and caches nothing more.
  CHECK(blockhash::host_cache_set_limit(8 * kMiB) == 14 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 6 * kMiB);
  blockhash::host_cache_set_limit(0);
  CHECK(blockhash::host_cache_state().bytes == 0);
  void* z = blockhash::grid_allocate(6 * kMiB);
  blockhash::grid_deallocate(z, 6 * kMiB);
  CHECK(blockhash::host_cache_state().bytes == 0);
  CHECK(blockhash::host_cache_state().limit == 0);
  // The variable's values: MiB, 0 for none; anything else the default, min(512 MiB, memory / 8).
  CHECK(blockhash::host_cache_limit_from("0") == 0);
  CHECK(blockhash::host_cache_limit_from("16") == 16 * kMiB);
  const std::size_t dflt = blockhash::host_cache_limit_from(nullptr);
  CHECK(dflt > 0);
  CHECK(dflt <= 512 * kMiB);
  CHECK(blockhash::host_cache_limit_from("") == dflt);
  CHECK(blockhash::host_cache_limit_from("-3") == dflt);
  CHECK(blockhash::host_cache_limit_from("12x") == dflt);
  if (!std::getenv("BHCL_HOST_CACHE_MB")) CHECK(bound.old == dflt);  // the bound the process started with
}

TEST_CASE("host cache: concurrent allocations and frees never hand one block to two owners") {
  CacheBound bound(64 * kMiB);
  std::atomic<bool> clash{false};
  auto worker = [&](unsigned char tag) {
    for (int i = 0; i < 200; ++i) {
      const std::size_t bytes = (4 + std::size_t(i % 3) * 2) * kMiB;
      auto* p = static_cast<unsigned char*>(blockhash::grid_allocate(bytes));
      p[0] = tag, p[bytes - 1] = tag;
      std::this_thread::yield();
      if (p[0] != tag || p[bytes - 1] != tag) clash = true;
      blockhash::grid_deallocate(p, bytes);
    }
  };
  std::thread t1(worker, 1), t2(worker, 2);
  t1.join();
  t2.join();
  CHECK(!clash);
  CHECK(blockhash::host_cache_state().bytes <= 64 * kMiB);
}

// Cached blocks come back with what their last owner wrote: the grid must write every element it
// reads. Blocks of every size a 1M-point grid asks for, filled with NaN bits, cached first; then
// a build, a 25 % insert (one rebuild across the band, its arrays new), an 8 % insert (a merge)
// and a 10 % remove, each answering bit for bit as brute force over the live points.
TEST_CASE("host cache: a grid built, grown and thinned on reused dirty blocks answers exactly") {
  CacheBound bound(512 * kMiB);
  std::vector<std::pair<void*, std::size_t>> dirty;
  for (std::size_t mib = 4; mib <= 24; mib += 2)  // 344 MiB: under the bound, none evicted
    for (int copy = 0; copy < (mib == 6 ? 8 : 2); ++copy) {  // 6 MiB: a 1M-point array with its room
      void* p = blockhash::grid_allocate(mib * kMiB);
      std::memset(p, 0xff, mib * kMiB);
      dirty.emplace_back(p, mib * kMiB);
    }
  for (auto [p, bytes] : dirty) blockhash::grid_deallocate(p, bytes);
  const std::size_t cached = blockhash::host_cache_state().bytes;
  REQUIRE(cached == 344 * kMiB);
  std::mt19937_64 rng(4539);
  Model m;
  auto ix = grid_over(m, rng, 1000000);
  CHECK(blockhash::host_cache_state().bytes < cached);  // the build took dirty blocks
  auto check = [&](const char* stage) {
    CAPTURE(stage);
    std::vector<float> qs = uniform(rng, 120, -0.1f, 1.1f);
    std::size_t k = 0;
    for (const auto& kv : m.live)
      if (k++ % 9973 == 0) qs.insert(qs.end(), kv.second.begin(), kv.second.end());
    const SearchParams sp = test::knn_params(16);
    const KnnResult got = ix->query(qs, sp);
    require_no_removed(got, m);
    test::require_identical(got, fresh_answer(m, qs, sp), stage);
  };
  check("built");
  const std::size_t rebuilds = ix->info().update_rebuilds;
  insert_both(*ix, m, uniform(rng, 250000, 0.0f, 1.0f));
  CHECK(ix->info().update_rebuilds == rebuilds + 1);
  check("25 % inserted");
  const std::size_t merges = ix->info().merges;
  insert_both(*ix, m, uniform(rng, 100000, 0.0f, 1.0f));
  CHECK(ix->info().merges == merges + 1);
  check("8 % inserted");
  std::vector<std::int32_t> drop;
  for (const auto& kv : m.live)
    if (rng() % 10 == 0) drop.push_back(kv.first);
  remove_both(*ix, m, drop);
  check("10 % removed");
}

TEST_CASE("host cache: a query the memory check would refuse releases the cache and measures again") {
  // In a child with room for 96 MiB more: a 64 MiB block freed into the cache still counts as
  // mapped memory, which leaves 32 MiB, and an 84 MB result (1M queries x k = 10) passes only once
  // the cache has given its block back.
  // What earlier tests in this process left in the cache, released before the child measures its
  // mapped memory: released in the child, after its limit was set, it left that much more room
  // (the check then passed without the release, run after the 1M grid test in one process).
  release_host_cache();
  const int rc = test::with_memory_limit(std::size_t(96) << 20, [] {
    // The block mapped and unmapped, not carved from (or freed into) free heap that earlier tests
    // left: otherwise it moves no mapped memory either way (the whole test binary in one process).
    mallopt(M_MMAP_THRESHOLD, 1 << 20);
    auto mapped_pages = [] {
      std::ifstream statm("/proc/self/statm");
      std::size_t pages = 0;
      statm >> pages;
      return pages;
    };
    blockhash::host_cache_set_limit(std::size_t(256) << 20);
    const std::size_t before = mapped_pages();
    void* p = blockhash::grid_allocate(std::size_t(64) << 20);
    // A free heap chunk that large still served it (earlier tests' heap): the premise fails, 4.
    if ((mapped_pages() - before) * std::size_t(sysconf(_SC_PAGESIZE)) < (std::size_t(64) << 20)) _exit(4);
    blockhash::grid_deallocate(p, std::size_t(64) << 20);
    if (blockhash::host_cache_state().bytes != (std::size_t(64) << 20)) throw std::logic_error("the block was not cached");
    try {
      check_result_memory(std::size_t(1) << 20, 10, false, 1, "blockhash");
    } catch (const Error&) {
      if (blockhash::host_cache_state().bytes != 0) throw;  // refused without releasing the cache: 1
      // Released and still refused (AddressSanitizer's quarantine keeps the freed block mapped): 2.
      throw std::bad_alloc();
    }
    if (blockhash::host_cache_state().bytes != 0) throw std::logic_error("passed without releasing the cache");
  });
  if (rc == 4) {  // only where other tests ran first in this process; ctest runs this case alone
    MESSAGE("skipped: the 64 MiB block came from free heap left by earlier tests, so it maps nothing");
    return;
  }
#if defined(__SANITIZE_ADDRESS__)
  CHECK((rc == 0 || rc == 2));
#else
  CHECK(rc == 0);
#endif
}
