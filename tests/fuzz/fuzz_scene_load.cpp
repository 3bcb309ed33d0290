// libFuzzer target: the OBJ scene loader (and the material libraries it names) must accept or
// refuse any bytes with bhcl::Error, never crash; whatever it accepts must pass Scene::validate
// with finite areas, normals, emitted power and camera basis, so that nothing non-finite can
// reach Embree.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <string>
#include <unistd.h>

#include "blockhash_cl/error.hpp"
#include "scene.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  // The loader reads a path: the input goes to a file of this process's own, in
  // BHCL_FUZZ_TMPDIR (.ci/fuzz: a folder of the fuzz build it empties after the run) or /tmp.
  static const std::string path = [] {
    const char* dir = std::getenv("BHCL_FUZZ_TMPDIR");
    return std::string(dir && *dir ? dir : "/tmp") + "/bhcl_fuzz_scene_" + std::to_string(getpid()) + ".obj";
  }();
  {
    std::ofstream f(path, std::ios::binary | std::ios::trunc);
    f.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
  }
  try {
    bhcl::render::Scene s = bhcl::render::load_obj_scene(path);
    s.validate();
    for (std::size_t i = 0; i < s.triangles.size(); ++i) {
      const auto t = static_cast<std::uint32_t>(i);
      const float a = s.triangle_area(t);
      const auto n = s.geometric_normal(t);
      if (!std::isfinite(a) || !(a > 0) || !std::isfinite(n.x) || !std::isfinite(n.y) || !std::isfinite(n.z))
        std::abort();
    }
    const auto& c = s.camera;
    if (!std::isfinite(c.direction.x) || !std::isfinite(c.direction.y) || !std::isfinite(c.direction.z) ||
        !std::isfinite(c.up.x) || !std::isfinite(c.up.y) || !std::isfinite(c.up.z) ||
        !std::isfinite(c.position.x) || !std::isfinite(c.position.y) || !std::isfinite(c.position.z))
      std::abort();
  } catch (const bhcl::Error&) {
  }
  return 0;
}
