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

namespace {

std::string system_reason(int err) { return std::string(" (") + std::strerror(err) + ")"; }

}  // namespace

void write_file(const std::string& path, std::initializer_list<std::string_view> parts,
                const std::string& what) {
  // A temporary beside the target (same directory, so the rename is atomic), written, flushed to
  // the disk and renamed over it: a failure or a kill leaves the old file as it was.
  static std::atomic<unsigned> serial{0};
  // Through a symbolic link: the file it names is replaced (beside it), not the link.
  std::string target = path;
  struct stat link {};
  if (::lstat(path.c_str(), &link) == 0 && S_ISLNK(link.st_mode)) {
    if (char* real = ::realpath(path.c_str(), nullptr)) {
      target = real;
      std::free(real);
    }
  }
  const std::size_t slash = target.find_last_of('/');
  const std::string dir = slash == std::string::npos ? std::string() : target.substr(0, slash + 1);
  const std::string name = slash == std::string::npos ? target : target.substr(slash + 1);
  if (name.empty()) throw Error(path + ": cannot write " + what + " (the path names a directory)");
  const std::string tmp = dir + "." + name + ".tmp." + std::to_string(::getpid()) + "." +
                          std::to_string(serial.fetch_add(1));
  struct stat old {};
  const bool had_old = ::stat(path.c_str(), &old) == 0;
  if (had_old && S_ISDIR(old.st_mode)) throw Error(path + ": cannot write " + what + " (a directory)");
  if (had_old && !S_ISREG(old.st_mode)) {
    // A device or FIFO (/dev/null, /dev/stdout): written in place, there is nothing to replace.
    errno = 0;
    std::ofstream out(path, std::ios::binary);
    if (!out) throw Error(path + ": cannot open for writing " + what + system_reason(errno));
    for (std::string_view part : parts) out.write(part.data(), static_cast<std::streamsize>(part.size()));
    errno = 0;
    out.close();
    if (!out) throw Error(path + ": writing " + what + " failed" + (errno ? system_reason(errno) : std::string()));
    return;
  }
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  if (fd < 0) throw Error(path + ": cannot open for writing " + what + system_reason(errno));
  auto fail = [&](const std::string& step, int err) {
    ::close(fd);
    ::unlink(tmp.c_str());
    return Error(path + ": writing " + what + " failed" + (step.empty() ? "" : " (" + step + ")") +
                 system_reason(err));
  };
  if (had_old) (void)::fchmod(fd, old.st_mode & 07777);  // keep the old file's permissions
  for (std::string_view part : parts) {
    const char* p = part.data();
    std::size_t left = part.size();
    while (left > 0) {
      const ssize_t w = ::write(fd, p, std::min<std::size_t>(left, std::size_t(1) << 30));
      if (w < 0 && errno == EINTR) continue;
      if (w <= 0) throw fail("", w < 0 ? errno : ENOSPC);
      p += w;
      left -= static_cast<std::size_t>(w);
    }
  }
  if (::fsync(fd) != 0 && errno != EINVAL && errno != EROFS) throw fail("fsync", errno);
  if (::close(fd) != 0) {
    const int err = errno;
    ::unlink(tmp.c_str());
    throw Error(path + ": writing " + what + " failed (close)" + system_reason(err));
  }
  if (::rename(tmp.c_str(), target.c_str()) != 0) {
    const int err = errno;
    ::unlink(tmp.c_str());
    throw Error(path + ": writing " + what + " failed (rename of the temporary " + tmp + ")" + system_reason(err));
  }
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
