#include "blockhash_cl/io.hpp"

#include <algorithm>
#include <cerrno>
#include <cfloat>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <sstream>

#include <sys/stat.h>

#include "blockhash_cl/atomic_file.hpp"
#include "blockhash_cl/error.hpp"

#include "core/io_formats.hpp"

namespace bhcl {

using io_detail::check_finite;
using io_detail::fail;
using io_detail::is_npy;
using io_detail::is_ply;
using io_detail::looks_like_text;
using io_detail::looks_like_utf16;
using io_detail::lower_extension;
using io_detail::parse_npy;
using io_detail::parse_ply;
using io_detail::parse_raw;
using io_detail::parse_text;
using io_detail::t_wide;
using io_detail::to_float;

const char* point_format_name(PointFormat f) {
  switch (f) {
    case PointFormat::Raw: return "raw float32";
    case PointFormat::Text: return "text";
    case PointFormat::Ply: return "PLY";
    case PointFormat::Npy: return "NPY";
    default: return "auto";
  }
}

PointFormat point_format_from_name(const std::string& path) {
  const std::string e = lower_extension(path);
  if (e == "ply") return PointFormat::Ply;
  if (e == "npy") return PointFormat::Npy;
  if (e == "txt" || e == "xyz" || e == "csv" || e == "asc" || e == "pts") return PointFormat::Text;
  if (e == "f32" || e == "bin" || e == "raw") return PointFormat::Raw;
  return PointFormat::Auto;
}

PointFormat sniff_point_format(const void* data, std::size_t size) {
  if (is_ply(data, size)) return PointFormat::Ply;
  if (is_npy(data, size)) return PointFormat::Npy;
  if (size && looks_like_text(data, size)) return PointFormat::Text;
  return PointFormat::Raw;
}

std::vector<float> parse_points(const void* data, std::size_t size, const std::string& what,
                                PointFormat format, bool require_finite) {
  if (format == PointFormat::Auto) format = point_format_from_name(what);
  if (format == PointFormat::Auto || format == PointFormat::Text) {
    // Text as editors save it: a UTF-8 byte order mark is skipped; UTF-16 is named, not called
    // binary data.
    const auto* b = static_cast<const unsigned char*>(data);
    if (size >= 3 && b[0] == 0xEF && b[1] == 0xBB && b[2] == 0xBF) {
      data = b + 3;
      size -= 3;
    } else if (looks_like_utf16(b, size)) {
      fail(what, "is UTF-16 text; text point files are read as ASCII or UTF-8 (convert it, e.g. "
                 "iconv -f UTF-16 -t UTF-8)");
    }
  }
  if (format == PointFormat::Auto) format = sniff_point_format(data, size);
  std::vector<float> xyz;
  switch (format) {
    case PointFormat::Text: xyz = parse_text(data, size, what); break;
    case PointFormat::Ply: xyz = parse_ply(data, size, what); break;
    case PointFormat::Npy: xyz = parse_npy(data, size, what); break;
    default: xyz = parse_raw(data, size, what); break;
  }
  if (require_finite) check_finite(xyz, what);
  return xyz;
}

std::vector<float> parse_points(const void* data, std::size_t size, const std::string& what,
                                bool require_finite) {
  return parse_points(data, size, what, PointFormat::Auto, require_finite);
}

std::uint64_t regular_file_size(const std::string& path, const std::string& what) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0)
    throw Error(path + ": cannot open " + what + " (" + std::strerror(errno) + ")");
  if (!S_ISREG(st.st_mode)) {
    const char* kind = S_ISDIR(st.st_mode)    ? "a directory"
                       : S_ISFIFO(st.st_mode) ? "a FIFO"
                       : S_ISCHR(st.st_mode)  ? "a character device"
                       : S_ISBLK(st.st_mode)  ? "a block device"
                       : S_ISSOCK(st.st_mode) ? "a socket"
                                              : "not a regular file";
    throw Error(path + ": is " + std::string(kind) + ", not " + what + " (a regular file)");
  }
  return static_cast<std::uint64_t>(st.st_size);
}

