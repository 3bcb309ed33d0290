// Point files in every format (PLY ASCII / binary both byte orders, text, NPY, raw float32), the
// format chosen by extension or by content, and each contradiction refused with one line naming
// the file; NPY result files from bhcl knn.
#include "test_util.hpp"

#include <cstring>
#include <iterator>

using namespace bhcl;

namespace {

std::string write_bytes(const std::string& name, const std::string& bytes) {
  std::string path = test::tmp_path(name);
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  return path;
}

template <typename T>
std::string bytes_of(T v, bool big_endian = false) {
  std::string s(sizeof(T), '\0');
  std::memcpy(s.data(), &v, sizeof(T));
  if (big_endian) std::reverse(s.begin(), s.end());
  return s;
}

// An NPY v1.0 file with the given header dict and body.
std::string npy(const std::string& dict, const std::string& body) {
  std::string header = dict;
  while ((10 + header.size() + 1) % 64) header += ' ';
  header += '\n';
  std::string s = "\x93NUMPY";
  s += '\x01';
  s += '\x00';
  s += static_cast<char>(header.size() & 0xff);
  s += static_cast<char>(header.size() >> 8);
  return s + header + body;
}

// The data of an NPY file written by bhcl (version 1.0: the header length at bytes 8-9).
template <typename T>
std::vector<T> npy_body(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::string all((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  REQUIRE(all.size() >= 10);
  REQUIRE(all.compare(0, 6, "\x93NUMPY") == 0);
  const std::size_t off = 10 + (static_cast<unsigned char>(all[8]) | (static_cast<unsigned char>(all[9]) << 8));
  REQUIRE(off % 64 == 0);
  REQUIRE((all.size() - off) % sizeof(T) == 0);
  std::vector<T> v((all.size() - off) / sizeof(T));
  std::memcpy(v.data(), all.data() + off, all.size() - off);
  return v;
}

const std::vector<float> kPts = {1.5f, -2.25f, 3.0f, 0.1f, 0.2f, 0.3f, -1e-3f, 4e5f, 7.0f};

void check_refused(const std::string& path, const std::string& expect) {
  INFO(path << " (expect '" << expect << "')");
  const std::string m = test::error_of([&] { read_points_file(path); });
  INFO(m);
  CHECK(m.rfind(path + ": ", 0) == 0);  // names the file first
  CHECK(m.find(expect) != std::string::npos);
  CHECK(m.find('\n') == std::string::npos);  // one line
}

}  // namespace

TEST_CASE("point_io: PLY ASCII with other properties and elements") {
  std::string ply =
      "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 3\nproperty float x\nproperty float y\n"
      "property float z\nproperty uchar red\nproperty list uchar int extra\nelement face 1\n"
      "property list uchar int vertex_indices\nend_header\n"
      "1.5 -2.25 3 255 2 7 8\n0.1 0.2 0.3 0 0\n-0.001 4e5 7 12 1 9\n3 0 1 2\n";
  CHECK(read_points_file(write_bytes("ascii.ply", ply)) == kPts);
  // Without an extension the header says PLY.
  CHECK(read_points_file(write_bytes("ascii_ply_noext", ply)) == kPts);
}

TEST_CASE("point_io: PLY binary, little and big endian, float and double, an element before the vertices") {
  for (bool big : {false, true}) {
    for (bool dbl : {false, true}) {
      CAPTURE(big);
      CAPTURE(dbl);
      std::string head = std::string("ply\nformat ") + (big ? "binary_big_endian" : "binary_little_endian") +
                         " 1.0\nelement camera 1\nproperty list uchar float view\nelement vertex 3\n"
                         "property short flags\nproperty " + (dbl ? "double" : "float") + " x\nproperty " +
                         (dbl ? "double" : "float") + " y\nproperty " + (dbl ? "double" : "float") +
                         " z\nproperty float confidence\nend_header\n";
      std::string body = bytes_of<std::uint8_t>(2) + bytes_of(1.0f, big) + bytes_of(2.0f, big);
      for (int i = 0; i < 3; ++i) {
        body += bytes_of<std::int16_t>(static_cast<std::int16_t>(-i), big);
        for (int a = 0; a < 3; ++a)
          body += dbl ? bytes_of(static_cast<double>(kPts[3 * i + a]), big) : bytes_of(kPts[3 * i + a], big);
        body += bytes_of(0.5f, big);
      }
      std::string name = std::string("bin_") + (big ? "be" : "le") + (dbl ? "_f64" : "_f32") + ".ply";
      CHECK(read_points_file(write_bytes(name, head + body)) == kPts);
      // Cut short: refused, not padded.
      check_refused(write_bytes("cut_" + name, head + body.substr(0, body.size() - 3)), "truncated");
    }
  }
}

TEST_CASE("point_io: text, white space or commas, comments, blank lines, CRLF") {
  std::string txt = "# x y z\n1.5 -2.25 3\n\n0.1,0.2,0.3  # a comment\r\n  -1e-3\t4e5 , 7\n";
  CHECK(read_points_file(write_bytes("pts.txt", txt)) == kPts);
  CHECK(read_points_file(write_bytes("pts.xyz", txt)) == kPts);
  CHECK(read_points_file(write_bytes("pts.csv", "1.5,-2.25,3\n0.1,0.2,0.3\n-0.001,400000,7\n")) == kPts);
  // No extension: the content is text.
  CHECK(read_points_file(write_bytes("pts_noext", txt)) == kPts);
  CHECK(read_points_file(write_bytes("only_comments.txt", "# nothing\n\n")).empty());
}

TEST_CASE("point_io: NPY float32 and float64, either byte order, and NPY results round trip") {
  std::string f4, f8, f8be;
  for (float v : kPts) {
    f4 += bytes_of(v);
    f8 += bytes_of(static_cast<double>(v));
    f8be += bytes_of(static_cast<double>(v), true);
  }
  CHECK(read_points_file(write_bytes("a_f4.npy", npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 3), }", f4))) == kPts);
  CHECK(read_points_file(write_bytes("a_f8.npy", npy("{'descr': '<f8', 'fortran_order': False, 'shape': (3, 3), }", f8))) == kPts);
  CHECK(read_points_file(write_bytes("a_f8be.npy", npy("{'descr': '>f8', 'fortran_order': False, 'shape': (3, 3), }", f8be))) == kPts);
  CHECK(read_points_file(write_bytes("a_f4_noext", npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 3), }", f4))) == kPts);
  // write_npy_file output reads back (points) and has the documented header.
  std::string P = test::tmp_path("written.npy");
  write_npy_file(P, kPts.data(), 3, 3);
  CHECK(read_points_file(P) == kPts);
  std::vector<std::int32_t> ids = {1, 2, 3, 4, 5, 6};
  std::string I = test::tmp_path("ids.npy");
  write_array_file(I, ids.data(), 3, 2);
  std::ifstream in(I, std::ios::binary);
  std::string all((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  CHECK(all.find("'descr': '<i4', 'fortran_order': False, 'shape': (3, 2)") != std::string::npos);
  CHECK(npy_body<std::int32_t>(I) == ids);  // the header padded to a multiple of 64 bytes
  std::vector<std::int32_t> counts = {4, 0, 2};
  write_array_file(I, counts.data(), 3, 0);
  std::ifstream in1(I, std::ios::binary);
  std::string one((std::istreambuf_iterator<char>(in1)), std::istreambuf_iterator<char>());
  CHECK(one.find("'shape': (3,)") != std::string::npos);
  CHECK(npy_body<std::int32_t>(I) == counts);
  // Without .npy: raw bytes, as before.
  std::string R = test::tmp_path("ids.i32");
  write_array_file(R, ids.data(), 3, 2);
  CHECK(test::read_raw<std::int32_t>(R) == ids);
}

TEST_CASE("point_io: a file whose content contradicts its format is refused with one line") {
  std::string f4;
  for (float v : kPts) f4 += bytes_of(v);
  const std::string good_head = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n";
  // Text given as raw: exactly 12 bytes, a multiple of 12, so only the content gives it away.
  check_refused(write_bytes("text_as.f32", "1 2 3\n4 5 6\n"), "looks like a text file, not raw float32");
  check_refused(write_bytes("ragged_text.f32", "1 2 3\n4 5 6 7\n"), "not a multiple of 12");
  check_refused(write_bytes("ply_as.f32", good_head + "property float z\nend_header\n1 2 3\n"), "is a PLY file");
  check_refused(write_bytes("npy_as.txt", npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 3), }", f4)),
                "is an NPY file");
  check_refused(write_bytes("noz.ply", good_head + "end_header\n1 2\n"), "no property z");
  check_refused(write_bytes("intx.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty int x\nproperty float y\n"
                                        "property float z\nend_header\n1 2 3\n"), "x is not float or double");
  check_refused(write_bytes("novertex.ply", "ply\nformat ascii 1.0\nelement face 0\nend_header\n"), "no vertex element");
  check_refused(write_bytes("noend.ply", good_head + "property float z\n"), "no end_header");
  check_refused(write_bytes("short.ply", "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                                         "property float z\nend_header\n1 2 3\n4 5\n"), "truncated");
  check_refused(write_bytes("notply.ply", "1 2 3\n"), "not a PLY file");
  check_refused(write_bytes("i4.npy", npy("{'descr': '<i4', 'fortran_order': False, 'shape': (3, 3), }", f4)),
                "is not float32 or float64");
  check_refused(write_bytes("n4.npy", npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 4), }", f4 + f4.substr(0, 12))),
                "not (N, 3)");
  check_refused(write_bytes("fortran.npy", npy("{'descr': '<f4', 'fortran_order': True, 'shape': (3, 3), }", f4)),
                "Fortran order");
  check_refused(write_bytes("cut.npy", npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 3), }", f4.substr(0, 30))),
                "the NPY data holds 30 bytes");
  check_refused(write_bytes("notnpy.npy", "1 2 3\n"), "not an NPY file");
  check_refused(write_bytes("word.txt", "1 2 3\nx y z\n"), "line 2: 'x' is not a number");
  check_refused(write_bytes("two.txt", "1 2 3\n4 5\n"), "line 2: expected 3 numbers (x y z), got 2");
  check_refused(write_bytes("binary.txt", std::string("1 2 3\n\x01\x02\x03 4 5\n", 14)), "binary data");
  check_refused(write_bytes("huge.txt", "1 2 3\n1e300 0 0\n"), "point 1 has coordinate x = 1e+300, beyond the float range");
  check_refused(write_bytes("nan.txt", "1 2 3\n0 nan 0\n"), "point 1 has a non-finite coordinate y");
}

TEST_CASE("point_io: bhcl knn reads PLY and text, writes NPY results, refuses a contradiction") {
  auto pts = datasets::uniform(500, 91);
  auto qs = datasets::uniform(20, 92);
  std::string ply = "ply\nformat binary_little_endian 1.0\nelement vertex 500\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n";
  ply.append(reinterpret_cast<const char*>(pts.data()), pts.size() * sizeof(float));
  std::string P = write_bytes("knn_pts.ply", ply);
  std::ostringstream txt;
  txt.precision(9);
  for (std::size_t i = 0; i < qs.size(); i += 3) txt << qs[i] << ", " << qs[i + 1] << ", " << qs[i + 2] << "\n";
  std::string Q = write_bytes("knn_q.txt", txt.str());
  std::string I = test::tmp_path("knn_ids.npy"), D = test::tmp_path("knn_d2.npy"), C = test::tmp_path("knn_c.npy");
  std::string out = test::run_bhcl_ok("knn --points " + P + " --queries " + Q + " --k 4 --method bruteforce --out-ids " + I +
                              " --out-dist2 " + D + " --out-counts " + C);
  SearchParams p = test::knn_params(4);
  KnnResult ref = reference::knn_float(pts.data(), 500, qs.data(), 20, p);
  CHECK(npy_body<std::int32_t>(I) == ref.ids);
  CHECK(npy_body<float>(D) == ref.dist2);
  CHECK(npy_body<std::int32_t>(C) == ref.counts);
  std::string bad = write_bytes("knn_text_as.f32", "1 2 3\n4 5 6\n");
  int rc = test::run_bhcl("knn --points " + bad + " --queries " + Q + " --k 4 --method bruteforce --out-ids " + I +
                          " --out-dist2 " + D,
                      &out);
  CHECK(rc == 1);
  CHECK(out.find(bad + ": looks like a text file") != std::string::npos);
}

TEST_CASE("point_io: declared_point_count reads a file's declared count without its body") {
  std::string f4, f8;
  for (float v : kPts) {
    f4 += bytes_of(v);
    f8 += bytes_of(static_cast<double>(v));
  }
  CHECK(declared_point_count(write_bytes("dc_f4.npy", npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 3), }", f4))) == 3u);
  CHECK(declared_point_count(write_bytes("dc_f8.npy", npy("{'descr': '<f8', 'fortran_order': False, 'shape': (3, 3), }", f8))) == 3u);
  // A header that declares more than its body holds: the declared count (read_points_file refuses it).
  CHECK(declared_point_count(write_bytes("dc_big.npy", npy("{'descr': '<f4', 'fortran_order': False, 'shape': (70000, 3), }", f4))) == 70000u);
  CHECK(declared_point_count(write_bytes("dc.f32", f4)) == 3u);  // raw: by its size
  CHECK(declared_point_count(write_bytes("dc.txt", "0 0 0\n1 1 1\n")) == 0u);  // text: not declared
  CHECK(declared_point_count(test::tmp_path("dc_missing.npy")) == 0u);
}
