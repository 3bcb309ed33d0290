// Issue 22, classes 4 and 5: messages that name the right thing (text encodings, MTL integers),
// and sizes checked before allocation (point files past the index range, kNN results that
// cannot fit).
#include <fcntl.h>

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

TEST_CASE("sizes: a single index of more than 2^31 - 2 points is refused before anything is read or allocated") {
  // 2^31 - 1 points behind a 4-point buffer: every method refuses from N alone (a read past the
  // buffer would fault, an allocation of the points' copies would take 25 GB).
  const std::vector<float> tiny(12, 0.5f);
  for (const std::string& method : method_names()) {
    std::string msg;
    try {
      make_index(method, test::runtime(), tiny.data(), std::size_t(0x7fffffff));
    } catch (const Error& e) {
      msg = e.what();
    }
    CHECK_MESSAGE(msg.find(method + ": N = 2147483647 points exceeds one index's int32 id range (at most 2^31 - 2 "
                           "points") != std::string::npos,
                  method << ": " << msg);
  }
}

TEST_CASE("sizes: point files past the index range are refused before they are read") {
  // A sparse raw file of 2^31 - 1 points (25.8 GB on paper, nothing on disk).
  const std::string raw = test::tmp_path("huge.f32");
  {
    const int fd = open(raw.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    REQUIRE(fd >= 0);
    REQUIRE(ftruncate(fd, off_t(0x7fffffff) * 12) == 0);
    close(fd);
  }
  std::string msg = error_of(raw);
  CHECK(msg.find("holds 2147483647 points (by its size)") != std::string::npos);
  CHECK(msg.find("refused before reading") != std::string::npos);
  std::remove(raw.c_str());
  // NPY and PLY headers that declare more points than the file could ever hold in the range.
  std::string header = "{'descr': '<f4', 'fortran_order': False, 'shape': (3000000000, 3), }";
  while ((header.size() + 11) % 64) header += ' ';
  header += '\n';
  std::string npy = std::string("\x93NUMPY\x01\x00", 8);
  npy += static_cast<char>(header.size() & 0xff);
  npy += static_cast<char>(header.size() >> 8);
  npy += header + std::string(48, '\0');
  msg = error_of(write_bytes("huge.npy", npy));
  CHECK(msg.find("holds 3000000000 points (by its header)") != std::string::npos);
  const std::string ply = "ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\n"
                          "property float y\nproperty float z\nend_header\n" + std::string(36, '\0');
  msg = error_of(write_bytes("huge.ply", ply));
  CHECK(msg.find("holds 4000000000 points (by its header)") != std::string::npos);
  // Files in range still read.
  CHECK(read_points_file(write_bytes("small.f32", std::string(24, '\0'))).size() == 6);
}

TEST_CASE("sizes: a kNN result that cannot fit is refused with what it needs, before any search") {
  const std::vector<float> pts = datasets::uniform(1000, 5);
  BruteForceIndex index(test::runtime(), pts.data(), 1000);
  SearchParams p = test::knn_params(256);
  p.sort_queries = 0;
  KnnResult out;
  // 2^40 queries x k = 256: 2.3 PB of results; the queries are never read.
  CHECK_THROWS_WITH_AS(index.query(pts.data(), std::size_t(1) << 40, p, out),
                       doctest::Contains("the result needs 2256197.9 GB"), Error);
  CHECK_THROWS_WITH_AS(check_result_memory(std::size_t(1) << 40, 256, false, 1, "bruteforce"),
                       doctest::Contains("refused before the search"), Error);
  // A result that fits is answered as before.
  CHECK_NOTHROW(check_result_memory(1000, 10, false, 1, "bruteforce"));
  CHECK_NOTHROW(index.query(pts.data(), 1000, p, out));
  CHECK(out.counts[0] == 256);
}

TEST_CASE("sizes: a radius call that cannot fit is refused with what it needs, before any search") {
  const std::vector<float> pts = datasets::uniform(1000, 6);
  BruteForceIndex index(test::runtime(), pts.data(), 1000);
  RadiusParams rp;
  RadiusResult out;
  // 2^40 queries: their offsets and counts alone are 17.6 TB; the queries are never read (in the
  // Hilbert order the reordered copy doubles it). Before, nothing was checked: std::bad_alloc.
  for (int sort : {0, 1}) {
    rp.sort_queries = sort;
    CHECK_THROWS_WITH_AS(index.radius_search(pts.data(), std::size_t(1) << 40, 0.1f, rp, out),
                         doctest::Contains(sort ? "the radius result needs 57174.8 GB" : "the radius result needs 17592.3 GB"),
                         Error);
  }
  CHECK_THROWS_WITH_AS(index.radius_search(pts.data(), std::size_t(1) << 40, 0.1f, rp, out),
                       doctest::Contains("refused before the search"), Error);
  // What the count pass found, before it is fetched: 2^40 points within the radius of 1000 queries.
  CHECK_THROWS_WITH_AS(check_radius_memory(1000, std::size_t(1) << 40, false, 1, 0, "bruteforce"),
                       doctest::Contains("points within the radius counted by the count pass"), Error);
  CHECK_THROWS_WITH_AS(check_radius_memory(1000, std::size_t(1) << 40, false, 1, 0, "bruteforce"),
                       doctest::Contains("refused before any of them is fetched"), Error);
  // A call that fits is answered as before.
  CHECK_NOTHROW(check_radius_memory(1000, 1000000, false, 2, 0, "bruteforce"));
  rp.sort_queries = -1;
  CHECK_NOTHROW(index.radius_search(pts.data(), 1000, 0.1f, rp, out));
  CHECK(out.n == 1000);
  CHECK(out.count(0) >= 1);
}

TEST_CASE("fork: an index queried in a forked child gets a clear error, never a hang") {
  const std::vector<float> pts = datasets::uniform(2000, 6);
  KdTreeIndex index(test::runtime(), pts.data(), 2000);
  SearchParams p = test::knn_params(4);
  KnnResult out;
  index.query(pts.data(), 100, p, out);
  const std::string msg_path = test::tmp_path("fork_msg_" + std::to_string(getpid()) + ".txt");
  const pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    alarm(120);  // a hang ends the child (and fails the check below)
    std::string text = "answered";
    try {
      KnnResult r;
      index.query(pts.data(), 100, p, r);
    } catch (const Error& e) {
      text = e.what();
    }
    std::ofstream(msg_path) << text;
    _exit(0);
  }
  int status = 0;
  waitpid(pid, &status, 0);
  CHECK(WIFEXITED(status));
  std::ifstream in(msg_path);
  std::stringstream ss;
  ss << in.rdbuf();
  std::remove(msg_path.c_str());
  INFO(ss.str());
  CHECK(ss.str().find("a forked child") != std::string::npos);
  CHECK(ss.str().find("spawn") != std::string::npos);
  // The parent still answers.
  KnnResult again;
  index.query(pts.data(), 100, p, again);
  CHECK(again.ids == out.ids);
}

#ifdef BHCL_HAVE_RENDER
TEST_CASE("messages: MTL illum outside the illumination models is refused at file:line") {
  write_bytes("illum_ok.obj", "mtllib illum.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  for (const char* value : {"99999999999", "-1", "11", "2.5", "x"}) {
    write_bytes("illum.mtl", std::string("newmtl m\nKd 0.5 0.5 0.5\nillum ") + value + "\n");
    INFO(value);
    const std::string msg = test::error_of([&] { render::load_scene(test::tmp_path("illum_ok.obj")); });
    INFO(msg);
    CHECK(msg.find("illum.mtl:3: ") != std::string::npos);
    CHECK(msg.find("must be an integer in [0, 10]") != std::string::npos);
  }
  write_bytes("illum.mtl", "newmtl m\nKd 0.5 0.5 0.5\nKe 1 1 1\nillum 3\n");
  CHECK_NOTHROW(render::load_scene(test::tmp_path("illum_ok.obj")));
}
#endif

}  // namespace bhcl
