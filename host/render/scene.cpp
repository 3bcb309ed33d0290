// Scene construction, the embedded Cornell Box and the OBJ/MTL loader.
#include "scene.hpp"

#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>

#include "blockhash_cl/cornell_box.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/numbers.hpp"

namespace bhcl::render {

std::uint32_t Scene::add_material(const Material& m) {
  materials.push_back(m);
  return static_cast<std::uint32_t>(materials.size() - 1);
}

void Scene::add_triangle(Vec3 a, Vec3 b, Vec3 c, std::uint32_t material) {
  auto base = static_cast<std::uint32_t>(vertices.size());
  vertices.push_back(a);
  vertices.push_back(b);
  vertices.push_back(c);
  triangles.push_back({base, base + 1, base + 2});
  triangle_material.push_back(material);
}

void Scene::add_quad(Vec3 a, Vec3 b, Vec3 c, Vec3 d, std::uint32_t material) {
  add_triangle(a, b, c, material);
  add_triangle(a, c, d, material);
}

Vec3 Scene::geometric_normal(std::uint32_t tri) const {
  const auto& t = triangles[tri];
  return normalize(cross(vertices[t[1]] - vertices[t[0]], vertices[t[2]] - vertices[t[0]]));
}

float Scene::triangle_area(std::uint32_t tri) const {
  const auto& t = triangles[tri];
  return 0.5f * length(cross(vertices[t[1]] - vertices[t[0]], vertices[t[2]] - vertices[t[0]]));
}

bool Scene::has_specular() const {
  for (std::size_t i = 0; i < triangles.size(); ++i)
    if (materials[triangle_material[i]].is_specular()) return true;
  return false;
}

bool Scene::has_light() const {
  for (std::size_t i = 0; i < triangles.size(); ++i)
    if (materials[triangle_material[i]].is_light() && triangle_area(static_cast<std::uint32_t>(i)) > 0)
      return true;
  return false;
}

float Scene::diagonal() const {
  Vec3 lo{INFINITY, INFINITY, INFINITY}, hi{-INFINITY, -INFINITY, -INFINITY};
  for (const auto& v : vertices)
    for (int d = 0; d < 3; ++d) {
      lo[d] = std::fmin(lo[d], v[d]);
      hi[d] = std::fmax(hi[d], v[d]);
    }
  return vertices.empty() ? 0.0f : length(hi - lo);
}

void Scene::validate() const {
  const std::string where = "scene '" + name + "'";
  if (triangles.empty()) throw Error(where + ": no triangles");
  if (triangle_material.size() != triangles.size())
    throw Error(where + ": " + std::to_string(triangles.size()) + " triangles but " +
                std::to_string(triangle_material.size()) + " material ids");
  for (std::size_t i = 0; i < vertices.size(); ++i)
    for (int d = 0; d < 3; ++d)
      if (!std::isfinite(vertices[i][d]))
        throw Error(where + ": vertex " + std::to_string(i) + " has a non-finite coordinate");
  for (std::size_t i = 0; i < triangles.size(); ++i) {
    for (auto v : triangles[i])
      if (v >= vertices.size())
        throw Error(where + ": triangle " + std::to_string(i) + " refers to vertex " +
                    std::to_string(v) + " of " + std::to_string(vertices.size()));
    if (triangle_material[i] >= materials.size())
      throw Error(where + ": triangle " + std::to_string(i) + " has material id " +
                  std::to_string(triangle_material[i]) + " of " + std::to_string(materials.size()));
  }
  for (const auto& m : materials) {
    for (int c = 0; c < 3; ++c) {
      if (!(m.kd[c] >= 0 && m.kd[c] <= 1) || !(m.ks[c] >= 0 && m.ks[c] <= 1))
        throw Error(where + ": material '" + m.name +
                    "' has a reflectance outside [0, 1] (energy would not be conserved)");
      if (!(m.emission[c] >= 0) || !std::isfinite(m.emission[c]))
        throw Error(where + ": material '" + m.name + "' has a negative or non-finite emission");
    }
    if (m.type == MaterialType::Glass && !(m.ior > 0 && std::isfinite(m.ior)))
      throw Error(where + ": glass material '" + m.name + "' needs an index of refraction > 0");
  }
  for (std::size_t i = 0; i < triangles.size(); ++i)
    if (!std::isfinite(triangle_area(static_cast<std::uint32_t>(i))))
      throw Error(where + ": triangle " + std::to_string(i) + " has an area that overflows");
  if (!std::isfinite(diagonal()))
    throw Error(where + ": the scene's extent overflows the float range");
  if (!has_light()) throw Error(where + ": no emitting surface (no material with Ke > 0)");
  if (!(vfov_ok(camera.vfov_deg)))
    throw Error(where + ": camera field of view must be in (0, 180) degrees");
}

bool vfov_ok(float v) { return v > 0 && v < 180; }

Scene cornell_scene() {
  namespace cb = bhcl::cornell;
  Scene s;
  s.name = "cornell";
  std::map<int, std::uint32_t> mat;
  auto material_for = [&](cb::Material m) {
    auto it = mat.find(static_cast<int>(m));
    if (it != mat.end()) return it->second;
    Material out;
    auto c = cb::rgb(m);
    switch (m) {
      case cb::Material::White: out.name = "white"; break;
      case cb::Material::Red: out.name = "red"; break;
      case cb::Material::Green: out.name = "green"; break;
      case cb::Material::Light: out.name = "light"; break;
    }
    if (m == cb::Material::Light) {
      // The Cornell data gives the light no reflectance: it only emits.
      out.kd = {0, 0, 0};
      out.emission = Vec3{c[0], c[1], c[2]} * kCornellLightRadiance;
    } else {
      out.kd = {c[0], c[1], c[2]};
    }
    return mat[static_cast<int>(m)] = s.add_material(out);
  };
  for (const auto& q : cb::quads()) {
    std::array<Vec3, 4> v;
    for (int i = 0; i < 4; ++i) v[i] = {q.v[i][0], q.v[i][1], q.v[i][2]};
    if (q.material == cb::Material::Light)
      for (auto& p : v) p.y -= kCornellLightDrop;
    // Wind the quad so that its front side is the documented (inward / outward) normal: the
    // light emits on its front side only.
    Vec3 n{q.normal[0], q.normal[1], q.normal[2]};
    if (dot(cross(v[1] - v[0], v[2] - v[0]), n) < 0) std::swap(v[1], v[3]);
    s.add_quad(v[0], v[1], v[2], v[3], material_for(q.material));
  }
  const auto& c = cb::camera();
  s.camera.position = {c.position[0], c.position[1], c.position[2]};
  s.camera.direction = {c.direction[0], c.direction[1], c.direction[2]};
  s.camera.up = {c.up[0], c.up[1], c.up[2]};
  s.camera.vfov_deg = 2.0f * std::atan(0.5f * c.film_height_m / c.focal_length_m) * 180.0f / kPi;
  return s;
}

namespace {

std::string dir_of(const std::string& path) {
  auto p = path.find_last_of('/');
  return p == std::string::npos ? std::string(".") : path.substr(0, p);
}

struct LineReader {
  std::string file;
  int line = 0;
  // The next line of f that holds a keyword (blank lines and # comments skipped): its first word
  // in key, the rest left in `in`; false at the end of the file. Counts the lines fail() names.
  bool next(std::istream& f, std::istringstream& in, std::string& key) {
    std::string text;
    while (std::getline(f, text)) {
      ++line;
      in.clear();
      in.str(text);
      if (!(in >> key) || key[0] == '#') continue;
      return true;
    }
    return false;
  }
  [[noreturn]] void fail(const std::string& msg) const {
    throw Error(file + ":" + std::to_string(line) + ": " + msg);
  }
  float number(std::istringstream& in, const char* what) const {
    std::string tok;
    if (!(in >> tok)) fail(std::string("missing ") + what);
    double d = 0;  // locale-free (numbers.hpp)
    if (bhcl::detail::parse_double(tok, d) == bhcl::detail::NumberParse::NotNumber)
      fail(std::string("bad number '") + tok + "' for " + what);
    const float v = std::isfinite(d) && std::fabs(d) < 0x1.ffffffp+127 ? float(d) : float(INFINITY);
    if (!std::isfinite(v)) fail(std::string("non-finite ") + what + " '" + tok + "'");
    return v;
  }
  // An integer in [lo, hi]: anything else (a fraction, a value out of range) refused at file:line.
  int integer(std::istringstream& in, const char* what, long lo, long hi) const {
    std::string tok;
    if (!(in >> tok)) fail(std::string("missing ") + what);
    char* end = nullptr;
    errno = 0;
    const long v = std::strtol(tok.c_str(), &end, 10);
    if (end == tok.c_str() || *end != '\0')
      fail(std::string("bad ") + what + " '" + tok + "': must be an integer in [" + std::to_string(lo) + ", " +
           std::to_string(hi) + "]");
    if (errno == ERANGE || v < lo || v > hi)
      fail(std::string(what) + " " + tok + " is out of range: must be an integer in [" + std::to_string(lo) +
           ", " + std::to_string(hi) + "]");
    return static_cast<int>(v);
  }
  Vec3 vec3(std::istringstream& in, const char* what) const {
    Vec3 v;
    v.x = number(in, what);
    v.y = number(in, what);
    v.z = number(in, what);
    return v;
  }
  void no_more(std::istringstream& in) const {
    std::string tok;
    if (in >> tok) fail("unexpected '" + tok + "' at the end of the line");
  }
};

std::map<std::string, Material> load_mtl(const std::string& path) {
  regular_file_size(path, "a material library");
  std::ifstream f(path);
  if (!f) throw Error(path + ": cannot open the material file");
  std::map<std::string, Material> out;
  LineReader r{path};
  Material* cur = nullptr;
  int illum = -1;
  auto finish = [&] {
    if (!cur) return;
    if (illum == 3) cur->type = MaterialType::Mirror;
    else if (illum == 4 || illum == 6 || illum == 7) cur->type = MaterialType::Glass;
  };
  std::istringstream in;
  std::string key;
  while (r.next(f, in, key)) {
    if (key == "newmtl") {
      finish();
      std::string name;
      if (!(in >> name)) r.fail("newmtl needs a name");
      if (out.count(name)) r.fail("material '" + name + "' is defined twice");
      cur = &out[name];
      cur->name = name;
      illum = -1;
      continue;
    }
    // Nothing of a file that is not a material library is quoted back.
    if (!cur) r.fail("not a material library (the first statement is not newmtl)");
    if (key == "Kd") cur->kd = r.vec3(in, "Kd");
    else if (key == "Ks") cur->ks = r.vec3(in, "Ks");
    else if (key == "Ke") cur->emission = r.vec3(in, "Ke");
    else if (key == "Ni") cur->ior = r.number(in, "Ni");
    else if (key == "illum") illum = r.integer(in, "illum", 0, 10);  // the MTL illumination models 0..10
    else if (key == "Ka" || key == "Ns" || key == "d" || key == "Tr" || key == "Tf" ||
             key.rfind("map_", 0) == 0)
      continue;
    else r.fail("unknown material statement");
    r.no_more(in);
    for (int c = 0; c < 3; ++c)
      if (cur->kd[c] < 0 || cur->kd[c] > 1 || cur->ks[c] < 0 || cur->ks[c] > 1)
        r.fail("reflectance of '" + cur->name + "' must be in [0, 1]");
    if (cur->emission.x < 0 || cur->emission.y < 0 || cur->emission.z < 0)
      r.fail("emission of '" + cur->name + "' must be >= 0");
    if (!(cur->ior > 0)) r.fail("Ni of '" + cur->name + "' must be > 0");
  }
  finish();
  return out;
}

// "7", "7/1", "7//3", "7/1/3", negative = relative to the end.
std::uint32_t face_index(const LineReader& r, const std::string& tok, std::size_t nverts) {
  std::string head = tok.substr(0, tok.find('/'));
  char* end = nullptr;
  long v = std::strtol(head.c_str(), &end, 10);
  if (head.empty() || *end != '\0') r.fail("bad face vertex '" + tok + "'");
  long idx = v > 0 ? v - 1 : static_cast<long>(nverts) + v;
  if (v == 0 || idx < 0 || idx >= static_cast<long>(nverts))
    r.fail("face vertex " + std::to_string(v) + " out of range (" + std::to_string(nverts) +
           " vertices so far)");
  return static_cast<std::uint32_t>(idx);
}

}  // namespace

Scene load_obj_scene(const std::string& path) {
  regular_file_size(path, "a scene file");  // a FIFO or /dev/zero would never end
  std::ifstream f(path);
  if (!f) throw Error(path + ": cannot open the scene file");
  Scene s;
  s.name = path;
  LineReader r{path};
  std::map<std::string, Material> library;
  std::map<std::string, std::uint32_t> used;
  std::uint32_t current = UINT32_MAX;
  bool have_camera = false;
  auto default_material = [&] {
    auto it = used.find("");
    if (it != used.end()) return it->second;
    Material m;
    m.name = "default";
    return used[""] = s.add_material(m);
  };
  std::istringstream in;
  std::string key;
  while (r.next(f, in, key)) {
    if (key == "v") {
      s.vertices.push_back(r.vec3(in, "vertex coordinate"));
      std::string w;
      if (in >> w) {
        std::istringstream wi(w);
        r.number(wi, "vertex w");
      }
      r.no_more(in);
    } else if (key == "f") {
      std::vector<std::uint32_t> poly;
      std::string tok;
      while (in >> tok) poly.push_back(face_index(r, tok, s.vertices.size()));
      if (poly.size() < 3) r.fail("a face needs at least 3 vertices, got " + std::to_string(poly.size()));
      std::uint32_t m = current == UINT32_MAX ? default_material() : current;
      for (std::size_t i = 1; i + 1 < poly.size(); ++i) {  // fan: planar convex polygons
        s.triangles.push_back({poly[0], poly[i], poly[i + 1]});
        s.triangle_material.push_back(m);
        // What the renderer derives from the triangle must be finite: finite coordinates near the
        // float maximum overflow the edge cross product, the area, the normal or the power.
        const auto t = static_cast<std::uint32_t>(s.triangles.size() - 1);
        const float area = s.triangle_area(t);
        const Vec3 nrm = s.geometric_normal(t);
        if (!std::isfinite(area) || !std::isfinite(nrm.x) || !std::isfinite(nrm.y) || !std::isfinite(nrm.z))
          r.fail(area > 0 || !std::isfinite(area) ? "the face's area or normal overflows (coordinates too large)"
                                                  : "the face is degenerate (zero area)");
        const Vec3 ke = s.materials[m].emission;
        if (!std::isfinite(float(M_PI) * area * std::fmax(ke.x, std::fmax(ke.y, ke.z))))
          r.fail("the face's emitted power overflows (emission times area)");
      }
    } else if (key == "mtllib") {
      std::string name;
      if (!(in >> name)) r.fail("mtllib needs a file name");
      // Inside the scene's folder only: an absolute path or one climbing out with ".." (symlinks
      // resolved) could name any readable file.
      namespace fs = std::filesystem;
      std::error_code ec;
      const fs::path folder = fs::weakly_canonical(fs::absolute(dir_of(path)), ec);
      const fs::path mpath = fs::weakly_canonical(folder / name, ec);
      const auto rel = mpath.lexically_relative(folder);
      if (fs::path(name).is_absolute() || ec || rel.empty() || *rel.begin() == "..")
        r.fail("mtllib must name a file inside the scene's folder (no absolute path, no '..')");
      for (auto& kv : load_mtl(mpath.string())) library[kv.first] = kv.second;
    } else if (key == "usemtl") {
      std::string name;
      if (!(in >> name)) r.fail("usemtl needs a material name");
      auto it = used.find(name);
      if (it != used.end()) {
        current = it->second;
      } else {
        auto lib = library.find(name);
        if (lib == library.end()) r.fail("material '" + name + "' is not defined (mtllib before usemtl?)");
        current = used[name] = s.add_material(lib->second);
      }
    } else if (key == "camera") {
      Vec3 pos = r.vec3(in, "camera position"), target = r.vec3(in, "camera target"),
           up = r.vec3(in, "camera up");
      float fov = r.number(in, "camera vfov_deg");
      r.no_more(in);
      Vec3 dir = target - pos;
      if (!std::isfinite(length(dir)) || !std::isfinite(length(cross(dir, up))))
        r.fail("the camera's direction overflows (target and position too far apart)");
      if (length(dir) <= 0) r.fail("camera target equals its position");
      if (length(cross(dir, up)) <= 0) r.fail("camera up is parallel to the view direction");
      if (!vfov_ok(fov)) r.fail("camera vfov_deg must be in (0, 180)");
      s.camera.position = pos;
      s.camera.direction = normalize(dir);
      s.camera.up = normalize(up);
      s.camera.vfov_deg = fov;
      have_camera = true;
    } else if (key == "vt" || key == "vn" || key == "o" || key == "g" || key == "s" || key == "l" ||
               key == "vp") {
      continue;
    } else {
      r.fail("unknown statement '" + key + "'");
    }
  }
  for (std::size_t i = 0; i < s.triangles.size(); ++i)
    if (s.triangle_area(static_cast<std::uint32_t>(i)) <= 0)
      throw Error(path + ": triangle " + std::to_string(i) + " is degenerate (zero area)");
  if (!have_camera && !s.vertices.empty()) {
    // No camera: look along +z at the middle of the bounding box from far enough to see it all.
    Vec3 lo = s.vertices[0], hi = s.vertices[0];
    for (const auto& v : s.vertices)
      for (int d = 0; d < 3; ++d) {
        lo[d] = std::fmin(lo[d], v[d]);
        hi[d] = std::fmax(hi[d], v[d]);
      }
    Vec3 c = (lo + hi) * 0.5f;
    float half = 0.5f * std::fmax(hi.x - lo.x, hi.y - lo.y);
    s.camera.vfov_deg = 40.0f;
    s.camera.position = {c.x, c.y, lo.z - half / std::tan(20.0f * kPi / 180.0f) * 1.1f};
  }
  s.validate();
  return s;
}

std::vector<std::string> scene_search_dirs() {
  std::vector<std::string> dirs;
  if (const char* e = std::getenv("BHCL_SCENES_DIR")) dirs.push_back(e);
  char buf[4096];
  ssize_t n = readlink("/proc/self/exe", buf, sizeof buf - 1);
  if (n > 0) {
    buf[n] = '\0';
    std::string exe_dir = dir_of(buf);
    dirs.push_back(exe_dir + "/scenes");
    dirs.push_back(exe_dir + "/../share/blockhash_cl/scenes");
  }
#ifdef BHCL_SCENES_SOURCE_DIR
  dirs.push_back(BHCL_SCENES_SOURCE_DIR);
#endif
  return dirs;
}

Scene load_scene(const std::string& name) {
  if (name == "cornell") return cornell_scene();
  bool is_path = name.find('/') != std::string::npos ||
                 (name.size() > 4 && name.compare(name.size() - 4, 4, ".obj") == 0);
  if (is_path) return load_obj_scene(name);
  std::string tried;
  for (const auto& d : scene_search_dirs()) {
    std::string p = d + "/" + name + ".obj";
    if (std::ifstream(p).good()) {
      Scene s = load_obj_scene(p);
      s.name = name;
      return s;
    }
    tried += (tried.empty() ? "" : ", ") + p;
  }
  throw Error("scene '" + name + "' not found: 'cornell' is built in; tried " + tried);
}

}  // namespace bhcl::render
