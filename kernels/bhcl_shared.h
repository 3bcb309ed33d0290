/* Constants and device layouts shared by the host library and the OpenCL kernels.
 * Valid OpenCL C and valid C++: the host includes it and checks the layouts with static_assert
 * (lib/src/core/layout_checks.cpp). Method-specific layouts live in their own *_layout.h files. */
#ifndef BHCL_SHARED_H
#define BHCL_SHARED_H

#ifdef __OPENCL_C_VERSION__
typedef uint bhcl_u32;
typedef int bhcl_i32;
typedef float bhcl_f32;
typedef uchar bhcl_u8;
#else
#include <cstdint>
typedef std::uint32_t bhcl_u32;
typedef std::int32_t bhcl_i32;
typedef float bhcl_f32;
typedef std::uint8_t bhcl_u8;
#endif

/* The largest k any kernel variant is compiled for (BHCL_KMAX <= BHCL_MAX_K). */
#define BHCL_MAX_K 256

/* Result rows: a missing neighbour is id -1 with squared distance +inf. */
#define BHCL_MISSING_ID (-1)

/* Inside the kernels an empty top-k slot holds this id, so that a real point at distance +inf
 * (overflowing coordinates) still ranks before an empty slot. */
#define BHCL_EMPTY_SLOT_ID 0x7fffffff

/* A point as stored on the device: 16 bytes, w unused (0). Same layout as cl_float4. */
typedef struct bhcl_point4 {
  bhcl_f32 x, y, z, w;
} bhcl_point4;

#endif /* BHCL_SHARED_H */
