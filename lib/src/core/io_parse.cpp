// The point-file parsers (raw float32, text, PLY, NPY) and the checks they share; the format
// choice and file reading are core/io.cpp's.
#include "core/io_formats.hpp"

#include <algorithm>
#include <cerrno>
#include <cfloat>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <sstream>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/numbers.hpp"

namespace bhcl::io_detail {
namespace {

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_BIG_ENDIAN__
constexpr bool kBigEndianHost = true;
#else
constexpr bool kBigEndianHost = false;
#endif

}  // namespace

[[noreturn]] void fail(const std::string& what, const std::string& msg) { throw Error(what + ": " + msg); }

std::string lower_extension(const std::string& path) {
  const auto slash = path.find_last_of('/');
  const auto dot = path.find_last_of('.');
  if (dot == std::string::npos || (slash != std::string::npos && dot < slash)) return "";
  std::string e = path.substr(dot + 1);
  for (char& c : e) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return e;
}

bool starts_with(const void* data, std::size_t size, const char* magic, std::size_t n) {
  return size >= n && std::memcmp(data, magic, n) == 0;
}

bool is_ply(const void* data, std::size_t size) {
  return starts_with(data, size, "ply\n", 4) || starts_with(data, size, "ply\r\n", 5);
}
bool is_npy(const void* data, std::size_t size) { return starts_with(data, size, "\x93NUMPY", 6); }

// Every byte printable ASCII or white space, and at least one digit.
bool looks_like_text(const void* data, std::size_t size) {
  const auto* b = static_cast<const unsigned char*>(data);
  bool digit = false;
  for (std::size_t i = 0; i < size; ++i) {
    const unsigned char c = b[i];
    if (c == '\n' || c == '\r' || c == '\t' || (c >= 0x20 && c < 0x7f)) {
      digit = digit || (c >= '0' && c <= '9');
      continue;
    }
    return false;
  }
  return digit;
}

// UTF-16 text: a byte order mark (FF FE or FE FF), or, without one, printable ASCII in every
// other byte with zeros between (checked over the first 256 bytes).
bool looks_like_utf16(const unsigned char* b, std::size_t size) {
  if (size >= 2 && ((b[0] == 0xFF && b[1] == 0xFE) || (b[0] == 0xFE && b[1] == 0xFF))) return true;
  const std::size_t m = std::min<std::size_t>(size, 256) & ~std::size_t(1);
  if (m < 4) return false;
  for (int zero_at = 0; zero_at < 2; ++zero_at) {
    bool ok = true, digit = false;
    for (std::size_t i = 0; i < m && ok; i += 2) {
      const unsigned char z = b[i + zero_at], c = b[i + 1 - zero_at];
      ok = z == 0 && (c == '\n' || c == '\r' || c == '\t' || (c >= 0x20 && c < 0x7f));
      digit = digit || (c >= '0' && c <= '9');
    }
    if (ok && digit) return true;
  }
  return false;
}

// read_points_file_f64: while set, every double coordinate a parser reads is also kept here at
// its value index (the float copy is what the parsers return; a float source fills none).
thread_local std::vector<double>* t_wide = nullptr;

// A double coordinate as float: refused (not turned into inf) when it does not fit.
float to_float(double v, const std::string& what, std::size_t value_index) {
  if (t_wide) {
    if (t_wide->size() <= value_index) t_wide->resize(value_index + 1, 0.0);
    (*t_wide)[value_index] = v;
  }
  // What rounds to a finite float is accepted (issue 38: 3.4028235e+38, FLT_MAX as numpy prints
  // float32, is 3.4e30 above FLT_MAX and rounds to it): below FLT_MAX + half its ulp
  // (2^128 - 2^103, which itself rounds to even, away to infinity) the conversion is finite.
  constexpr double kFloatRoundsToInf = 0x1.ffffffp+127;
  if (std::isfinite(v) && std::fabs(v) >= kFloatRoundsToInf) {
    std::ostringstream os;
    os << "point " << value_index / 3 << " has coordinate " << "xyz"[value_index % 3] << " = " << v
       << ", beyond the float range";
    fail(what, os.str());
  }
  return static_cast<float>(v);
}

void check_finite(const std::vector<float>& xyz, const std::string& what) {
  for (std::size_t i = 0; i < xyz.size(); ++i) {
    if (!std::isfinite(xyz[i])) {
      std::ostringstream os;
      os << "point " << i / 3 << " has a non-finite coordinate " << "xyz"[i % 3] << " = " << xyz[i];
      fail(what, os.str());
    }
  }
}

// ---- raw float32 ----

std::vector<float> parse_raw(const void* data, std::size_t size, const std::string& what) {
  if (is_ply(data, size)) fail(what, "is a PLY file, not raw float32 (name it .ply)");
  if (is_npy(data, size)) fail(what, "is an NPY file, not raw float32 (name it .npy)");
  if (size % 12 != 0) {
    std::ostringstream os;
    os << "size " << size << " bytes is not a multiple of 12 (raw float32 x y z per point)";
    if (size && looks_like_text(data, size)) os << "; it looks like a text file";
    fail(what, os.str());
  }
  if (size && looks_like_text(data, size))
    fail(what, "looks like a text file, not raw float32 (name it .txt or .xyz to read it as text)");
  std::vector<float> xyz(size / 4);
  if (size) std::memcpy(xyz.data(), data, size);
  return xyz;
}

// ---- text ----

std::vector<float> parse_text(const void* data, std::size_t size, const std::string& what) {
  if (is_ply(data, size)) fail(what, "is a PLY file, not text (name it .ply)");
  if (is_npy(data, size)) fail(what, "is an NPY file, not text (name it .npy)");
  const char* p = static_cast<const char*>(data);
  const char* end = p + size;
  std::vector<float> xyz;
  std::size_t line_no = 0;
  std::string token;
  while (p < end) {
    const char* eol = static_cast<const char*>(std::memchr(p, '\n', static_cast<std::size_t>(end - p)));
    if (!eol) eol = end;
    ++line_no;
    const char* q = p;
    p = eol + (eol < end ? 1 : 0);
    int count = 0;
    auto separator = [](char c) { return c == ' ' || c == '\t' || c == ',' || c == '\r'; };
    while (q < eol) {
      while (q < eol && separator(*q)) ++q;
      if (q == eol || *q == '#') break;  // the rest of the line is a comment
      const char* t = q;
      while (q < eol && !separator(*q) && *q != '#') ++q;
      ++count;
      if (count > 3) continue;
      token.assign(t, q);
      // A byte that is no text at all: this is not a text file.
      for (unsigned char c : token)
        if (c < 0x20 || c >= 0x7f) fail(what, "line " + std::to_string(line_no) + ": binary data, not text");
      double v = 0;  // locale-free (numbers.hpp); past the double range: +-inf, refused below
      if (detail::parse_double(token, v) == detail::NumberParse::NotNumber)
        fail(what, "line " + std::to_string(line_no) + ": '" + token.substr(0, 40) +
                       "' is not a number (text point files hold x y z per line; '#' starts a comment)");
      xyz.push_back(to_float(v, what, xyz.size()));
    }
    if (count != 0 && count != 3)
      fail(what, "line " + std::to_string(line_no) + ": expected 3 numbers (x y z), got " +
                     std::to_string(count));
  }
  return xyz;
}

namespace {

enum class PlyType { I8, U8, I16, U16, I32, U32, F32, F64, Invalid };

PlyType ply_type(const std::string& t) {
  if (t == "char" || t == "int8") return PlyType::I8;
  if (t == "uchar" || t == "uint8") return PlyType::U8;
  if (t == "short" || t == "int16") return PlyType::I16;
  if (t == "ushort" || t == "uint16") return PlyType::U16;
  if (t == "int" || t == "int32") return PlyType::I32;
  if (t == "uint" || t == "uint32") return PlyType::U32;
  if (t == "float" || t == "float32") return PlyType::F32;
  if (t == "double" || t == "float64") return PlyType::F64;
  return PlyType::Invalid;
}

std::size_t ply_size(PlyType t) {
  switch (t) {
    case PlyType::I8: case PlyType::U8: return 1;
    case PlyType::I16: case PlyType::U16: return 2;
    case PlyType::I32: case PlyType::U32: case PlyType::F32: return 4;
    case PlyType::F64: return 8;
    default: return 0;
  }
}

struct PlyProperty {
  std::string name;
  PlyType type = PlyType::Invalid;
  bool list = false;
  PlyType count_type = PlyType::Invalid;
};

struct PlyElement {
  std::string name;
  std::size_t count = 0;
  std::vector<PlyProperty> props;
};

// Reads values of the body in order: ASCII tokens or binary scalars of either byte order.
class PlyReader {
 public:
  PlyReader(const unsigned char* p, const unsigned char* end, int format, const std::string& what)
      : p_(p), end_(end), format_(format), what_(what) {}

