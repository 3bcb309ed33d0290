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

namespace io_detail {

void write_npy(const std::string& path, const void* data, const char* descr, std::size_t item,
               std::size_t rows, std::size_t cols) {
  std::string header = std::string("{'descr': '") + descr + "', 'fortran_order': False, 'shape': (" +
                       std::to_string(rows) + (cols ? ", " + std::to_string(cols) + ")" : ",)") + ", }";
  // Magic (6) + version (2) + length (2) + header + '\n', padded with spaces to 64 bytes.
  const std::size_t unpadded = 10 + header.size() + 1;
  header.append((64 - unpadded % 64) % 64, ' ');
  header += '\n';
  std::string out = "\x93NUMPY";
  out += '\x01';
  out += '\x00';
  out += static_cast<char>(header.size() & 0xff);
  out += static_cast<char>((header.size() >> 8) & 0xff);
  out += header;
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
