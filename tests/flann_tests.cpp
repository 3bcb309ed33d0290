// What only FLANN has: its thread count and its constructor checks. Its answers are checked with
// every exact method in exact_methods_vs_bruteforce.cpp.
#include "test_util.hpp"

using namespace bhcl;

TEST_CASE("flann: results do not depend on the thread count") {
  auto pts = datasets::clustered(3000, 221, 6, 0.01f);
  auto qs = datasets::uniform(2000, 222);  // > one 256-query chunk per thread
  SearchParams p = test::knn_params(12);
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
  mo.set("threads", "3");
  auto viaf = make_index("flann", test::runtime(), pts.data(), 3000, mo);
  CHECK(viaf->method() == "flann");
  CHECK(viaf->exact());
  CHECK(dynamic_cast<const FlannIndex&>(*viaf).threads() == 3);
}

TEST_CASE("flann: a null runtime or a negative thread count is refused") {
  auto rt = test::runtime();
  std::vector<float> pts = datasets::uniform(10, 251);
  CHECK_THROWS_WITH_AS(FlannIndex(rt, pts.data(), 0), doctest::Contains("empty"), Error);
  CHECK_THROWS_WITH_AS(FlannIndex(nullptr, pts.data(), 10), doctest::Contains("runtime"), Error);
  FlannParams bad;
  bad.threads = -1;
  CHECK_THROWS_WITH_AS(FlannIndex(rt, pts.data(), 10, bad), doctest::Contains("threads"), Error);
}
