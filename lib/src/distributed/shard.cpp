#include "distributed/shard.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>

namespace bhcl::distributed {

blockhash::Quantiser global_quantiser(MPI_Comm comm, const float* xyz, std::size_t n) {
  // min of (lo, -hi) in one allreduce; doubles hold every float exactly.
  double local[6], global[6];
  for (int d = 0; d < 3; ++d) local[d] = local[3 + d] = std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < n; ++i)
    for (int d = 0; d < 3; ++d) {
      const double v = xyz[3 * i + d];
      local[d] = std::min(local[d], v);
      local[3 + d] = std::min(local[3 + d], -v);
    }
  MPI_Allreduce(local, global, 6, MPI_DOUBLE, MPI_MIN, comm);
  // The same rule as blockhash::make_quantiser (one scale for all axes, the largest extent), on
  // the global box.
  blockhash::Quantiser q;
  q.bits = kKeyBits;
  double extent = 0;
  for (int d = 0; d < 3; ++d) {
    q.origin[d] = std::isfinite(global[d]) ? global[d] : 0.0;
    if (std::isfinite(global[d])) extent = std::max(extent, -global[3 + d] - global[d]);
  }
  q.scale = extent > 0 ? std::ldexp(1.0, kKeyBits) / extent : 0.0;
  return q;
}

std::vector<Composite> find_splitters(MPI_Comm comm, const std::vector<Composite>& sorted_local,
                                      std::uint64_t n_global) {
  int ranks = 1;
  MPI_Comm_size(comm, &ranks);
  const std::size_t R = static_cast<std::size_t>(ranks);
  // splitter r: the smallest v with #{elements <= v} >= t_r + 1, t_r = floor(r N / R).
  std::vector<std::uint64_t> target(R);
  for (std::size_t r = 0; r < R; ++r) target[r] = (n_global * r) / R + 1;
  const Composite top = (Composite(1) << (3 * kKeyBits + kPositionBits)) - 1;  // every composite is <= top
  std::vector<Composite> lo(R, 0), hi(R, top), mid(R);
  std::vector<std::uint64_t> local(R), global(R);
  for (;;) {
    // Every rank takes the same branches: lo and hi only change with the global counts.
    bool open = false;
    for (std::size_t r = 0; r < R; ++r) {
      open = open || lo[r] < hi[r];
      mid[r] = lo[r] + (hi[r] - lo[r]) / 2;
      local[r] = static_cast<std::uint64_t>(
          std::upper_bound(sorted_local.begin(), sorted_local.end(), mid[r]) - sorted_local.begin());
    }
    if (!open) break;
    MPI_Allreduce(local.data(), global.data(), ranks, MPI_UINT64_T, MPI_SUM, comm);
    for (std::size_t r = 0; r < R; ++r) {
      if (lo[r] >= hi[r]) continue;
      if (global[r] >= target[r]) hi[r] = mid[r];
      else lo[r] = mid[r] + 1;
    }
  }
  return lo;
}

std::vector<Box> run_boxes(const float* xyz, std::size_t n, std::size_t count) {
  count = std::min(count, n);
  std::vector<Box> boxes(count);
  for (std::size_t j = 0; j < count; ++j) {
    Box& b = boxes[j];
    for (int d = 0; d < 3; ++d) {
      b.lo[d] = std::numeric_limits<float>::infinity();
      b.hi[d] = -std::numeric_limits<float>::infinity();
    }
    const std::size_t first = j * n / count, end = (j + 1) * n / count;
    for (std::size_t i = first; i < end; ++i)
      for (int d = 0; d < 3; ++d) {
        b.lo[d] = std::min(b.lo[d], xyz[3 * i + d]);
        b.hi[d] = std::max(b.hi[d], xyz[3 * i + d]);
      }
  }
  return boxes;
}

Box union_box(const std::vector<Box>& boxes) {
  Box u;
  for (int d = 0; d < 3; ++d) {
    u.lo[d] = std::numeric_limits<float>::infinity();
    u.hi[d] = -std::numeric_limits<float>::infinity();
  }
  for (const Box& b : boxes)
    for (int d = 0; d < 3; ++d) {
      u.lo[d] = std::min(u.lo[d], b.lo[d]);
      u.hi[d] = std::max(u.hi[d], b.hi[d]);
    }
  return u;
}

bool box_may_hold(const Box& b, const float q[3], double bound) {
  if (!(bound < std::numeric_limits<double>::infinity())) return true;
  double d2 = 0;
  for (int d = 0; d < 3; ++d) {
    const double g = std::max({double(b.lo[d]) - double(q[d]), double(q[d]) - double(b.hi[d]), 0.0});
    d2 += g * g;
  }
  return d2 <= bound * (1.0 + 1e-5) + 1e-43;
}

std::string nonfinite_point(const float* points, std::size_t n, std::int64_t first_id, const char* label) {
  for (std::size_t i = 0; i < n; ++i) {
    const float* p = points + 3 * i;
    if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) {
      std::ostringstream os;
      os << label << ": point " << first_id + static_cast<std::int64_t>(i) << " (this rank's point " << i
         << ") has a non-finite coordinate (" << p[0] << ", " << p[1] << ", " << p[2] << ")";
      return os.str();
    }
  }
  return {};
}

}  // namespace bhcl::distributed