  double read(PlyType t) {
    if (format_ == 0) return read_ascii();
    const std::size_t n = ply_size(t);
    if (static_cast<std::size_t>(end_ - p_) < n) truncated();
    unsigned char b[8];
    std::memcpy(b, p_, n);
    p_ += n;
    if ((format_ == 2) != kBigEndianHost) std::reverse(b, b + n);
    switch (t) {
      case PlyType::I8: return static_cast<std::int8_t>(b[0]);
      case PlyType::U8: return b[0];
      case PlyType::I16: { std::int16_t v; std::memcpy(&v, b, 2); return v; }
      case PlyType::U16: { std::uint16_t v; std::memcpy(&v, b, 2); return v; }
      case PlyType::I32: { std::int32_t v; std::memcpy(&v, b, 4); return v; }
      case PlyType::U32: { std::uint32_t v; std::memcpy(&v, b, 4); return v; }
      case PlyType::F32: { float v; std::memcpy(&v, b, 4); return v; }
      case PlyType::F64: { double v; std::memcpy(&v, b, 8); return v; }
      default: return 0;
    }
  }
  void skip_property(const PlyProperty& pr) {
    if (!pr.list) {
      read(pr.type);
      return;
    }
    const double n = read(pr.count_type);
    if (!(n >= 0) || n != std::floor(n)) fail(what_, "a list property '" + pr.name + "' has a bad length");
    for (double i = 0; i < n; ++i) read(pr.type);
  }
  void set_context(const std::string& element, std::size_t row) {
    element_ = element;
    row_ = row;
  }

