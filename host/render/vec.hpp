// Small vector maths, a counter-based random number generator and the sampling helpers the
// renderer needs. Header-only so that the hot loops inline.
#pragma once

#include <cmath>
#include <cstdint>

namespace bhcl::render {

struct Vec3 {
  float x = 0, y = 0, z = 0;
  Vec3() = default;
  constexpr Vec3(float a, float b, float c) : x(a), y(b), z(c) {}
  float operator[](int i) const { return i == 0 ? x : (i == 1 ? y : z); }
  float& operator[](int i) { return i == 0 ? x : (i == 1 ? y : z); }
};

inline Vec3 operator+(Vec3 a, Vec3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline Vec3 operator-(Vec3 a, Vec3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 operator-(Vec3 a) { return {-a.x, -a.y, -a.z}; }
inline Vec3 operator*(Vec3 a, Vec3 b) { return {a.x * b.x, a.y * b.y, a.z * b.z}; }
inline Vec3 operator*(Vec3 a, float s) { return {a.x * s, a.y * s, a.z * s}; }
inline Vec3 operator*(float s, Vec3 a) { return a * s; }
inline Vec3 operator/(Vec3 a, float s) { return a * (1.0f / s); }
inline Vec3& operator+=(Vec3& a, Vec3 b) { return a = a + b; }
inline Vec3& operator*=(Vec3& a, Vec3 b) { return a = a * b; }
inline Vec3& operator*=(Vec3& a, float s) { return a = a * s; }
inline float dot(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline Vec3 cross(Vec3 a, Vec3 b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline float length(Vec3 a) { return std::sqrt(dot(a, a)); }
inline Vec3 normalize(Vec3 a) { return a / length(a); }
inline float max_component(Vec3 a) { return std::fmax(a.x, std::fmax(a.y, a.z)); }
inline float luminance(Vec3 c) { return 0.2126f * c.x + 0.7152f * c.y + 0.0722f * c.z; }
inline bool is_black(Vec3 c) { return c.x <= 0 && c.y <= 0 && c.z <= 0; }

// An orthonormal basis around a unit normal (Duff et al. 2017, branchless).
struct Frame {
  Vec3 t, b, n;
  explicit Frame(Vec3 nn) : n(nn) {
    float sign = std::copysign(1.0f, n.z);
    float a = -1.0f / (sign + n.z);
    float bb = n.x * n.y * a;
    t = {1.0f + sign * n.x * n.x * a, sign * bb, -sign * n.x};
    b = {bb, sign + n.y * n.y * a, -n.y};
  }
  Vec3 to_world(Vec3 v) const { return t * v.x + b * v.y + n * v.z; }
};

// Counter-based seeding (SplitMix64) + PCG32 stream: every pixel sample and every photon gets its
// own generator from (seed, index), so results do not depend on thread count or scheduling.
inline std::uint64_t splitmix64(std::uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

class Rng {
 public:
  Rng(std::uint64_t seed, std::uint64_t stream, std::uint64_t index) {
    state_ = splitmix64(seed ^ splitmix64(stream * 0xD1B54A32D192ED03ull ^ splitmix64(index)));
    inc_ = (splitmix64(index + 0x632BE59BD9B4E019ull * (stream + 1)) << 1) | 1u;
    next();
  }
  std::uint32_t next() {
    std::uint64_t old = state_;
    state_ = old * 6364136223846793005ull + inc_;
    std::uint32_t xorshifted = static_cast<std::uint32_t>(((old >> 18u) ^ old) >> 27u);
    std::uint32_t rot = static_cast<std::uint32_t>(old >> 59u);
    return (xorshifted >> rot) | (xorshifted << ((32 - rot) & 31));
  }
  // Uniform in [0, 1): 24 random bits, so the result is never rounded up to 1.
  float uniform() { return static_cast<float>(next() >> 8) * (1.0f / 16777216.0f); }

 private:
  std::uint64_t state_, inc_;
};

constexpr float kPi = 3.14159265358979323846f;

// Cosine-distributed direction around +z (Malley's method); pdf = cos(theta) / pi.
inline Vec3 cosine_hemisphere(float u1, float u2) {
  float r = std::sqrt(u1), phi = 2.0f * kPi * u2;
  return {r * std::cos(phi), r * std::sin(phi), std::sqrt(std::fmax(0.0f, 1.0f - u1))};
}

// Uniform point on a triangle (barycentrics by the square-root method).
inline Vec3 sample_triangle(Vec3 a, Vec3 b, Vec3 c, float u1, float u2) {
  float su = std::sqrt(u1);
  return a * (1.0f - su) + b * (su * (1.0f - u2)) + c * (su * u2);
}

inline Vec3 reflect(Vec3 d, Vec3 n) { return d - n * (2.0f * dot(d, n)); }

// Dielectric Fresnel reflectance for unpolarised light; cos_i >= 0 on the incident side, eta =
// n_incident / n_transmitted. Returns 1 for total internal reflection.
inline float fresnel_dielectric(float cos_i, float eta) {
  float sin2_t = eta * eta * std::fmax(0.0f, 1.0f - cos_i * cos_i);
  if (sin2_t >= 1.0f) return 1.0f;
  float cos_t = std::sqrt(1.0f - sin2_t);
  float rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
  float rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
  return 0.5f * (rs * rs + rp * rp);
}

// A ray meets a glass surface at x: reflected with the Fresnel probability (u uniform in [0, 1)),
// else refracted by Snell's law. n faces the incoming ray; front: it arrives from outside (ior is
// the glass's). org moves eps off the surface on the side the ray leaves to.
// Returns the factor by which RADIANCE carried back along the ray changes: (n_from / n_to)^2 on
// refraction (n_from: the index on the side the ray comes from), 1 on reflection. Radiance / n^2
// is what is conserved across a smooth interface (the same flux through a solid angle that Snell's
// law compresses by n_to^2 / n_from^2), so a camera or gather ray entering glass sees (1 / ior)^2
// of the radiance inside, and one leaving glass sees ior^2 times the radiance outside. Flux
// (photon power) is conserved and takes no such factor; callers carrying flux ignore the value.
inline float glass_scatter(Vec3& dir, Vec3& org, Vec3 x, Vec3 n, bool front, float ior, float u,
                           float eps) {
  float eta = front ? 1.0f / ior : ior;  // n_from / n_to
  float cos_i = -dot(dir, n);
  if (u < fresnel_dielectric(cos_i, eta)) {
    dir = reflect(dir, n);
    org = x + n * eps;
    return 1.0f;
  }
  float cos_t = std::sqrt(std::fmax(0.0f, 1.0f - eta * eta * (1.0f - cos_i * cos_i)));
  dir = normalize(dir * eta + n * (eta * cos_i - cos_t));
  org = x - n * eps;
  return eta * eta;
}

}  // namespace bhcl::render
