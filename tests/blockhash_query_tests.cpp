// Block hashing queries: the OpenCL kernel against its host reference (bit for bit), the result
// contract, accuracy behaviour, the Cornell-wall case, the buffer-level call and the CLI.
#include "blockhash/build.hpp"
#include "test_util.hpp"

using namespace bhcl;

namespace {

// The two L-table layouts (auto's grid has its own tests: blockhash_grid_tests.cpp and
// grid_far_vs_bruteforce.cpp): "tables", auto's L tables (grid = 0: guarded thresholds, a
// directory, probes, box order), and "paper", the talk's.
BlockHashBuildParams layout(const char* name) {
  BlockHashBuildParams p;
  const bool tables = std::string(name) == "tables";
  p.preset = BlockHashBuildParams::parse_preset(tables ? "auto" : name);
  if (tables) p.grid = 0;
  return p;
}

// body(case, layout name, index over the case's points) for every case and each layout, both
// captured for the checks' messages: the one construction the case-by-layout tests share.
template <class Body>
void each_case_and_layout(const std::vector<test::NamedCase>& cases, std::initializer_list<const char*> layouts,
                          Body&& body) {
  for (const test::NamedCase& c : cases)
    for (const char* pr : layouts) {
      CAPTURE(c.name);
      CAPTURE(pr);
      auto index = BlockHashIndex::build(test::runtime(), c.pts.data(), c.pts.size() / 3, layout(pr));
      body(c, pr, *index);
    }
}

// Kernel == reference exactly (ids, distances, counts, points examined), and the contract.
void kernel_equals_reference(const BlockHashIndex& index, const std::vector<float>& pts,
                             const std::vector<float>& qs, const SearchParams& p) {
  const std::size_t n = qs.size() / 3;
  SearchParams pe = p;
  pe.count_examined = true;
  KnnResult r = index.query(qs, pe);
  const std::vector<std::int32_t>& ex = r.examined;
  std::vector<std::int32_t> ex_ref;
  KnnResult ref = index.reference_query(qs.data(), n, p, &ex_ref);
  REQUIRE(r.counts == ref.counts);
  REQUIRE(r.ids == ref.ids);
  for (std::size_t i = 0; i < r.dist2.size(); ++i) {
    INFO("entry " << i);
    REQUIRE((r.dist2[i] == ref.dist2[i] || (std::isinf(r.dist2[i]) && std::isinf(ref.dist2[i]))));
  }
  REQUIRE(ex == ex_ref);
  // The plain host-array call answers the same.
  KnnResult plain = index.query(qs, p);
  REQUIRE(plain.ids == r.ids);
  REQUIRE(plain.counts == r.counts);
  test::check_contract(r, pts.data(), pts.size() / 3, qs.data(), p);
  // The budget bounds the scan to within one block.
  const std::uint32_t slack = std::uint32_t(index.X());
  SearchParams pb = p;
  if (pb.A == 0) pb.A = 8;  // SearchParams' default: the block layouts' 8
  for (std::size_t i = 0; i < n; ++i) REQUIRE(std::uint32_t(ex[i]) < BlockHashIndex::budget(pb) + slack);
}

}  // namespace

