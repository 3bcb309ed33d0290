// The photon record, as in the talk: position, power and incoming direction in 24 bytes.
#pragma once

#include <Imath/half.h>

#include <cmath>
#include <cstdint>

#include "vec.hpp"

namespace bhcl::render {

// Power is stored as three half floats RELATIVE to the map's power scale (PhotonMap::power_scale,
// the emitted power per photon), so the halves stay near 1 whatever the light's units and the
// photon count: no overflow or denormals. The direction (unit, pointing back towards where the
// photon came from) is octahedral-encoded in two signed 16-bit integers (error below 1e-4 rad).
struct PhotonRecord {
  float position[3];
  std::uint16_t power[3];  // Imath::half bits
  std::int16_t direction[2];
  std::uint16_t flags;     // bits 0-7: diffuse/specular bounces before this hit; bit 8: caustic;
                           // bit 9: stored inside glass (position keyed by medium_key);
                           // bits 10-12: the surface's orientation class + 1 (surface_area.hpp;
                           // 0: not known)

  static constexpr std::uint16_t kCaustic = 0x100;
  static constexpr std::uint16_t kInGlass = 0x200;
  static constexpr int kClassShift = 10;
  static constexpr std::uint16_t kClassMask = 0x1C00;

  // The orientation class (0..5) of the surface the photon landed on, on its lit side; -1 unknown.
  int surface_class() const { return ((flags & kClassMask) >> kClassShift) - 1; }
  void set_surface_class(int c) {
    flags = static_cast<std::uint16_t>((flags & ~kClassMask) | (((c + 1) << kClassShift) & kClassMask));
  }

  void set_power(Vec3 p) {
    power[0] = Imath::half(p.x).bits();
    power[1] = Imath::half(p.y).bits();
    power[2] = Imath::half(p.z).bits();
  }
  Vec3 get_power() const {
    Imath::half h[3];
    for (int c = 0; c < 3; ++c) h[c].setBits(power[c]);
    return {float(h[0]), float(h[1]), float(h[2])};
  }
  void set_direction(Vec3 d) {
    float s = std::fabs(d.x) + std::fabs(d.y) + std::fabs(d.z);
    float u = d.x / s, v = d.y / s;
    if (d.z < 0) {
      float pu = (1.0f - std::fabs(v)) * std::copysign(1.0f, u);
      float pv = (1.0f - std::fabs(u)) * std::copysign(1.0f, v);
      u = pu;
      v = pv;
    }
    direction[0] = static_cast<std::int16_t>(std::lround(std::fmax(-1.0f, std::fmin(1.0f, u)) * 32767.0f));
    direction[1] = static_cast<std::int16_t>(std::lround(std::fmax(-1.0f, std::fmin(1.0f, v)) * 32767.0f));
  }
  Vec3 get_direction() const { return normalize(get_direction_unnormalized()); }
  // The same direction, not of unit length: enough for sign tests (saves a sqrt and a divide).
  Vec3 get_direction_unnormalized() const {
    float u = direction[0] / 32767.0f, v = direction[1] / 32767.0f;
    Vec3 d{u, v, 1.0f - std::fabs(u) - std::fabs(v)};
    if (d.z < 0) {
      float pu = (1.0f - std::fabs(v)) * std::copysign(1.0f, u);
      float pv = (1.0f - std::fabs(u)) * std::copysign(1.0f, v);
      d.x = pu;
      d.y = pv;
    }
    return d;
  }
  Vec3 get_position() const { return {position[0], position[1], position[2]}; }
};
static_assert(sizeof(PhotonRecord) == 24, "the talk's photon record is 24 bytes");

// Light on a surface inside glass and light on the same surface outside it are separate: a glass
// block with no bottom face stands on the floor, and the floor under it is lit only through the
// glass while the floor beside it is lit directly or lies in the block's shadow. A density
// estimate whose disc straddles the glass wall would mix the two (light leaking through the wall:
// the floor in the shadow beside the block brightened by the caustic under it, the floor under
// the block darkened). So photons and queries are keyed by their medium: the kNN search sees the
// points inside glass moved by `separation` along x, at least one scene diagonal away from every
// point outside (separation = medium_separation of the scene), and the two media never meet in
// one estimate. Distances within a medium are unchanged (a translation).
inline float medium_separation(float scene_diagonal) { return 2.0f * scene_diagonal; }
inline Vec3 medium_key(Vec3 x, bool in_glass, float separation) {
  return in_glass ? Vec3{x.x + separation, x.y, x.z} : x;
}

}  // namespace bhcl::render
