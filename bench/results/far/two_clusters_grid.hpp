// The data of the far callgrind programs beside this file (callgrind_harness.cpp,
// perfect_bound_ceiling.cpp): far_bench's two clusters (60000 points, Gaussian sigma 0.01 at
// x = 0 and 1) with nq queries between them, and their grid built on one thread with its pyramid.
#pragma once
#include <random>
#include <vector>
#include "blockhash/grid.hpp"

inline void two_clusters(std::size_t nq, std::vector<float>& pts, std::vector<float>& q) {
  const std::size_t n = 60000;
  std::mt19937_64 rng(11);
  std::normal_distribution<float> gd(0.0f, 0.01f);
  pts.assign(3 * n, 0.0f);
  q.assign(3 * nq, 0.0f);
  for (std::size_t i = 0; i < n; ++i) { pts[3*i] = gd(rng) + (i % 2 ? 1.0f : 0.0f); pts[3*i+1] = gd(rng); pts[3*i+2] = gd(rng); }
  std::uniform_real_distribution<float> ux(0.1f, 0.9f), uyz(-0.05f, 0.05f);
  for (std::size_t i = 0; i < nq; ++i) q[3*i] = ux(rng), q[3*i+1] = uyz(rng), q[3*i+2] = uyz(rng);
}

inline void build_clusters_grid(const std::vector<float>& pts, double target_cell_points, bhcl::blockhash::Grid& g) {
  using namespace bhcl::blockhash;
  GridInput in; in.xyz = pts.data(); in.n_aos = pts.size() / 3;
  GridBuildArgs a; a.target_cell_points = target_cell_points; a.threads = 1;
  GridBuildStats st; build_grid(in, a, g, &st);
  build_grid_occupancy(g, 1);
}