TEST_CASE("blockhash_vs_reference: every distribution, both L-table layouts, kernel == host reference") {
  using Case = test::NamedCase;
  std::vector<Case> cases;
  cases.push_back({"uniform", datasets::uniform(12000, 1), datasets::uniform(400, 2)});
  cases.push_back({"far queries", datasets::clustered(12000, 3, 8, 0.01f), datasets::clustered(400, 4, 8, 0.01f)});
  cases.push_back({"duplicates", datasets::with_duplicates(8000, 5, 0.3), {}});
  cases.back().qs.assign(cases.back().pts.begin(), cases.back().pts.begin() + 3 * 300);
  auto off = datasets::uniform(8000, 6, -10.0f, 10.0f);
  auto offq = datasets::uniform(300, 7, -10.0f, 10.0f);
  datasets::offset(off, 1e5, -3e4, 2e3);
  datasets::offset(offq, 1e5, -3e4, 2e3);
  cases.push_back({"offset", off, offq});
  auto plane = datasets::uniform(8000, 8);
  for (std::size_t i = 0; i < 8000; ++i) plane[3 * i + 2] = 0.25f;  // flat: a zero extent
  cases.push_back({"plane", plane, datasets::uniform(300, 9)});
  cases.push_back({"cornell", datasets::cornell_photons(15000, 10), datasets::cornell_queries(400, 11, 0.5f)});
  each_case_and_layout(cases, {"paper", "tables"}, [](const Case& c, const char*, const BlockHashIndex& index) {
    for (int k : {1, 10, 50}) {
      CAPTURE(k);
      SearchParams p = test::knn_params(k);
      p.A = k == 10 ? 8.0f : 2.5f;
      if (k == 1 && std::string(c.name) != "uniform") continue;  // a kernel variant of its own
      kernel_equals_reference(index, c.pts, c.qs, p);
    }
  });
}

TEST_CASE("blockhash_vs_reference: radius, k > N, probes on/off, box skip off, non-finite queries") {
  auto pts = datasets::clustered(6000, 21, 5, 0.02f);
  auto qs = datasets::clustered(300, 22, 5, 0.02f);
  auto a = BlockHashIndex::build(test::runtime(), pts.data(), 6000, layout("tables"));
  SearchParams p = test::knn_params(20);
  p.max_radius = 0.01f;
  kernel_equals_reference(*a, pts, qs, p);
  p.max_radius = INFINITY;
  p.neighbour_probes = 0;
  kernel_equals_reference(*a, pts, qs, p);
  auto paper = BlockHashIndex::build(test::runtime(), pts.data(), 6000, layout("paper"));
  p.neighbour_probes = 1;  // a paper index probes neighbours when asked
  kernel_equals_reference(*paper, pts, qs, p);
  p.neighbour_probes = 1;  // the near-side neighbours, within a radius too
  kernel_equals_reference(*a, pts, qs, p);
  p.max_radius = 0.01f;
  kernel_equals_reference(*a, pts, qs, p);
  p.max_radius = INFINITY;
  // Bucket order (the talk's scan) with and without box skipping.
  BlockHashBuildParams nb = layout("tables");
  nb.box_order = 0;
  nb.box_skip = 0;
  auto noskip = BlockHashIndex::build(test::runtime(), pts.data(), 6000, nb);
  p.neighbour_probes = -1;
  kernel_equals_reference(*noskip, pts, qs, p);
  nb.box_skip = 1;
  auto skip = BlockHashIndex::build(test::runtime(), pts.data(), 6000, nb);
  kernel_equals_reference(*skip, pts, qs, p);
  // k larger than N and a budget over everything: every point, -1/+inf after them.
  auto few = datasets::uniform(7, 3);
  auto tiny = BlockHashIndex::build(test::runtime(), few.data(), 7, layout("tables"));
  SearchParams big = test::knn_params(12);
  big.A = 32;
  KnnResult r = tiny->query(qs, big);
  for (std::size_t q = 0; q < 300; ++q) {
    REQUIRE(r.counts[q] <= 7);
    CHECK(r.id(q, 11) == -1);
    CHECK(std::isinf(r.d2(q, 7)));
  }
  kernel_equals_reference(*tiny, few, qs, big);
  std::vector<float> bad = {0.5f, NAN, 0.5f, 0.1f, 0.2f, 0.3f, INFINITY, 0.0f, 0.0f};
  QueryStats st;
  KnnResult rb = a->query(bad, p, &st);
  CHECK(st.nonfinite_queries == 2);
  CHECK(rb.counts[0] == 0);
  CHECK(rb.counts[1] == p.k);
  CHECK(rb.counts[2] == 0);
}

