// FLANN (host) against brute force: bit-exact under the contract on the same point sets as the
// kd-tree kernel, whatever the thread count; the buffer-level call; bad input.
#include "test_util.hpp"

using namespace bhcl;

namespace bhcl::test {
// Defined in kdtree_vs_bruteforce.cpp: the point sets every exact method is checked on.
struct PointSet {
  std::string name;
  std::vector<float> points, queries;
};
std::vector<PointSet> exact_point_sets();
std::vector<float> queries_for(const std::vector<float>& pts, std::uint64_t seed, std::size_t each);
void require_identical(const KnnResult& r, const KnnResult& ref, const std::string& what);
void check_index_on_set(const Index& index, const PointSet& s);
}  // namespace bhcl::test

namespace {

void run_set(const std::string& name) {
  for (const auto& s : test::exact_point_sets()) {
    if (s.name != name) continue;
    FlannParams fp;
    fp.threads = 2;
    FlannIndex index(test::runtime(), s.points.data(), s.points.size() / 3, fp);
    test::check_index_on_set(index, s);
    return;
  }
  FAIL("no point set named " << name);
}

}  // namespace

TEST_CASE("flann_vs_bruteforce: uniform") { run_set("uniform"); }
TEST_CASE("flann_vs_bruteforce: clustered") { run_set("clustered"); }
TEST_CASE("flann_vs_bruteforce: 50% duplicates") { run_set("duplicates"); }
TEST_CASE("flann_vs_bruteforce: all points identical") { run_set("identical"); }
TEST_CASE("flann_vs_bruteforce: flat (z = const)") { run_set("flat"); }
TEST_CASE("flann_vs_bruteforce: collinear") { run_set("collinear"); }
TEST_CASE("flann_vs_bruteforce: offset by 1e4..1e6") { run_set("offset"); }

TEST_CASE("flann_vs_bruteforce: equals the brute-force kernel and the kd-tree kernel") {
  auto pts = datasets::with_duplicates(2500, 211, 0.3);
  auto qs = test::queries_for(pts, 212, 100);
  FlannIndex fl(test::runtime(), pts.data(), 2500);
  BruteForceIndex bf(test::runtime(), pts.data(), 2500);
  KdTreeIndex kd(test::runtime(), pts.data(), 2500);
  for (int k : {1, 10, 200}) {
    CAPTURE(k);
    SearchParams p;
    p.k = k;
    KnnResult f = fl.query(qs, p);
    test::require_identical(f, bf.query(qs, p), "flann vs bruteforce kernel");
    test::require_identical(f, kd.query(qs, p), "flann vs kdtree kernel");
  }
}

TEST_CASE("flann: results do not depend on the thread count") {
  auto pts = datasets::clustered(3000, 221, 6, 0.01f);
  auto qs = datasets::uniform(2000, 222);  // > one 256-query chunk per thread
  SearchParams p;
  p.k = 12;
  FlannParams one;
  one.threads = 1;
  FlannIndex base(test::runtime(), pts.data(), 3000, one);
  KnnResult ref = base.query(qs, p);
  CHECK(base.threads() == 1);
  for (int t : {2, 3, 8}) {
    CAPTURE(t);
    FlannParams fp;
    fp.threads = t;
    FlannIndex index(test::runtime(), pts.data(), 3000, fp);
    CHECK(index.threads() == t);
    test::require_identical(index.query(qs, p), ref, "threads");
  }
  MethodOptions mo;
  mo.threads = 3;
  auto viaf = make_index("flann", test::runtime(), pts.data(), 3000, mo);
  CHECK(viaf->method() == "flann");
  CHECK(viaf->exact());
  CHECK(dynamic_cast<const FlannIndex&>(*viaf).threads() == 3);
}

