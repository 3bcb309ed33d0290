// Sharding by Hilbert-key range: the global quantiser, the count-balanced splitters, the boxes a
// rank shares, and the conservative ball-box test that decides which ranks a query visits.
#pragma once

#include <mpi.h>

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "blockhash/build.hpp"
#include "blockhash_cl/distributed.hpp"

namespace bhcl::distributed {

// Hilbert keys take 3 x 21 = 63 bits; a point's place in the global order is the composite
// (key << 40) | position, unique per point (positions over all ranks, from 0, are below 2^40:
// kMaxPoints; global ids add DistributedBuildParams::id_base only on the way out).
using Composite = unsigned __int128;
inline constexpr int kKeyBits = 21;
inline constexpr int kPositionBits = 40;
inline constexpr std::uint64_t kMaxPoints = (std::uint64_t(1) << kPositionBits) - 1;
inline Composite composite(std::uint64_t key, std::uint64_t position) {
  return (Composite(key) << kPositionBits) | position;
}
inline std::uint64_t key_of(Composite c) { return static_cast<std::uint64_t>(c >> kPositionBits); }
inline std::uint64_t position_of(Composite c) { return static_cast<std::uint64_t>(c) & kMaxPoints; }

// The quantiser of the block-hash build over the bounding box of every rank's points (collective:
// one allreduce). Every rank gets the same one, so a position has the same key everywhere.
blockhash::Quantiser global_quantiser(MPI_Comm comm, const float* xyz, std::size_t n);

inline std::uint64_t hilbert_key(const blockhash::Quantiser& q, const float* p) {
  return blockhash::hilbert_encode(q.cell(0, p[0]), q.cell(1, p[1]), q.cell(2, p[2]), q.bits);
}

// Collective. `sorted_local`: this rank's composites, ascending. Returns R splitters: splitter[r]
// is the element of global rank floor(r * n_global / R) in the order of all composites, so that
// rank r's shard, [splitter[r], splitter[r + 1]), holds floor((r+1) N / R) - floor(r N / R)
// points (an empty shard where two splitters coincide). Found by bisection on the composite's
// value with one allreduce of R counts per step (103 steps), so it is exact and deterministic and
// moves no points.
std::vector<Composite> find_splitters(MPI_Comm comm, const std::vector<Composite>& sorted_local,
                                      std::uint64_t n_global);

using Box = ShardBox;
// The boxes of min(count, n) consecutive, equally long runs of n points (xyz in the order to cut).
std::vector<Box> run_boxes(const float* xyz, std::size_t n, std::size_t count);
Box union_box(const std::vector<Box>& boxes);

// True when some point of `b` could be at a float squared distance <= bound from q under the
// contract's arithmetic (knn.hpp). The box distance is taken in double and compared with a margin
// that covers the float rounding of the point distance (a relative 1e-5, far above the 5 ulp of
// the contract's sum, and an absolute 1e-43 for subnormal results), so a box is never skipped
// when one of its points would make the k best; an extra box only costs a visit.
bool box_may_hold(const Box& b, const float q[3], double bound);

// The first of this rank's n points with a NaN/Inf coordinate, "<label>: point G (this rank's
// point i) has a non-finite coordinate (x, y, z)", G its global id (the first point's is
// first_id); empty when every point is finite. The build's and the insert's check.
std::string nonfinite_point(const float* points, std::size_t n, std::int64_t first_id, const char* label);

}  // namespace bhcl::distributed
