// The measured Cornell Box (Cornell PCG "Cornell Box Data", the scene with two white blocks),
// embedded so that the demo, the tests and the renderer need no data files. Geometry in mm.
#pragma once

#include <array>
#include <cstddef>
#include <string>
#include <vector>

namespace bhcl::cornell {

using Vec3 = std::array<float, 3>;

enum class Material { White, Red, Green, Light };

// A planar quad, vertices in the published order; `normal` is the unit normal on the side that
// faces the inside of the box (walls) or away from the block (blocks).
struct Quad {
  std::string name;
  Material material;
  std::array<Vec3, 4> v;
  Vec3 normal;
  float area() const;
};

struct Camera {
  Vec3 position{278.0f, 273.0f, -800.0f};
  Vec3 direction{0.0f, 0.0f, 1.0f};
  Vec3 up{0.0f, 1.0f, 0.0f};
  float focal_length_m = 0.035f;
  float film_width_m = 0.025f, film_height_m = 0.025f;
};

// The light, floor, ceiling, back, right (green, x = 0) and left (red, x ~ 556) walls, and the
// 5 + 5 quads of the short and the tall block.
const std::vector<Quad>& quads();
const Camera& camera();

// Reflectance spectra (400..700 nm every 4 nm) and the light's emission (piecewise linear
// between 400, 500, 600, 700 nm) as measured.
struct Spectrum {
  std::vector<float> wavelength_nm, value;
  float at(float nm) const;  // linear interpolation, clamped
};
const Spectrum& reflectance(Material m);  // White, Red or Green
const Spectrum& light_emission();

// RGB reduction (documented choice): each channel is the mean of the spectrum over a band,
// B = 400-500 nm, G = 500-600 nm, R = 600-700 nm (the box filters of a simple 3-band camera).
// For the light, the emission is then scaled so that the channel mean is 1.
std::array<float, 3> rgb(Material m);

}  // namespace bhcl::cornell