TEST_CASE("blockhash: with unlimited budget and buckets the answer is exact") {
  // B large enough to keep every block, A large: the candidates cover the query's cells and the
  // neighbours; on uniform data that contains the k nearest for nearly all queries.
  auto pts = datasets::uniform(5000, 31);
  auto qs = datasets::uniform(200, 32);
  BlockHashBuildParams bp = layout("tables");
  bp.B = 1000;
  bp.P = 3;  // big cells: 64 cells of ~80 points
  bp.hilbert_seed = 0;
  auto index = BlockHashIndex::build(test::runtime(), pts.data(), 5000, bp);
  SearchParams p = test::knn_params(5);
  p.A = 1000;
  KnnResult r = index->query(qs, p);
  KnnResult truth = reference::knn_float(pts.data(), 5000, qs.data(), 200, p);
  Accuracy acc = evaluate_accuracy(r, truth);
  CHECK(acc.recall > 0.97);
  // Far from the data every cell is empty: the Hilbert seed still gives k answers.
  std::vector<float> far = {5.0f, 5.0f, 5.0f, -3.0f, 0.5f, 0.5f};
  auto seeded = BlockHashIndex::build(test::runtime(), pts.data(), 5000, layout("tables"));
  KnnResult rf = seeded->query(far, p);
  CHECK(rf.counts[0] == 5);
  CHECK(rf.counts[1] == 5);
}

TEST_CASE("blockhash: recall does not fall as A grows, at a fixed build") {
  // Queries from the same clusters as the points (the first 20000 are the points).
  auto all = datasets::clustered(20500, 41, 10, 0.03f);
  std::vector<float> pts(all.begin(), all.begin() + 3 * 20000), qs(all.begin() + 3 * 20000, all.end());
  for (const char* pr : {"paper", "tables"}) {
    CAPTURE(pr);
    auto index = BlockHashIndex::build(test::runtime(), pts.data(), 20000, layout(pr));
    for (int k : {10, 50}) {
      SearchParams p = test::knn_params(k);
      KnnResult truth = reference::knn_float(pts.data(), 20000, qs.data(), 500, p);
      double last = -1;
      for (float A : {1.0f, 2.0f, 4.0f, 8.0f, 16.0f, 32.0f}) {
        p.A = A;
        KnnResult r = index->query(qs, p);
        double rec = evaluate_accuracy(r, truth).recall;
        CAPTURE(A);
        // The candidate order does not depend on A, so a larger budget scans a superset.
        CHECK(rec >= last);
        last = rec;
      }
      if (std::string(pr) == "tables") CHECK(last > 0.99);
    }
  }
}

TEST_CASE("blockhash: Cornell walls with queries just off the surface") {
  auto pts = datasets::cornell_photons(20000, 51);
  auto qs = datasets::cornell_queries(500, 52, 0.5f);
  SearchParams p = test::knn_params(10);
  p.A = 8;
  KnnResult truth = reference::knn_float(pts.data(), 20000, qs.data(), 500, p);
  auto a = BlockHashIndex::build(test::runtime(), pts.data(), 20000);  // auto: the grid
  REQUIRE(a->info().grid);
  KnnResult r = a->query(qs, p);
  Accuracy acc = evaluate_accuracy(r, truth);
  MESSAGE("auto on Cornell 20k, k=10 A=8: " << acc.summary() << "  " << a->info().summary());
  CHECK(acc.recall > 0.9);
  CHECK(acc.incomplete_queries == 0);
  CHECK(r.ids == a->reference_query(qs.data(), 500, p).ids);
  auto t = BlockHashIndex::build(test::runtime(), pts.data(), 20000, layout("tables"));
  const Accuracy at = evaluate_accuracy(t->query(qs, p), truth);
  MESSAGE("auto's L tables on Cornell 20k, k=10 A=8: " << at.summary() << "  " << t->info().summary());
  CHECK(at.incomplete_queries == 0);
  kernel_equals_reference(*t, pts, qs, p);
  // The guard matters at fine cells (P = 40, as at 1M points): without it the thresholds crowd
  // into the walls and the home cells of queries 0.5 mm off them are empty.
  auto empty_home = [&](const BlockHashIndex& idx) {
    const auto& s = idx.structure();
    int empty = 0;
    for (std::size_t i = 0; i < 500; ++i) {
      long b = s.find_bucket(0, s.point_cell(0, &qs[3 * i]));
      empty += (b < 0 || s.buckets[b].n_refs == 0) ? 1 : 0;
    }
    return empty / 500.0;
  };
  BlockHashBuildParams g = layout("tables");
  g.P = 40;
  g.B = 16;
  g.hilbert_seed = 0;
  BlockHashBuildParams ng = g;
  ng.guard_thresholds = 0;
  auto guarded = BlockHashIndex::build(test::runtime(), pts.data(), 20000, g);
  auto unguarded = BlockHashIndex::build(test::runtime(), pts.data(), 20000, ng);
  double eg = empty_home(*guarded), eu = empty_home(*unguarded);
  Accuracy ag = evaluate_accuracy(guarded->reference_query(qs.data(), 500, p), truth);
  Accuracy au = evaluate_accuracy(unguarded->reference_query(qs.data(), 500, p), truth);
  MESSAGE("P = 40: empty home cells guarded " << eg << " unguarded " << eu << "; recall " << ag.recall << " vs " << au.recall);
  CHECK(eg < eu);
  CHECK(ag.recall > au.recall);
}

