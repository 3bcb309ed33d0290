/* Power-of-two scaling of coordinates and squared distances, for point sets whose extent is
 * outside the range where float distances are safe (see knn.hpp, "Extreme scales"). ldexp is
 * exact unless the result leaves the float range. Item i of a launch is first + its global id (launches
 * stay below the driver's limit: detail::launch_1d_split). */

__kernel void bhcl_scale_copy(__global const float* src, __global float* dst, ulong count,
                              int exponent, ulong first) {
  size_t i = first + get_global_id(0);
  if (i < count) dst[i] = ldexp(src[i], exponent);
}

__kernel void bhcl_scale_in_place(__global float* data, ulong count, int exponent, ulong first) {
  size_t i = first + get_global_id(0);
  if (i < count) data[i] = ldexp(data[i], exponent);
}
