#include "blockhash_cl/atomic_file.hpp"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdlib>
#include <cstring>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include "blockhash_cl/error.hpp"

namespace bhcl {

namespace {
std::string system_reason(int err) { return std::string(" (") + std::strerror(err) + ")"; }
}  // namespace

AtomicFile::AtomicFile(const std::string& path, const std::string& what) : path_(path), what_(what) {
  static std::atomic<unsigned> serial{0};
  // Through a symbolic link: the file it names is replaced (beside it), not the link.
  target_ = path;
  struct stat link {};
  if (::lstat(path.c_str(), &link) == 0 && S_ISLNK(link.st_mode)) {
    if (char* real = ::realpath(path.c_str(), nullptr)) {
      target_ = real;
      std::free(real);
    }
  }
  const std::size_t slash = target_.find_last_of('/');
  const std::string dir = slash == std::string::npos ? std::string() : target_.substr(0, slash + 1);
  const std::string name = slash == std::string::npos ? target_ : target_.substr(slash + 1);
  if (name.empty()) throw Error(path + ": cannot write " + what + " (the path names a directory)");
  struct stat old {};
  const bool had_old = ::stat(path.c_str(), &old) == 0;
  if (had_old && S_ISDIR(old.st_mode)) throw Error(path + ": cannot write " + what + " (a directory)");
  if (had_old && !S_ISREG(old.st_mode)) {
    // A device or FIFO (/dev/null, /dev/stdout): written in place, there is nothing to replace.
    in_place_ = true;
    fd_ = ::open(path.c_str(), O_WRONLY | O_CLOEXEC);
    if (fd_ < 0) throw Error(path + ": cannot open for writing " + what + system_reason(errno));
    return;
  }
  tmp_ = dir + "." + name + ".tmp." + std::to_string(::getpid()) + "." + std::to_string(serial.fetch_add(1));
  fd_ = ::open(tmp_.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  if (fd_ < 0) throw Error(path + ": cannot open for writing " + what + system_reason(errno));
  if (had_old) (void)::fchmod(fd_, old.st_mode & 07777);  // keep the old file's permissions
}

AtomicFile::~AtomicFile() {
  if (fd_ >= 0) ::close(fd_);
  if (!done_ && !tmp_.empty()) ::unlink(tmp_.c_str());
}

void AtomicFile::fail(const std::string& step, int err) {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
  if (!tmp_.empty()) ::unlink(tmp_.c_str());
  done_ = true;
  throw Error(path_ + ": writing " + what_ + " failed" + (step.empty() ? "" : " (" + step + ")") + system_reason(err));
}

void AtomicFile::write(const void* data, std::size_t bytes) {
  if (fd_ < 0) throw Error(path_ + ": writing " + what_ + " after the file was closed");
  const char* p = static_cast<const char*>(data);
  while (bytes > 0) {
    const ssize_t w = ::write(fd_, p, std::min<std::size_t>(bytes, std::size_t(1) << 30));
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) fail("", w < 0 ? errno : ENOSPC);
    p += w;
    bytes -= static_cast<std::size_t>(w);
    size_ += static_cast<std::uint64_t>(w);
  }
}

void AtomicFile::write_at(std::uint64_t offset, const void* data, std::size_t bytes) {
  if (fd_ < 0) throw Error(path_ + ": writing " + what_ + " after the file was closed");
  if (in_place_) throw Error(path_ + ": " + what_ + " cannot be written to a device or FIFO (its header is known only at the end)");
  if (offset + bytes > size_) throw Error(path_ + ": internal error: write_at past what was written");
  const char* p = static_cast<const char*>(data);
  while (bytes > 0) {
    const ssize_t w = ::pwrite(fd_, p, bytes, static_cast<off_t>(offset));
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) fail("", w < 0 ? errno : ENOSPC);
    p += w;
    bytes -= static_cast<std::size_t>(w);
    offset += static_cast<std::uint64_t>(w);
  }
}

void AtomicFile::commit() {
  if (fd_ < 0) throw Error(path_ + ": writing " + what_ + " after the file was closed");
  if (in_place_) {
    const int fd = fd_;
    fd_ = -1;
    done_ = true;
    if (::close(fd) != 0) throw Error(path_ + ": writing " + what_ + " failed (close)" + system_reason(errno));
    return;
  }
  if (::fsync(fd_) != 0 && errno != EINVAL && errno != EROFS) fail("fsync", errno);
  const int fd = fd_;
  fd_ = -1;
  if (::close(fd) != 0) {
    const int err = errno;
    ::unlink(tmp_.c_str());
    done_ = true;
    throw Error(path_ + ": writing " + what_ + " failed (close)" + system_reason(err));
  }
  if (::rename(tmp_.c_str(), target_.c_str()) != 0) {
    const int err = errno;
    ::unlink(tmp_.c_str());
    done_ = true;
    throw Error(path_ + ": writing " + what_ + " failed (rename of the temporary " + tmp_ + ")" + system_reason(err));
  }
  done_ = true;
}

}  // namespace bhcl