TEST_CASE("blockhash: buffer-level call on the caller's queue and buffers") {
  auto rt = test::runtime();
  auto pts = datasets::uniform(4000, 61);
  auto qs = datasets::uniform(100, 62);
  auto index = BlockHashIndex::build(rt, pts.data(), 4000, layout("tables"));
  SearchParams p = test::knn_params(8);
  cl_int err = CL_SUCCESS;
  cl::Buffer qb(rt->context(), CL_MEM_READ_ONLY | CL_MEM_COPY_HOST_PTR, qs.size() * 4, qs.data(), &err);
  REQUIRE(err == CL_SUCCESS);
  ResultBuffers out{cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 8 * 4),
                    cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 8 * 4),
                    cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 4)};
  cl::CommandQueue queue(rt->context(), rt->device(), CL_QUEUE_PROFILING_ENABLE);
  cl::Event e = index->enqueue_query(queue, qb, 100, out, p);
  REQUIRE(e.wait() == CL_SUCCESS);
  std::vector<std::int32_t> ids(800);
  queue.enqueueReadBuffer(out.ids, CL_TRUE, 0, 800 * 4, ids.data());
  KnnResult ref = index->reference_query(qs.data(), 100, p);
  CHECK(ids == ref.ids);
  ResultBuffers small = out;
  small.ids = cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 16);
  CHECK_THROWS_WITH_AS(index->enqueue_query(queue, qb, 100, small, p), doctest::Contains("ids buffer"), Error);
  SearchParams bad = p;
  bad.A = -1;
  CHECK_THROWS_WITH_AS(index->query(qs, bad), doctest::Contains("A must be"), Error);
  bad = p;
  bad.neighbour_probes = 3;
  CHECK_THROWS_AS(index->query(qs, bad), Error);
  CHECK_THROWS_WITH_AS(BlockHashIndex::build(rt, pts.data(), 0), doctest::Contains("empty"), Error);
  pts[3 * 17 + 2] = NAN;
  CHECK_THROWS_WITH_AS(BlockHashIndex::build(rt, pts.data(), 4000), doctest::Contains("point 17"), Error);
}