namespace {

// The point count a file declares before its body is read: raw by its size, NPY by its shape,
// PLY by its vertex element; 0 when the prefix does not say (text, or an unknown header).
std::uint64_t declared_points(const std::string& path, const char* head, std::size_t head_size,
                              std::uint64_t size, const char** by) {
  *by = "header";
  PointFormat f = point_format_from_name(path);
  if (f == PointFormat::Auto) {
    if (is_ply(head, head_size)) f = PointFormat::Ply;
    else if (is_npy(head, head_size)) f = PointFormat::Npy;
    else if (looks_like_text(head, head_size) || looks_like_utf16(reinterpret_cast<const unsigned char*>(head), head_size) ||
             (head_size >= 3 && static_cast<unsigned char>(head[0]) == 0xEF)) f = PointFormat::Text;
    else f = PointFormat::Raw;
  }
  const std::string h(head, head_size);
  auto number_after = [&](const std::string& key, std::size_t limit) -> std::uint64_t {
    const std::size_t at = h.find(key);
    if (at == std::string::npos || at > limit) return 0;
    return std::strtoull(h.c_str() + at + key.size(), nullptr, 10);
  };
  switch (f) {
    case PointFormat::Raw: *by = "size"; return size / 12;
    case PointFormat::Npy: return is_npy(head, head_size) ? number_after("'shape': (", h.size()) : 0;
    case PointFormat::Ply: return is_ply(head, head_size) ? number_after("element vertex ", h.find("end_header")) : 0;
    default: return 0;
  }
}

// declared_points of the file's first 4 KiB, read from `in` (left where that read stopped).
std::uint64_t declared_in_head(std::istream& in, const std::string& path, std::uint64_t size, const char** by) {
  char head[4096];
  in.read(head, static_cast<std::streamsize>(std::min<std::uint64_t>(size, sizeof head)));
  return declared_points(path, head, static_cast<std::size_t>(in.gcount()), size, by);
}

}  // namespace

std::uint64_t declared_point_count(const std::string& path) noexcept {
  try {
    const std::uint64_t size = regular_file_size(path, "a point file");
    std::ifstream in(path, std::ios::binary);
    const char* by = "";
    return in ? declared_in_head(in, path, size, &by) : 0;
  } catch (...) {
    return 0;
  }
}

std::vector<float> read_points_file(const std::string& path, bool require_finite, std::size_t max_points) {
  const std::uint64_t size = regular_file_size(path, "a point file");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path + ": cannot open point file (" + std::strerror(errno) + ")");
  if (max_points) {
    // Sizes before allocation: a file that declares more points than the index range is refused
    // from its size or header, before its body is read.
    const char* by = "";
    const std::uint64_t declared = declared_in_head(in, path, size, &by);
    if (declared > max_points)
      throw Error(path + ": holds " + std::to_string(declared) + " points (by its " + by +
                  "), more than the index range allows (" + std::to_string(max_points) +
                  "): refused before reading it");
    in.clear();
    in.seekg(0);
  }
  std::vector<char> bytes(static_cast<std::size_t>(size));
  if (size > 0 && !in.read(bytes.data(), static_cast<std::streamsize>(size)))
    throw Error(path + ": read failed after " + std::to_string(in.gcount()) + " bytes");
  return parse_points(bytes.data(), bytes.size(), path, require_finite);
}

std::vector<double> read_points_file_f64(const std::string& path, std::vector<float>* as_float,
                                         bool require_finite, std::size_t max_points) {
  std::vector<double> wide;
  struct Sink {  // reset on every exit, errors included
    explicit Sink(std::vector<double>* w) { t_wide = w; }
    ~Sink() { t_wide = nullptr; }
  } sink(&wide);
  std::vector<float> xyz = read_points_file(path, require_finite, max_points);
  // A float source (raw float32, NPY <f4) passed no double: its values widen exactly.
  if (wide.size() != xyz.size()) wide.assign(xyz.begin(), xyz.end());
  if (as_float) *as_float = std::move(xyz);
  return wide;
}

Recentring choose_origin(const double* xyz, std::size_t n) {
  Recentring r;
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (std::size_t i = 0; i < n; ++i)
    for (int d = 0; d < 3; ++d) {
      const double v = xyz[3 * i + d];
      if (!std::isfinite(v)) continue;  // named later by the index build
      lo[d] = std::min(lo[d], v);
      hi[d] = std::max(hi[d], v);
    }
  double far = 0, near = 0, c[3];
  for (int d = 0; d < 3; ++d) {
    if (!(lo[d] <= hi[d])) return r;  // no finite coordinate: nothing to gain
    c[d] = static_cast<double>(static_cast<float>(0.5 * lo[d] + 0.5 * hi[d]));
    far = std::max({far, std::fabs(lo[d]), std::fabs(hi[d])});
    near = std::max({near, std::fabs(lo[d] - c[d]), std::fabs(hi[d] - c[d])});
  }
  // Two bits gained or more (the Python package's rule, blockhash_cl._origin_for): elsewhere the
  // float32 coordinates are as good and stay the caller's own.
  if (far > 4.0 * near)
    for (int d = 0; d < 3; ++d) r.origin[d] = c[d];
  r.recentred = r.origin[0] != 0 || r.origin[1] != 0 || r.origin[2] != 0;
  return r;
}

std::vector<float> relative_points(const double* xyz, std::size_t n, Recentring& r, const std::string& what) {
  std::vector<float> out(3 * n);
  for (std::size_t i = 0; i < 3 * n; ++i) {
    const double v = xyz[i] - r.origin[i % 3];
    if (std::isfinite(v)) r.max_abs_relative = std::max(r.max_abs_relative, std::fabs(v));
    out[i] = to_float(v, what, i);
  }
  const float m = static_cast<float>(r.max_abs_relative);
  r.float32_step = double(std::nextafter(m, INFINITY)) - double(m);
  return out;
}

}  // namespace bhcl
