#include "blockhash_cl/datasets.hpp"

#include <random>

#include "blockhash_cl/error.hpp"

namespace bhcl::datasets {

std::vector<float> uniform(std::size_t n, std::uint64_t seed, float lo, float hi) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(lo, hi);
  std::vector<float> xyz(3 * n);
  for (auto& v : xyz) v = u(rng);
  return xyz;
}

std::vector<float> clustered(std::size_t n, std::uint64_t seed, int clusters, float sigma) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::normal_distribution<float> g(0.0f, sigma);
  std::vector<float> centres(3 * static_cast<std::size_t>(clusters));
  for (auto& c : centres) c = u(rng);
  std::uniform_int_distribution<int> pick(0, clusters - 1);
  std::vector<float> xyz(3 * n);
  for (std::size_t i = 0; i < n; ++i) {
    int c = pick(rng);
    for (int d = 0; d < 3; ++d) xyz[3 * i + d] = centres[3 * c + d] + g(rng);
  }
  return xyz;
}

std::vector<float> with_duplicates(std::size_t n, std::uint64_t seed, double fraction) {
  std::vector<float> xyz = uniform(n, seed);
  std::mt19937_64 rng(seed ^ 0x9e3779b97f4a7c15ull);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  for (std::size_t i = 1; i < n; ++i) {
    if (u(rng) < fraction) {
      std::size_t src = std::uniform_int_distribution<std::size_t>(0, i - 1)(rng);
      for (int d = 0; d < 3; ++d) xyz[3 * i + d] = xyz[3 * src + d];
    }
  }
  return xyz;
}

void offset(std::vector<float>& xyz, double dx, double dy, double dz) {
  for (std::size_t i = 0; i + 2 < xyz.size(); i += 3) {
    xyz[i] = static_cast<float>(xyz[i] + dx);
    xyz[i + 1] = static_cast<float>(xyz[i + 1] + dy);
    xyz[i + 2] = static_cast<float>(xyz[i + 2] + dz);
  }
}

std::vector<float> by_name(const std::string& name, std::size_t n, std::uint64_t seed) {
  if (name == "uniform") return uniform(n, seed);
  if (name == "clustered") return clustered(n, seed);
  if (name == "duplicates") return with_duplicates(n, seed, 0.10);
  throw Error("unknown data set '" + name + "' (uniform, clustered, duplicates)");
}

}  // namespace bhcl::datasets
