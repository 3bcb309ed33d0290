// The ikd-Tree baseline's wrapper (see ikdtree_baseline.hpp): the only file that includes its header.
#include "ikdtree_baseline.hpp"

#include <algorithm>
#include <thread>

#include <ikd_Tree.h>

namespace bhcl::bench {

using Point = ikdTree_PointType;
using Tree = KD_TREE<Point>;

struct IkdTree::Impl {
  // ikd-Tree's defaults as FAST-LIO2 sets them (delete 0.5, balance 0.6); the downsampling box is
  // unused (every add passes downsample_on = false).
  Tree tree{0.5f, 0.6f, 0.2f};
};

namespace {
Tree::PointVector to_points(const float* xyz, std::size_t n) {
  Tree::PointVector v;
  v.reserve(n);
  for (std::size_t i = 0; i < n; ++i) v.emplace_back(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]);
  return v;
}
}  // namespace

IkdTree::IkdTree() : impl_(std::make_unique<Impl>()) {}
IkdTree::~IkdTree() = default;

void IkdTree::build(const float* xyz, std::size_t n) { impl_->tree.Build(to_points(xyz, n)); }

void IkdTree::add(const float* xyz, std::size_t n) {
  Tree::PointVector v = to_points(xyz, n);
  impl_->tree.Add_Points(v, false);
}

void IkdTree::remove(const float* xyz, std::size_t n) {
  Tree::PointVector v = to_points(xyz, n);
  impl_->tree.Delete_Points(v);
}

void IkdTree::query(const std::vector<float>& qs, int k, int threads, std::vector<float>& xyz, std::vector<float>& dist2,
                    std::vector<int>& counts) {
  const std::size_t n = qs.size() / 3, K = std::size_t(k);
  xyz.assign(3 * n * K, 0.0f);
  dist2.assign(n * K, 0.0f);
  counts.assign(n, 0);
  // Nearest_Search may run concurrently (FAST-LIO2 calls it from an OpenMP loop; a rebuild in its
  // own thread is fenced by the tree's search mutex).
  auto run = [&](std::size_t b, std::size_t e) {
    Tree::PointVector found;
    std::vector<float> d;
    for (std::size_t i = b; i < e; ++i) {
      impl_->tree.Nearest_Search(Point(qs[3 * i], qs[3 * i + 1], qs[3 * i + 2]), k, found, d);
      const std::size_t c = std::min(K, found.size());
      for (std::size_t j = 0; j < c; ++j) {
        xyz[3 * (i * K + j)] = found[j].x;
        xyz[3 * (i * K + j) + 1] = found[j].y;
        xyz[3 * (i * K + j) + 2] = found[j].z;
        dist2[i * K + j] = d[j];
      }
      counts[i] = int(c);
    }
  };
  std::vector<std::thread> pool;
  const std::size_t T = std::size_t(std::max(1, threads));
  for (std::size_t t = 0; t < T; ++t) pool.emplace_back(run, n * t / T, n * (t + 1) / T);
  for (auto& th : pool) th.join();
}

std::size_t IkdTree::size() { return std::size_t(impl_->tree.validnum()); }

}  // namespace bhcl::bench