 private:
  [[noreturn]] void truncated() {
    fail(what_, "truncated: " + element_ + " " + std::to_string(row_) + " ends past the end of the file");
  }
  double read_ascii() {
    while (p_ < end_ && std::isspace(*p_)) ++p_;
    if (p_ >= end_) truncated();
    const unsigned char* start = p_;
    while (p_ < end_ && !std::isspace(*p_)) ++p_;
    std::string tok(start, p_);
    double v = 0;  // locale-free (numbers.hpp)
    if (detail::parse_double(tok, v) == detail::NumberParse::NotNumber)
      fail(what_, element_ + " " + std::to_string(row_) + ": '" + tok.substr(0, 40) + "' is not a number");
    return v;
  }
  const unsigned char* p_;
  const unsigned char* end_;
  int format_;  // 0 ascii, 1 binary little endian, 2 binary big endian
  const std::string& what_;
  std::string element_;
  std::size_t row_ = 0;
};
}  // namespace

namespace {

struct PlyHeader {
  int format = -1;  // 0 ascii, 1 binary little endian, 2 binary big endian
  std::vector<PlyElement> elements;
};

// A "property" line's declaration (after the word "property"); `at` names the line.
PlyProperty ply_property(std::istringstream& ls, const std::string& line, const std::string& what,
                         const std::string& at) {
  PlyProperty pr;
  std::string t;
  ls >> t;
  if (t == "list") {
    std::string ct, it;
    ls >> ct >> it >> pr.name;
    pr.list = true;
    pr.count_type = ply_type(ct);
    pr.type = ply_type(it);
    if (pr.count_type == PlyType::Invalid || pr.count_type == PlyType::F32 || pr.count_type == PlyType::F64 ||
        pr.type == PlyType::Invalid)
      fail(what, at + "bad list property '" + line.substr(0, 60) + "'");
  } else {
    pr.type = ply_type(t);
    ls >> pr.name;
    if (pr.type == PlyType::Invalid) fail(what, at + "unknown property type '" + t.substr(0, 20) + "'");
  }
  if (pr.name.empty()) fail(what, at + "a property without a name");
  return pr;
}

// An "element" line's declaration: its name and row count.
PlyElement ply_element(std::istringstream& ls, const std::string& line, const std::string& what,
                       const std::string& at) {
  PlyElement e;
  std::string count;
  ls >> e.name >> count;
  unsigned long long c = 0;
  if (e.name.empty() || detail::parse_integer(count, c) != detail::NumberParse::Ok)
    fail(what, at + "bad element line '" + line.substr(0, 60) + "'");
  e.count = static_cast<std::size_t>(c);
  return e;
}

// The header, up to and including end_header; *p moves to the body's first byte.
PlyHeader parse_ply_header(const unsigned char** p, const unsigned char* end, const std::string& what) {
  PlyHeader h;
  bool header_done = false;
  std::size_t line_no = 0;
  while (*p < end) {
    const auto* eol = static_cast<const unsigned char*>(std::memchr(*p, '\n', static_cast<std::size_t>(end - *p)));
    if (!eol) break;
    std::string line(*p, eol);
    *p = eol + 1;
    ++line_no;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream ls(line);
    std::string word;
    ls >> word;
    const std::string at = "header line " + std::to_string(line_no) + ": ";
    if (line_no == 1 || word.empty() || word == "comment" || word == "obj_info") continue;
    if (word == "end_header") {
      header_done = true;
      break;
    }
    if (word == "format") {
      std::string f, version;
      ls >> f >> version;
      if (f == "ascii") h.format = 0;
      else if (f == "binary_little_endian") h.format = 1;
      else if (f == "binary_big_endian") h.format = 2;
      else fail(what, at + "unknown PLY format '" + f + "'");
    } else if (word == "element") {
      h.elements.push_back(ply_element(ls, line, what, at));
    } else if (word == "property") {
      if (h.elements.empty()) fail(what, at + "a property before any element");
      h.elements.back().props.push_back(ply_property(ls, line, what, at));
    } else {
      fail(what, at + "unexpected '" + word.substr(0, 20) + "'");
    }
  }
  if (!header_done) fail(what, "the PLY header has no end_header line");
  if (h.format < 0) fail(what, "the PLY header has no format line");
  return h;
}

// The vertex element's x, y and z properties (their places in its list), each float or double.
void xyz_properties(const PlyElement& vertex, const std::string& what, int axis_prop[3]) {
  for (int a = 0; a < 3; ++a) {
    const std::string name(1, "xyz"[a]);
    axis_prop[a] = -1;
    for (std::size_t i = 0; i < vertex.props.size(); ++i)
      if (vertex.props[i].name == name) axis_prop[a] = static_cast<int>(i);
    if (axis_prop[a] < 0) fail(what, "the PLY vertex element has no property " + name);
    const PlyProperty& pr = vertex.props[static_cast<std::size_t>(axis_prop[a])];
    if (pr.list || (pr.type != PlyType::F32 && pr.type != PlyType::F64))
      fail(what, "the PLY vertex property " + name + " is not float or double");
  }
}

// The body must be able to hold the declared elements up to the vertices before anything is
// allocated: the fewest bytes a row takes is a digit and a separator per ASCII value (the last
// value of the file needs no separator), the scalar sizes in binary.
void check_body_holds(const PlyHeader& h, std::vector<PlyElement>::const_iterator vit, std::size_t remaining,
                      const std::string& what) {
  for (auto it = h.elements.begin(); it <= vit; ++it) {
    std::size_t row_min = 0;
    for (const auto& pr : it->props) row_min += h.format == 0 ? 2 : ply_size(pr.list ? pr.count_type : pr.type);
    if (it->props.empty() && it->count > 0 && it == vit) fail(what, "the PLY vertex element has no properties");
    if (row_min > 0 && it->count > (remaining + (h.format == 0 ? 1 : 0)) / row_min)
      fail(what, "truncated: the header declares " + std::to_string(it->count) + " " + it->name +
                     " rows, more than the file holds");
  }
}

}  // namespace

std::vector<float> parse_ply(const void* data, std::size_t size, const std::string& what) {
  if (!is_ply(data, size)) {
    if (is_npy(data, size)) fail(what, "is an NPY file, not PLY (name it .npy)");
    fail(what, "not a PLY file (the first line is not 'ply')");
  }
  const auto* bytes = static_cast<const unsigned char*>(data);
  const unsigned char* end = bytes + size;
  const unsigned char* p = bytes;
  const PlyHeader h = parse_ply_header(&p, end, what);
  auto vit = std::find_if(h.elements.begin(), h.elements.end(), [](const PlyElement& e) { return e.name == "vertex"; });
  if (vit == h.elements.end()) fail(what, "the PLY file has no vertex element");
  int axis_prop[3];
  xyz_properties(*vit, what, axis_prop);
  check_body_holds(h, vit, static_cast<std::size_t>(end - p), what);
  PlyReader reader(p, end, h.format, what);
  for (auto it = h.elements.begin(); it < vit; ++it)  // elements before the vertices: skipped
    for (std::size_t r = 0; !it->props.empty() && r < it->count; ++r) {
      reader.set_context(it->name, r);
      for (const auto& pr : it->props) reader.skip_property(pr);
    }
  std::vector<float> xyz(vit->count * 3);
  for (std::size_t r = 0; r < vit->count; ++r) {
    reader.set_context("vertex", r);
    for (std::size_t i = 0; i < vit->props.size(); ++i) {
      const PlyProperty& pr = vit->props[i];
      int axis = -1;
      for (int a = 0; a < 3; ++a)
        if (axis_prop[a] == static_cast<int>(i)) axis = a;
      if (axis < 0) {
        reader.skip_property(pr);
        continue;
      }
      const double v = reader.read(pr.type);
      xyz[3 * r + static_cast<std::size_t>(axis)] = to_float(v, what, 3 * r + static_cast<std::size_t>(axis));
    }
  }
  return xyz;
}

// ---- NPY ----

std::vector<float> parse_npy(const void* data, std::size_t size, const std::string& what) {
  if (!is_npy(data, size)) {
    if (is_ply(data, size)) fail(what, "is a PLY file, not NPY (name it .ply)");
    fail(what, "not an NPY file (no \\x93NUMPY magic)");
  }
  const auto* b = static_cast<const unsigned char*>(data);
  if (size < 10) fail(what, "truncated NPY header");
  const int major = b[6];
  std::size_t header_len = 0, offset = 0;
  if (major == 1) {
    header_len = b[8] | (std::size_t(b[9]) << 8);
    offset = 10;
  } else if (major == 2 || major == 3) {
    if (size < 12) fail(what, "truncated NPY header");
    header_len = b[8] | (std::size_t(b[9]) << 8) | (std::size_t(b[10]) << 16) | (std::size_t(b[11]) << 24);
    offset = 12;
  } else {
    fail(what, "NPY version " + std::to_string(major) + " is not supported");
  }
  if (header_len > size - offset) fail(what, "truncated NPY header");
  const std::string h(reinterpret_cast<const char*>(b + offset), header_len);
  offset += header_len;
  auto value_of = [&](const std::string& key) {
    const auto k = h.find("'" + key + "'");
    if (k == std::string::npos) fail(what, "the NPY header has no '" + key + "'");
    auto colon = h.find(':', k);
    if (colon == std::string::npos) fail(what, "bad NPY header");
    auto v = h.find_first_not_of(' ', colon + 1);
    if (v == std::string::npos) fail(what, "bad NPY header");
    return h.substr(v);
  };
  std::string descr = value_of("descr");
  if (descr.size() < 2 || descr[0] != '\'') fail(what, "bad NPY descr");
  descr = descr.substr(1, descr.find('\'', 1) == std::string::npos ? 0 : descr.find('\'', 1) - 1);
  std::size_t item = 0;
  bool big = false;
  if (descr == "<f4" || descr == "=f4") item = 4;
  else if (descr == "<f8" || descr == "=f8") item = 8;
  else if (descr == ">f4") item = 4, big = true;
  else if (descr == ">f8") item = 8, big = true;
  else fail(what, "NPY dtype '" + descr.substr(0, 20) + "' is not float32 or float64");
  if (value_of("fortran_order").rfind("False", 0) != 0)
    fail(what, "the NPY array is in Fortran order (save it in C order)");
  const std::string shape = value_of("shape");
  if (shape.empty() || shape[0] != '(') fail(what, "bad NPY shape");
  const std::string dims_text = shape.substr(1, shape.find(')') == std::string::npos ? 0 : shape.find(')') - 1);
  std::vector<unsigned long long> dims;
  {
    std::string t = dims_text;
    for (char& c : t)
      if (c == ',') c = ' ';
    std::istringstream ds(t);
    std::string d;
    while (ds >> d) {
      unsigned long long v = 0;
      if (detail::parse_integer(d, v) != detail::NumberParse::Ok) fail(what, "bad NPY shape (" + dims_text.substr(0, 40) + ")");
      dims.push_back(v);
    }
  }
  if (dims.size() != 2 || dims[1] != 3)
    fail(what, "the NPY array has shape (" + dims_text.substr(0, 40) + "), not (N, 3)");
  const std::size_t body = size - offset;
  if (dims[0] > body / (3 * item) || dims[0] * 3 * item != body)
    fail(what, "the NPY data holds " + std::to_string(body) + " bytes, shape (" + std::to_string(dims[0]) +
                   ", 3) of " + descr + " needs " + (dims[0] > body ? "more" : std::to_string(dims[0] * 3 * item)));
  const std::size_t n = static_cast<std::size_t>(dims[0]) * 3;
  std::vector<float> xyz(n);
  for (std::size_t i = 0; i < n; ++i) {
    unsigned char v[8];
    std::memcpy(v, b + offset + i * item, item);
    if (big != kBigEndianHost) std::reverse(v, v + item);
    if (item == 4) {
      std::memcpy(&xyz[i], v, 4);
    } else {
      double d;
      std::memcpy(&d, v, 8);
      xyz[i] = to_float(d, what, i);
    }
  }
  return xyz;
}
}  // namespace bhcl::io_detail
