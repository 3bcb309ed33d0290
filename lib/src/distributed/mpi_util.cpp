#include "distributed/mpi_util.hpp"

#include "distributed/agreement.hpp"

#include <algorithm>
#include <climits>
#include <cstring>

#include "blockhash_cl/distributed.hpp"
#include "blockhash_cl/error.hpp"

namespace bhcl {

void mpi_agree(MPI_Comm comm, const std::string& local_error, const std::string& what) {
  int rank = 0;
  MPI_Comm_rank(comm, &rank);
  distributed::gate(comm, what);  // a rank that stops answering ends the job, named (issue 22)
  // One allreduce when every rank succeeded (the common case); the failure path adds a count and
  // the first failing rank's message, which every rank reaches because every rank saw the flag.
  int mine = local_error.empty() ? INT_MAX : rank;
  int first = INT_MAX;
  MPI_Allreduce(&mine, &first, 1, MPI_INT, MPI_MIN, comm);
  if (first == INT_MAX) return;
  int failed_here = local_error.empty() ? 0 : 1, failed = 0;
  MPI_Allreduce(&failed_here, &failed, 1, MPI_INT, MPI_SUM, comm);
  int len = rank == first ? static_cast<int>(std::min<std::size_t>(local_error.size(), 1 << 16)) : 0;
  MPI_Bcast(&len, 1, MPI_INT, first, comm);
  std::string msg(static_cast<std::size_t>(len), '\0');
  if (rank == first) std::memcpy(msg.data(), local_error.data(), msg.size());
  if (len > 0) MPI_Bcast(msg.data(), len, MPI_CHAR, first, comm);
  std::string text = what + ": rank " + std::to_string(first) + ": " + msg;
  if (failed > 1)
    text += " (and " + std::to_string(failed - 1) + " other rank" + (failed > 2 ? "s" : "") + " failed)";
  throw Error(text);
}

namespace distributed {

std::vector<unsigned char> exchange(MPI_Comm comm, const void* send,
                                    const std::vector<std::size_t>& send_counts,
                                    std::size_t record_bytes, std::vector<std::size_t>& recv_counts,
                                    const std::string& what) {
  int ranks = 1;
  MPI_Comm_size(comm, &ranks);
  const std::size_t R = static_cast<std::size_t>(ranks);
  std::vector<std::uint64_t> sc(send_counts.begin(), send_counts.end()), rc(R, 0);
  MPI_Alltoall(sc.data(), 1, MPI_UINT64_T, rc.data(), 1, MPI_UINT64_T, comm);
  recv_counts.assign(rc.begin(), rc.end());
  // MPI counts and displacements are ints, in records of the contiguous type below.
  std::uint64_t total_send = 0, total_recv = 0;
  for (std::size_t r = 0; r < R; ++r) total_send += sc[r], total_recv += rc[r];
  std::string err;
  if (total_send > INT_MAX || total_recv > INT_MAX || record_bytes > INT_MAX)
    err = what + ": " + std::to_string(total_send) + " records out, " + std::to_string(total_recv) +
          " in, more than one MPI call carries (2^31 - 1): use more ranks";
  mpi_agree(comm, err, "DistributedIndex");
  std::vector<int> scount(R), sdispl(R), rcount(R), rdispl(R);
  int so = 0, ro = 0;
  for (std::size_t r = 0; r < R; ++r) {
    scount[r] = static_cast<int>(sc[r]);
    rcount[r] = static_cast<int>(rc[r]);
    sdispl[r] = so;
    rdispl[r] = ro;
    so += scount[r];
    ro += rcount[r];
  }
  std::vector<unsigned char> recv(static_cast<std::size_t>(total_recv) * record_bytes);
  MPI_Datatype rec;
  MPI_Type_contiguous(static_cast<int>(record_bytes), MPI_BYTE, &rec);
  MPI_Type_commit(&rec);
  // MPI wants non-null buffers on some implementations even for zero counts.
  static unsigned char dummy[1];
  MPI_Alltoallv(send ? send : dummy, scount.data(), sdispl.data(), rec,
                recv.empty() ? dummy : recv.data(), rcount.data(), rdispl.data(), rec, comm);
  MPI_Type_free(&rec);
  return recv;
}

}  // namespace distributed
}  // namespace bhcl
