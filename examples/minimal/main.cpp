// The smallest use of blockhash_cl: points (from a file in any supported format, or random),
// a block-hash index and an exact kd-tree, the 8 nearest neighbours of a few queries by both,
// and the recall of the approximate answer. Exits non-zero if the library misbehaves.
#include <blockhash_cl/blockhash_cl.hpp>

#include <cstdio>
#include <algorithm>
#include <exception>
#include <memory>
#include <random>
#include <vector>

int main(int argc, char** argv) try {
  std::vector<float> points;
  if (argc > 1) {
    points = bhcl::read_points_file(argv[1]);  // PLY, NPY, text or raw float32
  } else {
    std::mt19937 rng(1);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    points.resize(3 * 20000);
    for (float& v : points) v = u(rng);
  }
  const std::size_t N = points.size() / 3;
  std::vector<float> queries(points.begin(), points.begin() + 3 * std::min<std::size_t>(N, 100));
  const std::size_t n = queries.size() / 3;

  auto rt = std::make_shared<bhcl::Runtime>();  // BHCL_DEVICE, else PoCL
  auto approx = bhcl::BlockHashIndex::build(rt, points.data(), N, bhcl::BlockHashBuildParams{});
  bhcl::KdTreeIndex exact(rt, points.data(), N);
  bhcl::SearchParams p;
  p.k = 8;
  p.A = 8;  // block hashing examines at most A*k points per query
  bhcl::KnnResult a = approx->query(queries, p);
  bhcl::KnnResult e = exact.query(queries, p);
  const bhcl::Accuracy acc = bhcl::evaluate_accuracy(a, e);
  std::printf("blockhash_cl %s on %s: N=%zu n=%zu k=%d: recall %.4f; query 0's nearest: %d (d2 %g)\n",
              BHCL_VERSION_STRING, rt->info().device_name.c_str(), N, n, p.k, acc.recall, e.id(0, 0),
              static_cast<double>(e.d2(0, 0)));
  // Each query is one of the points: its nearest neighbour is itself, at distance 0.
  return e.counts[0] == p.k && e.d2(0, 0) == 0.0f && acc.recall > 0.5 ? 0 : 1;
} catch (const std::exception& ex) {
  std::fprintf(stderr, "minimal: %s\n", ex.what());
  return 1;
}