TEST_CASE("blockhash: memory reporting and the talk's formula") {
  auto pts = datasets::uniform(20000, 71);
  auto paper = BlockHashIndex::build(test::runtime(), pts.data(), 20000, layout("paper"));
  const auto& s = paper->structure();
  CHECK(paper->memory_bytes() == s.device_bytes());
  CHECK(paper->memory_bytes() >= s.blocks.size() * 256 + s.refs.size() * 4);
  CHECK(paper->memory_per_point() > 16.0);
  double f = BlockHashIndex::talk_overhead(20000, 8, 10, 10);
  double l = std::log(20000.0);
  CHECK(f == doctest::Approx((4 * 8.0 * l * l * l + 12 * l * l + 1.6 * 20000) / (24.0 * 20000)));
  CHECK(paper->measured_overhead() > 0);
  MESSAGE("paper 20k: " << paper->info().summary() << "  memory/point " << paper->memory_per_point()
                        << "  overhead " << paper->measured_overhead() << " (talk " << f << ")");
}

TEST_CASE("blockhash: bhcl knn --method blockhash with presets and save/load") {
  auto pts = datasets::uniform(3000, 81);
  auto qs = datasets::uniform(50, 82);
  std::string P = test::tmp_path("bh_pts.f32"), Q = test::tmp_path("bh_q.f32");
  write_points_file(P, pts);
  write_points_file(Q, qs);
  std::string I1 = test::tmp_path("bh_ids1.i32"), I2 = test::tmp_path("bh_ids2.i32"),
              D = test::tmp_path("bh_d.f32"), IDX = test::tmp_path("bh_index.bin");
  std::string out;
  std::string common = "knn --points " + P + " --queries " + Q + " --k 7 --method blockhash --out-dist2 " + D;
  REQUIRE(test::run_bhcl(common + " --preset auto --A 4 --out-ids " + I1 + " --save-index " + IDX, &out) == 0);
  REQUIRE(test::run_bhcl(common + " --A 4 --out-ids " + I2 + " --load-index " + IDX, &out) == 0);
  CHECK(test::read_raw<std::int32_t>(I1) == test::read_raw<std::int32_t>(I2));
  REQUIRE(test::run_bhcl(common + " --preset paper --A 16 --L 5 --P 6 --B 4 --out-ids " + I2, &out) == 0);
  CHECK(out.find("blockhash") != std::string::npos);
  auto other = pts;
  other[3 * 100] += 0.25f;
  write_points_file(P, other);
  CHECK(test::run_bhcl(common + " --out-ids " + I2 + " --load-index " + IDX, &out) != 0);
  CHECK(out.find("point 100 differs") != std::string::npos);
  CHECK(test::run_bhcl(common + " --preset paper --P 0 --out-ids " + I2, &out) != 0);
  CHECK(out.find("P must be") != std::string::npos);
}

TEST_CASE("blockhash: a recall target is met on held-out queries") {
  // The index tunes A on a sample of its own points; queries it never saw must reach the target
  // within 0.01 (or above), for every preset and a spread of targets.
  using Set = test::NamedCase;
  std::vector<Set> sets;
  sets.push_back({"uniform", datasets::uniform(40000, 61), datasets::uniform(2000, 62)});
  sets.push_back({"cornell", datasets::cornell_photons(40000, 63), datasets::cornell_queries(2000, 64, 0.5f)});
  each_case_and_layout(sets, {"tables", "paper"}, [](const Set& set, const char* pr, BlockHashIndex& index) {
    for (double target : {0.9, 0.95, 0.99}) {
      CAPTURE(target);
      SearchParams p = test::knn_params(10);
      p.recall_target = target;
      BlockHashIndex::RecallTuning t = index.tune_for_recall(target, p);
      MESSAGE(std::string(set.name) << " " << std::string(pr) << " target " << target << ": A " << t.A << " sample recall "
                       << t.recall << std::string(t.reached ? "" : " (not reached)"));
      if (!t.reached) continue;  // paper's fixed buckets may cap recall below the target
      KnnResult r = index.query(set.qs, p);
      KnnResult truth = reference::knn_float(set.pts.data(), set.pts.size() / 3, set.qs.data(), 2000, p);
      double rec = evaluate_accuracy(r, truth).recall;
      CHECK(rec >= target - 0.01);
      // The query used the tuned A: the same answer as asking for that A.
      SearchParams a = p;
      a.recall_target = 0;
      a.A = t.A;
      CHECK(index.query(set.qs, a).ids == r.ids);
    }
    if (std::string(pr) == "tables") CHECK(index.tune_for_recall(0.95, SearchParams{}).reached);
  });
  SearchParams bad;
  bad.recall_target = 1.5;
  auto pts = datasets::uniform(1000, 65);
  auto index = BlockHashIndex::build(test::runtime(), pts.data(), 1000);
  CHECK_THROWS_WITH_AS(index->query(pts, bad), doctest::Contains("recall_target"), Error);
}

