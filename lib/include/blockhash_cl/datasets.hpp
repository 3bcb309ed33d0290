// Generated point sets for the demo, the tests and the benchmarks (seeded, reproducible).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace bhcl::datasets {

// N points uniform in the cube [lo, hi]^3.
std::vector<float> uniform(std::size_t n, std::uint64_t seed, float lo = 0.0f, float hi = 1.0f);

// N points in `clusters` Gaussian blobs of standard deviation sigma, centres uniform in [0,1]^3.
std::vector<float> clustered(std::size_t n, std::uint64_t seed, int clusters = 16,
                             float sigma = 0.01f);

// N points of which about `fraction` are exact copies of other points of the set.
std::vector<float> with_duplicates(std::size_t n, std::uint64_t seed, double fraction);

// Adds (dx, dy, dz) to every point (offset data for numerical stress).
void offset(std::vector<float>& xyz, double dx, double dy, double dz);

// Generates by name: "uniform", "clustered", "duplicates" (10 % exact duplicates).
std::vector<float> by_name(const std::string& name, std::size_t n, std::uint64_t seed);

}  // namespace bhcl::datasets
