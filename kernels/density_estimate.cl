// The density estimate inside the query (lib/include/blockhash_cl/density_query.hpp): one
// work-item per query reduces the query's k-nearest list (ids, squared distances, count, as any
// method's kernel wrote them into a device buffer) to the estimate
//     E = sum_j w(d_j / r) P_j / (norm_w pi r^2)       over the listed points facing the query
// (dot(D_j, N) > 0, D_j the point's direction, N the query's normal), and the squared radius r^2
// it used. Only these 16 bytes per query leave the device: the lists stay in a reused chunk buffer.
//
// The disc follows the renderer's estimators (host/render/density.hpp, same formulas, in float
// here where the host sums the mean and variance in double):
//   kth:  r^2 = d_count                        mean: r = mean(d) / m1(c)
//   var:  r^2 = var(d) / (m2(c) - m1(c)^2) (two passes in float),    m1 = (2c + 1) / (3c), m2 = (c + 1) / (2c)
// with r^2 = max_radius^2 when fewer than k points were found within a finite max_radius; then
// scaled by scale2 (a progressive pass: only the list's prefix inside the shrunk disc counts).
// Filters: 0 box (w = 1), 1 cone (w = 1 - d / (c r)), 2 Epanechnikov (w = 1 - d^2 / r^2).

__kernel void bhcl_density_estimate(__global const int* ids, __global const float* dist2,
                                    __global const int* counts, __global const float* normals,
                                    __global const float* power, __global const float* direction,
                                    const int k, const float max_radius, const int estimator,
                                    const int filter, const float cone, const float scale2,
                                    const uint n, __global float* out, const ulong first) {
  const size_t q = first + get_global_id(0); /* launches stay below the driver's limit (launch_1d_split) */
  if (q >= n) return;
  __global const float* d2 = dist2 + (size_t)q * (size_t)k;
  __global const int* id = ids + (size_t)q * (size_t)k;
  const int count = counts[q];
  float r2 = 0.0f;
  if (count > 0) {
    if (count < k && isfinite(max_radius)) {
      r2 = max_radius * max_radius;
    } else if (estimator == 0 || count < 2) {
      r2 = d2[count - 1];
    } else {
      float s1 = 0.0f;
      for (int j = 0; j < count; ++j) s1 += sqrt(d2[j]);
      const float c = (float)count;
      const float m1 = (2.0f * c + 1.0f) / (3.0f * c), m2 = (c + 1.0f) / (2.0f * c);
      const float mean = s1 / c;
      if (estimator == 1) {
        const float r = mean / m1;
        r2 = r * r;
      } else {
        // Two passes: var(d) is ~1/18 of r^2, and the host's one-pass s2/n - mean^2 (in double)
        // would cancel 4 of float's 7 digits here.
        float sv = 0.0f;
        for (int j = 0; j < count; ++j) {
          const float t = sqrt(d2[j]) - mean;
          sv += t * t;
        }
        r2 = (sv / c) / (m2 - m1 * m1);
      }
    }
  }
  float3 sum = (float3)(0.0f, 0.0f, 0.0f);
  if (r2 > 0.0f && isfinite(r2)) {
    int used = count;
    if (scale2 < 1.0f) {
      r2 *= scale2;
      used = 0;
      while (used < count && d2[used] <= r2) ++used;
    }
    if (r2 > 0.0f) {
      const float radius = sqrt(r2);
      const float3 nq = vload3(q, normals);
      for (int j = 0; j < used; ++j) {
        const int p = id[j];
        if (dot(vload3(p, direction), nq) <= 0.0f) continue;  // arrived from behind the surface
        float w = 1.0f;
        if (filter == 1) w = fmax(0.0f, 1.0f - sqrt(d2[j]) / (cone * radius));
        else if (filter == 2) w = fmax(0.0f, 1.0f - d2[j] / r2);
        sum += vload3(p, power) * w;
      }
      const float norm = (filter == 0 ? 1.0f : filter == 1 ? 1.0f - 2.0f / (3.0f * cone) : 0.5f) *
                         3.14159265358979f * r2;
      sum /= norm;
    } else {
      r2 = 0.0f;
    }
  } else {
    r2 = 0.0f;
  }
  vstore4((float4)(sum, r2), q, out);
}
