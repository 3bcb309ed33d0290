// Writing files: atomically (a temporary renamed over the target), raw and NPY arrays.
#include "blockhash_cl/io.hpp"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <fstream>

#include <sys/stat.h>
#include <fcntl.h>
#include <unistd.h>

#include "blockhash_cl/atomic_file.hpp"
#include "blockhash_cl/error.hpp"
#include "core/io_formats.hpp"

namespace bhcl {

std::string npy_header(const char* descr, std::uint64_t rows, std::size_t cols, std::size_t pad_to) {
  std::string dict = std::string("{'descr': '") + descr + "', 'fortran_order': False, 'shape': (" +
                     std::to_string(rows) + (cols ? ", " + std::to_string(cols) + ")" : ",)") + ", }";
  // Magic (6) + version (2) + length (2) + dict + '\n', padded with spaces.
  const std::size_t want = pad_to ? pad_to : (10 + dict.size() + 1 + 63) / 64 * 64;
  if (want < 10 + dict.size() + 1 || want - 10 > 0xffff)
    throw Error("npy header: " + std::to_string(10 + dict.size() + 1) + " bytes do not fit in " + std::to_string(want));
  dict.append(want - 10 - dict.size() - 1, ' ');
  dict += '\n';
  std::string out = "\x93NUMPY";
  out += '\x01';
  out += '\x00';
  out += static_cast<char>(dict.size() & 0xff);
  out += static_cast<char>((dict.size() >> 8) & 0xff);
  return out + dict;
}

namespace io_detail {

void write_npy(const std::string& path, const void* data, const char* descr, std::size_t item,
               std::size_t rows, std::size_t cols) {
  const std::string out = npy_header(descr, rows, cols);
  write_file(path, {out, std::string_view(static_cast<const char*>(data), rows * (cols ? cols : 1) * item)},
             "the NPY array");
}

}  // namespace io_detail

using io_detail::lower_extension;
using io_detail::write_npy;

void write_file(const std::string& path, std::initializer_list<std::string_view> parts,
                const std::string& what) {
  // A temporary beside the target, written, flushed and renamed over it (AtomicFile).
  AtomicFile f(path, what);
  for (std::string_view part : parts) f.write(part.data(), part.size());
  f.commit();
}

void write_raw_file(const std::string& path, const void* data, std::size_t bytes) {
  write_file(path, {std::string_view(static_cast<const char*>(data), bytes)}, "the raw array");
}

void write_points_file(const std::string& path, const std::vector<float>& xyz) {
  write_raw_file(path, xyz.data(), xyz.size() * sizeof(float));
}

void write_npy_file(const std::string& path, const float* data, std::size_t rows, std::size_t cols) {
  write_npy(path, data, "<f4", 4, rows, cols);
}

void write_npy_file(const std::string& path, const std::int32_t* data, std::size_t rows, std::size_t cols) {
  write_npy(path, data, "<i4", 4, rows, cols);
}

void write_npy_file(const std::string& path, const std::int64_t* data, std::size_t rows, std::size_t cols) {
  write_npy(path, data, "<i8", 8, rows, cols);
}

void write_array_file(const std::string& path, const std::int64_t* data, std::size_t rows,
                      std::size_t cols) {
  if (lower_extension(path) == "npy") write_npy_file(path, data, rows, cols);
  else write_raw_file(path, data, rows * (cols ? cols : 1) * sizeof(std::int64_t));
}

void write_array_file(const std::string& path, const float* data, std::size_t rows, std::size_t cols) {
  if (lower_extension(path) == "npy") write_npy_file(path, data, rows, cols);
  else write_raw_file(path, data, rows * (cols ? cols : 1) * sizeof(float));
}

void write_array_file(const std::string& path, const std::int32_t* data, std::size_t rows,
                      std::size_t cols) {
  if (lower_extension(path) == "npy") write_npy_file(path, data, rows, cols);
  else write_raw_file(path, data, rows * (cols ? cols : 1) * sizeof(std::int32_t));
}

}  // namespace bhcl
