// The device layouts of kernels/*.h, checked on the host: a mismatch fails the build.
#include <CL/opencl.hpp>

#include <cstddef>

#include "bhcl_shared.h"
#include "blockhash_cl/knn.hpp"

static_assert(sizeof(bhcl_point4) == sizeof(cl_float4), "bhcl_point4 must match float4");
static_assert(offsetof(bhcl_point4, z) == 8, "bhcl_point4.z offset");
static_assert(BHCL_MAX_K == bhcl::kMaxK, "kernel and host maximum k differ");
static_assert(BHCL_MISSING_ID == -1, "missing id is -1 by contract");
