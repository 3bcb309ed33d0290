// What keeps a distributed job from being silently wrong or hung (issue 22):
//  - parameter agreement: every rank's build and search parameters, as (name, value) text, are
//    checked against rank 0's by one allreduce of a hash (the common case costs that alone); when
//    they differ every rank throws the same bhcl::Error naming the first differing rank, the
//    parameter and both values ("rank 2 has method = bruteforce where rank 0 has kdtree");
//  - a deadline on every collective step: before each exchange (mpi_agree calls gate()) the ranks
//    check in with rank 0, point to point, polled up to the deadline. A rank that does not arrive
//    in time ends the job (MPI_Abort) with a message on stderr naming it and the step, instead of
//    leaving the others waiting forever. The deadline is the communicator's (set_deadline: the
//    index sets DistributedBuildParams::deadline_s on its own communicator), else the environment
//    variable BHCL_MPI_DEADLINE_S, else kDefaultDeadlineS; 0 turns it off. It bounds how long a
//    rank waits for the others at a step, so it must exceed the slowest rank's local work between
//    two steps (reading the files on rank 0, building its shard, answering its queries).
#pragma once

#include <mpi.h>

#include <string>
#include <utility>
#include <vector>

#include "blockhash_cl/distributed.hpp"

namespace bhcl::distributed {

inline constexpr double kDefaultDeadlineS = 600;

// (name, value as text) pairs; values written so that equal text means equal parameter (floats
// with 9 significant digits, doubles with 17: both round-trip).
using Parameters = std::vector<std::pair<std::string, std::string>>;

Parameters build_parameters(const DistributedBuildParams& p);
Parameters search_parameters(const SearchParams& p);
Parameters radius_parameters(float r, const RadiusParams& p);

// Collective over comm: returns when every rank passed the same parameters as rank 0; otherwise
// throws bhcl::Error on every rank, "<what>: the ranks passed different parameters: rank R has
// NAME = V where rank 0 has W" (and how many ranks differ).
void agree_parameters(MPI_Comm comm, const Parameters& mine, const std::string& what);

// The deadline of comm's collective steps in seconds (0: none), see above.
double deadline_seconds(MPI_Comm comm);
// Sets comm's deadline (0: none; negative: back to the environment's / the default).
void set_deadline(MPI_Comm comm, double seconds);
// Checks BHCL_MPI_DEADLINE_S: empty when unset or valid, else the reason (the index refuses).
std::string deadline_env_error();

// Collective over comm: returns when every rank reached it within the deadline; otherwise prints
// "<step>: rank R did not answer within T s ...: ending the job" on stderr and calls MPI_Abort.
void gate(MPI_Comm comm, const std::string& step);

}  // namespace bhcl::distributed
