// Photon density estimators: how the disc that the k nearest photons cover is sized, and how the
// photons inside it are weighted.
//
// Approximate neighbours dilate the radius of the k-th found photon (the talk's "future work"):
// a few of the true k nearest are missed and farther ones stand in, so the classic estimate,
// which divides the k photons' power by pi r_k^2, falls as r_k grows. The other two radius
// estimators read the whole list of distances instead of its last entry:
//   kth:  r = d_k                                 (Jensen's classic)
//   mean: r = mean(d_j) / m1(k)                   ("average radius")
//   var:  r = sqrt(var(d_j) / v(k))               ("variance of radii")
// where m1 and v are what mean(d)/r and var(d)/r^2 are for k photons of a uniform density in a
// disc of radius r found by a k-nearest search: k - 1 of them uniform in the disc (E d = 2r/3,
// E d^2 = r^2/2) and the k-th on its rim. Then
//   m1(k) = (2k + 1) / (3k),   m2(k) = (k + 1) / (2k),   v(k) = m2(k) - m1(k)^2   (1/18 as k grows)
// so each estimator is consistent for r_k of an exact search. With fewer than k photons inside
// the search's maximum radius the disc is that radius for every estimator (it is known).
//
// Filters weight photon j by w(d_j / r) and divide by the filter's integral over the disc
// (w = 0 beyond the filter's support, so a photon outside an estimated disc adds nothing):
//   box:          w = 1                                  integral pi r^2
//   cone:         w = 1 - s / c, c = kConeFilter = 1.1   integral pi r^2 (1 - 2 / (3c))
//   epanechnikov: w = 1 - s^2                            integral pi r^2 / 2
// The box filter keeps every photon found, whatever the disc: the k photons over the estimated
// area.
//
// Header-only and inline: PhotonMap::radiance runs it once per gather query.
#pragma once

#include <cmath>
#include <cstddef>
#include <string>

namespace bhcl::render {

inline constexpr float kConeFilter = 1.1f;

enum class RadiusEstimator { Kth, Mean, Variance };
enum class DensityFilter { Box, Cone, Epanechnikov };

struct DensityEstimator {
  RadiusEstimator radius = RadiusEstimator::Kth;
  DensityFilter filter = DensityFilter::Cone;
  bool operator==(const DensityEstimator& o) const { return radius == o.radius && filter == o.filter; }
};

// Each estimator's and filter's command-line name, one table per enum: the names and the parsers
// read the same table, so a value added to one cannot be missing from the other.
template <class E>
struct NamedValue {
  E value;
  const char* name;
};
inline constexpr NamedValue<RadiusEstimator> kRadiusEstimatorNames[] = {
    {RadiusEstimator::Kth, "kth"}, {RadiusEstimator::Mean, "mean"}, {RadiusEstimator::Variance, "var"}};
inline constexpr NamedValue<DensityFilter> kDensityFilterNames[] = {
    {DensityFilter::Box, "box"}, {DensityFilter::Cone, "cone"}, {DensityFilter::Epanechnikov, "epanechnikov"}};

template <class E, std::size_t N>
const char* name_in(const NamedValue<E> (&table)[N], E e) {
  for (const NamedValue<E>& v : table)
    if (v.value == e) return v.name;
  return "?";
}
// false when the name is not in the table (out unchanged).
template <class E, std::size_t N>
bool parse_name_in(const NamedValue<E> (&table)[N], const std::string& s, E& out) {
  for (const NamedValue<E>& v : table)
    if (s == v.name) return out = v.value, true;
  return false;
}

inline const char* radius_estimator_name(RadiusEstimator e) { return name_in(kRadiusEstimatorNames, e); }
inline const char* density_filter_name(DensityFilter f) { return name_in(kDensityFilterNames, f); }
// "kth/cone", "var/epanechnikov", ...
inline std::string estimator_name(const DensityEstimator& e) {
  return std::string(radius_estimator_name(e.radius)) + "/" + density_filter_name(e.filter);
}

// Parsers for the command line; false when the name is unknown.
inline bool parse_radius_estimator(const std::string& s, RadiusEstimator& out) {
  return parse_name_in(kRadiusEstimatorNames, s, out);
}
inline bool parse_density_filter(const std::string& s, DensityFilter& out) {
  return parse_name_in(kDensityFilterNames, s, out);
}

// Filter weight of a photon at squared distance d2 from the query, for a disc of squared radius
// r2 (radius r); 0 beyond the support.
inline float filter_weight(DensityFilter f, float d2, float r2, float r) {
  switch (f) {
    case DensityFilter::Box: return 1.0f;
    case DensityFilter::Cone: return std::fmax(0.0f, 1.0f - std::sqrt(d2) / (kConeFilter * r));
    case DensityFilter::Epanechnikov: return std::fmax(0.0f, 1.0f - d2 / r2);
  }
  return 0.0f;
}
// The filter's integral over the unit disc, over pi.
inline float filter_norm(DensityFilter f) {
  switch (f) {
    case DensityFilter::Box: return 1.0f;
    case DensityFilter::Cone: return 1.0f - 2.0f / (3.0f * kConeFilter);
    case DensityFilter::Epanechnikov: return 0.5f;
  }
  return 1.0f;
}

// The squared disc radius from the ascending squared distances d2[0..count) of a k-nearest search
// with maximum radius max_radius (infinite: none). 0 when there is no disc (no photon, or all on
// the query point).
inline float disc_radius2(RadiusEstimator e, const float* d2, int count, int k, float max_radius) {
  if (count <= 0) return 0.0f;
  if (count < k && std::isfinite(max_radius)) return max_radius * max_radius;
  if (e == RadiusEstimator::Kth || count < 2) return d2[count - 1];
  // Sums in double: k can be thousands and d2 spans many orders of magnitude.
  double s1 = 0, s2 = 0;
  for (int j = 0; j < count; ++j) {
    s1 += std::sqrt(static_cast<double>(d2[j]));
    s2 += d2[j];
  }
  const double n = count, m1 = (2 * n + 1) / (3 * n), m2 = (n + 1) / (2 * n);
  const double mean = s1 / n;
  if (e == RadiusEstimator::Mean) {
    const double r = mean / m1;
    return static_cast<float>(r * r);
  }
  const double var = std::fmax(0.0, s2 / n - mean * mean);
  return static_cast<float>(var / (m2 - m1 * m1));
}

}  // namespace bhcl::render