TEST_CASE("flann: k > N, radius 0, overflowing distances, non-finite queries") {
  {
    auto pts = datasets::uniform(5, 231);
    auto qs = datasets::uniform(20, 232);
    FlannIndex index(test::runtime(), pts.data(), 5);
    SearchParams p;
    p.k = 32;
    KnnResult r = index.query(qs, p);
    test::require_identical(r, reference::knn_float(pts.data(), 5, qs.data(), 20, p), "k > N");
    for (auto c : r.counts) CHECK(c == 5);
  }
  {
    auto pts = datasets::with_duplicates(1000, 233, 0.5);
    std::vector<float> on(pts.begin(), pts.begin() + 3 * 40);
    FlannIndex index(test::runtime(), pts.data(), 1000);
    SearchParams p;
    p.k = 16;
    p.max_radius = 0.0f;
    test::require_identical(index.query(on, p), reference::knn_float(pts.data(), 1000, on.data(), 40, p),
                            "radius 0");
  }
  {
    std::vector<float> pts = {0.0f, 0.0f, 0.0f, 3e19f, 0.0f, 0.0f, -3e19f, 1e19f, 0.0f,
                              1.0f, 1.0f, 1.0f, 0.0f, -3e19f, 2e19f};
    std::vector<float> qs = {0.5f, 0.5f, 0.5f, -3e19f, -3e19f, 0.0f};
    // Extreme scale: ordered by the true distances, distances +inf (knn.hpp, "Extreme scales").
    FlannIndex index(test::runtime(), pts.data(), 5);
    BruteForceIndex brute(test::runtime(), pts.data(), 5);
    SearchParams p;
    p.k = 5;
    KnnResult r = index.query(qs, p);
    test::require_identical(r, brute.query(qs, p), "overflowing distances");
    test::check_exact_vs_double(r, pts.data(), 5, qs.data(), 2, p);
  }
  {
    auto pts = datasets::uniform(500, 234);
    std::vector<float> qs = datasets::uniform(4, 235);
    qs[3 * 0 + 1] = NAN;
    qs[3 * 2 + 2] = INFINITY;
    FlannIndex index(test::runtime(), pts.data(), 500);
    SearchParams p;
    p.k = 5;
    QueryStats st;
    KnnResult r = index.query(qs, p, &st);
    CHECK(st.nonfinite_queries == 2);
    CHECK(st.n_queries == 4);
    CHECK(st.batches == 0);
    CHECK(r.counts == std::vector<std::int32_t>{0, 5, 0, 5});
    CHECK(r.id(0, 0) == -1);
  }
}

TEST_CASE("flann: buffer-level call answers on the host into the caller's buffers") {
  auto rt = test::runtime();
  auto pts = datasets::uniform(1500, 241);
  auto qs = datasets::uniform(100, 242);
  FlannIndex index(rt, pts.data(), 1500);
  SearchParams p;
  p.k = 8;
  p.max_batch = 30;  // several host round trips, each on its own rows
  cl::Buffer qb(rt->context(), CL_MEM_READ_ONLY | CL_MEM_COPY_HOST_PTR, qs.size() * 4, qs.data());
  ResultBuffers out{cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 8 * 4),
                    cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 8 * 4),
                    cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 100 * 4)};
  cl::Event e = index.enqueue_query(rt->queue(), qb, 100, out, p);
  std::vector<cl::Event> wait{e};
  std::vector<int> ids(800), counts(100);
  std::vector<float> d2(800);
  rt->queue().enqueueReadBuffer(out.ids, CL_TRUE, 0, 800 * 4, ids.data(), &wait);
  rt->queue().enqueueReadBuffer(out.dist2, CL_TRUE, 0, 800 * 4, d2.data(), &wait);
  rt->queue().enqueueReadBuffer(out.counts, CL_TRUE, 0, 100 * 4, counts.data(), &wait);
  KnnResult ref = reference::knn_float(pts.data(), 1500, qs.data(), 100, p);
  CHECK(ids == ref.ids);
  CHECK(d2 == ref.dist2);
  CHECK(counts == ref.counts);
}

TEST_CASE("flann: bad input is refused with a clear error") {
  auto rt = test::runtime();
  std::vector<float> pts = datasets::uniform(10, 251);
  CHECK_THROWS_WITH_AS(FlannIndex(rt, pts.data(), 0), doctest::Contains("empty"), Error);
  CHECK_THROWS_WITH_AS(FlannIndex(nullptr, pts.data(), 10), doctest::Contains("runtime"), Error);
  FlannParams bad;
  bad.threads = -1;
  CHECK_THROWS_WITH_AS(FlannIndex(rt, pts.data(), 10, bad), doctest::Contains("threads"), Error);
  pts[3 * 2 + 0] = NAN;
  CHECK_THROWS_WITH_AS(FlannIndex(rt, pts.data(), 10), doctest::Contains("point 2"), Error);
  pts[3 * 2 + 0] = 0.5f;
  FlannIndex index(rt, pts.data(), 10);
  SearchParams p;
  p.k = 0;
  CHECK_THROWS_WITH_AS(index.query(pts, p), doctest::Contains("k = 0"), Error);
  p.k = 3;
  p.max_radius = -2.0f;
  CHECK_THROWS_WITH_AS(index.query(pts, p), doctest::Contains("max_radius"), Error);
}
