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
// The centres come from centre_seed, the points from seed: sets with the same centre_seed (and
// another seed) are drawn from the same distribution, e.g. points and their queries.
std::vector<float> clustered(std::size_t n, std::uint64_t seed, int clusters = 16,
                             float sigma = 0.01f, std::uint64_t centre_seed = 0x5eed);

// N points of which about `fraction` are exact copies of other points of the set.
std::vector<float> with_duplicates(std::size_t n, std::uint64_t seed, double fraction);

// Adds (dx, dy, dz) to every point (offset data for numerical stress).
void offset(std::vector<float>& xyz, double dx, double dy, double dz);

// A photon-map-like set on the Cornell Box surfaces (cornell_box.hpp, mm; docs/ACCURACY.md,
// "Photon-map-like data"): half the points uniform by area over the 5 walls and the 2 blocks, half where
// rays from the light's centre, drawn from a cos^8 lobe around straight down, first hit the
// scene; about 1 % exact duplicates. Not photon tracing (the renderer does that): a stand-in with
// the same planar, uneven, coincident structure.
std::vector<float> cornell_photons(std::size_t n, std::uint64_t seed);

// Query points drawn like cornell_photons, then moved offset_mm off the surface along its normal
// (into the room): the case where planar data defeats naive thresholds.
std::vector<float> cornell_queries(std::size_t n, std::uint64_t seed, float offset_mm = 0.5f);

// Generates by name: "uniform", "clustered", "duplicates" (10 % exact duplicates), "cornell".
std::vector<float> by_name(const std::string& name, std::size_t n, std::uint64_t seed);

// Query points for a named set: like the points, except "cornell" (0.5 mm off the surfaces).
std::vector<float> queries_by_name(const std::string& name, std::size_t n, std::uint64_t seed);

}  // namespace bhcl::datasets