TEST_CASE("blockhash: sorted dispatch equals the caller's order, both L-table layouts, extreme scales, several dispatches") {
  auto rt = test::runtime();
  for (double scale : {1.0, 0x1p-70, 0x1p70}) {
    auto pts = datasets::clustered(6000, 71, 6, 0.02f);
    auto qs = datasets::clustered(900, 72, 6, 0.02f);
    for (auto& v : pts) v = static_cast<float>(v * scale);
    for (auto& v : qs) v = static_cast<float>(v * scale);
    qs[3 * 7 + 2] = INFINITY;  // a non-finite query keeps its row
    for (const char* name : {"tables", "paper"}) {
      CAPTURE(scale);
      CAPTURE(name);
      auto index = BlockHashIndex::build(rt, pts.data(), 6000, layout(name));
      SearchParams p = test::knn_params(9);
      p.count_examined = true;
      p.sort_queries = 0;
      KnnResult plain = index->query(qs, p);
      p.sort_queries = 1;
      for (std::size_t batch : {std::size_t(0), std::size_t(128)}) {
        p.max_batch = batch;
        KnnResult sorted = index->query(qs, p);
        CHECK(sorted.ids == plain.ids);
        CHECK(sorted.dist2 == plain.dist2);
        CHECK(sorted.counts == plain.counts);
        CHECK(sorted.examined == plain.examined);
      }
      CHECK(plain.counts[7] == 0);
    }
  }
}

TEST_CASE("blockhash: examined counts are an option of every query path (sorted, buffer-level)") {
  auto rt = test::runtime();
  auto pts = datasets::clustered(5000, 61, 6, 0.02f);
  auto qs = datasets::clustered(300, 62, 6, 0.02f);
  auto index = BlockHashIndex::build(rt, pts.data(), 5000, layout("tables"));
  SearchParams p = test::knn_params(10);
  p.count_examined = true;
  p.sort_queries = 0;
  KnnResult plain = index->query(qs, p);
  REQUIRE(plain.examined.size() == 300);
  std::vector<std::int32_t> ex_ref;
  index->reference_query(qs.data(), 300, p, &ex_ref);
  CHECK(plain.examined == ex_ref);
  // Dispatched in Hilbert order: the counts come back in the caller's order with their rows.
  p.sort_queries = 1;
  KnnResult sorted = index->query(qs, p);
  CHECK(sorted.ids == plain.ids);
  CHECK(sorted.examined == plain.examined);
  // The buffer-level call writes them to the caller's buffer.
  CHECK(test::buffer_query(*index, qs, p).examined == plain.examined);
  // Without the option nothing is counted; a missing buffer and an exact method are refused.
  p.count_examined = false;
  CHECK(index->query(qs, p).examined.empty());
  p.count_examined = true;
  cl::Buffer qb(rt->context(), CL_MEM_READ_ONLY | CL_MEM_COPY_HOST_PTR, qs.size() * 4, qs.data());
  ResultBuffers none{cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 300 * 10 * 4),
                     cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 300 * 10 * 4),
                     cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 300 * 4)};
  CHECK_THROWS_AS(index->enqueue_query(rt->queue(), qb, 300, none, p), Error);
  auto kd = make_index("kdtree", rt, pts.data(), 5000);
  CHECK_THROWS_WITH_AS(kd->query(qs, p), doctest::Contains("does not count"), Error);
}
