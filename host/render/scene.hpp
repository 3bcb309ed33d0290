// Scenes for the photon-mapping renderer: triangles with materials, a pinhole camera, emitters.
//
// Units: geometry in millimetres (the Cornell Box's unit). Emission is radiance in arbitrary
// linear units; the rendered image is radiance in the same units (see photon_map.hpp for why the
// length unit cancels). Surfaces are two-sided for diffuse and specular scattering; emitters emit
// on the front side only (counter-clockwise winding, the OBJ convention).
//
// Scene files: Wavefront OBJ (v, f with any polygon size and negative indices, usemtl, mtllib;
// vt/vn/o/g/s/l are accepted and ignored) with one extension,
//   camera px py pz  tx ty tz  ux uy uz  vfov_deg      (position, look-at target, up, vertical FOV)
// and a material file in the MTL subset
//   newmtl NAME | Kd r g b (diffuse albedo) | Ks r g b (specular reflectance / glass tint)
//   Ke r g b (emitted radiance) | Ni ior | illum N (3: mirror; 4, 6, 7: glass; else diffuse)
// (Ka, Ns, d, Tr, Tf and map_* are accepted and ignored). Errors name the file and the line.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "vec.hpp"

namespace bhcl::render {

enum class MaterialType { Diffuse, Mirror, Glass };

struct Material {
  std::string name;
  MaterialType type = MaterialType::Diffuse;
  Vec3 kd{0.8f, 0.8f, 0.8f};  // diffuse albedo (Diffuse)
  Vec3 ks{1.0f, 1.0f, 1.0f};  // reflectance (Mirror) or transmission tint (Glass)
  float ior = 1.5f;           // Glass
  Vec3 emission{0, 0, 0};     // emitted radiance, front side

  bool is_light() const { return !is_black(emission); }
  bool is_specular() const { return type != MaterialType::Diffuse; }
  // Reflects diffusely: stores photons, gets direct light and final gather.
  bool is_diffuse() const { return type == MaterialType::Diffuse && !is_black(kd); }
};

struct Camera {
  Vec3 position{0, 0, 0}, direction{0, 0, 1}, up{0, 1, 0};
  float vfov_deg = 40.0f;
};

struct Scene {
  std::string name;
  std::vector<Vec3> vertices;
  std::vector<std::array<std::uint32_t, 3>> triangles;
  std::vector<std::uint32_t> triangle_material;
  std::vector<Material> materials;
  Camera camera;

  std::uint32_t add_material(const Material& m);
  // A planar quad a b c d as two triangles (a b c) and (a c d); winding gives the front side.
  void add_quad(Vec3 a, Vec3 b, Vec3 c, Vec3 d, std::uint32_t material);
  void add_triangle(Vec3 a, Vec3 b, Vec3 c, std::uint32_t material);

  const Material& material_of(std::uint32_t tri) const { return materials[triangle_material[tri]]; }
  Vec3 geometric_normal(std::uint32_t tri) const;  // unit, front side (winding)
  float triangle_area(std::uint32_t tri) const;
  bool has_specular() const;
  bool has_light() const;
  float diagonal() const;  // of the bounding box; sets ray offsets
  // Throws bhcl::Error when the scene cannot be rendered: no triangles, non-finite vertices,
  // out-of-range indices, no emitter, albedo above 1.
  void validate() const;
};

// The measured Cornell Box (bhcl::cornell): quads in mm, RGB by the band-average reduction of
// cornell_box.hpp (R = mean over 600-700 nm, G = 500-600, B = 400-500), the light's emission
// scaled so that its mean channel is kCornellLightRadiance: radiance (1.55, 1.08, 0.37) x 40, so
// the emitted power is pi x 40 x (130 x 105 mm^2) x those channels = (2.67, 1.85, 0.63) x 10^6
// radiance x mm^2, and the brightest walls come out near radiance 1 (an EXR viewer's exposure 0).
// The light has no reflectance (the data give none). It is lowered by kCornellLightDrop mm so that
// it is not coplanar with the ceiling (rays would flicker between the two).
inline constexpr float kCornellLightRadiance = 40.0f;
inline constexpr float kCornellLightDrop = 0.5f;
Scene cornell_scene();

// A vertical field of view the pinhole camera can use: (0, 180) degrees.
bool vfov_ok(float vfov_deg);

// Loads an OBJ scene (and its mtllib). Throws bhcl::Error naming file:line on bad input.
Scene load_obj_scene(const std::string& path);

// "cornell" is the embedded Cornell Box; a path (containing '/' or ending in .obj) is loaded;
// any other name NAME is NAME.obj in the scene directories: $BHCL_SCENES_DIR, the directory of
// the executable and its ../share/blockhash_cl/scenes, then the source tree's host/scenes.
Scene load_scene(const std::string& name_or_path);
std::vector<std::string> scene_search_dirs();

}  // namespace bhcl::render
