// Issue 22, classes 4 and 5: messages that name the right thing (text encodings, MTL integers),
// and sizes checked before allocation (point files past the index range, kNN results that
// cannot fit).
#include "test_util.hpp"

#ifdef BHCL_HAVE_RENDER
#include "scene.hpp"
#endif

namespace bhcl {
namespace {

std::string write_bytes(const std::string& name, const std::string& bytes) {
  const std::string path = test::tmp_path(name);
  std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;
  return path;
}

std::string utf16le(const std::string& ascii, bool bom) {
  std::string out = bom ? std::string("\xFF\xFE", 2) : std::string();
  for (char c : ascii) {
    out += c;
    out += '\0';
  }
  return out;
}

std::string error_of(const std::string& path) {
  try {
    read_points_file(path);
  } catch (const Error& e) {
    return e.what();
  }
  return "no error";
}

}  // namespace

TEST_CASE("messages: a UTF-8 byte order mark is accepted, and UTF-16 text is named, not called binary data") {
  const std::string text = "0 0 0\n1 2 3\n# c\n4.5, 5, 6\n";
  const std::vector<float> want = {0, 0, 0, 1, 2, 3, 4.5f, 5, 6};
  CHECK(read_points_file(write_bytes("bom.txt", "\xEF\xBB\xBF" + text)) == want);
  CHECK(read_points_file(write_bytes("bom_noext", "\xEF\xBB\xBF" + text)) == want);
  for (const auto& [name, bytes] : std::vector<std::pair<std::string, std::string>>{
           {"u16bom.txt", utf16le(text, true)},
           {"u16.xyz", utf16le(text, false)},
           {"u16bom_noext", utf16le(text, true)},
           {"u16_noext", utf16le(text, false)}}) {
    const std::string msg = error_of(write_bytes(name, bytes));
    INFO(name << ": " << msg);
    CHECK(msg.find("is UTF-16 text") != std::string::npos);
    CHECK(msg.find(name) != std::string::npos);
    CHECK(msg.find("binary data") == std::string::npos);
  }
}

#ifdef BHCL_HAVE_RENDER
TEST_CASE("messages: MTL illum outside the illumination models is refused at file:line") {
  write_bytes("illum_ok.obj", "mtllib illum.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  for (const char* value : {"99999999999", "-1", "11", "2.5", "x"}) {
    write_bytes("illum.mtl", std::string("newmtl m\nKd 0.5 0.5 0.5\nillum ") + value + "\n");
    INFO(value);
    try {
      render::load_scene(test::tmp_path("illum_ok.obj"));
      FAIL("loaded");
    } catch (const Error& e) {
      const std::string msg = e.what();
      INFO(msg);
      CHECK(msg.find("illum.mtl:3: ") != std::string::npos);
      CHECK(msg.find("must be an integer in [0, 10]") != std::string::npos);
    }
  }
  write_bytes("illum.mtl", "newmtl m\nKd 0.5 0.5 0.5\nKe 1 1 1\nillum 3\n");
  CHECK_NOTHROW(render::load_scene(test::tmp_path("illum_ok.obj")));
}
#endif

}  // namespace bhcl
