// MPI plumbing of the distributed index: a wall clock, the all-to-all exchange of fixed-size
// records, and the rule that keeps every collective step failure-safe (mpi_agree after each
// phase of local work, so that no rank is left in a collective another rank never reaches).
#pragma once

#include <mpi.h>

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace bhcl::distributed {

class Stopwatch {
 public:
  double seconds() const {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0_).count();
  }

 private:
  std::chrono::steady_clock::time_point t0_ = std::chrono::steady_clock::now();
};

// Collective all-to-all of records of `record_bytes` bytes. `send` holds the records grouped by
// destination rank in rank order, send_counts[r] of them for rank r. Returns the records received,
// grouped by source rank in rank order; recv_counts gets how many came from each rank. Counts
// above what MPI's int counts allow make it throw on every rank (mpi_agree), naming `what`.
std::vector<unsigned char> exchange(MPI_Comm comm, const void* send,
                                    const std::vector<std::size_t>& send_counts,
                                    std::size_t record_bytes, std::vector<std::size_t>& recv_counts,
                                    const std::string& what);

}  // namespace bhcl::distributed
