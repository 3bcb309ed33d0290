#include "blockhash_cl/atomic_file.hpp"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdlib>
#include <cstring>

#include <chrono>
#include <climits>
#include <csignal>
#include <string>
#include <vector>

#include <dirent.h>
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/random.h>
#include <sys/stat.h>
#include <unistd.h>

#include "blockhash_cl/error.hpp"

namespace bhcl {

namespace {
std::string system_reason(int err) { return std::string(" (") + std::strerror(err) + ")"; }

// The temporaries being written now, for the signal handler (install_temporary_cleanup): a fixed
// table, so that the handler touches no allocation, each slot the directory's descriptor and the
// temporary's name within it (unlinkat is async-signal-safe). A slot is claimed by a
// compare-exchange on `state` (0 free, 1 being filled, 2 live); the handler reads live slots only.
struct TmpSlot {
  std::atomic<int> state{0};
  int dirfd = -1;
  char name[NAME_MAX + 1] = {};
};
constexpr int kSlots = 64;
TmpSlot g_slots[kSlots];

int register_temporary(int dirfd, const std::string& name) {
  for (int i = 0; i < kSlots; ++i) {
    int expect = 0;
    if (!g_slots[i].state.compare_exchange_strong(expect, 1)) continue;
    g_slots[i].dirfd = dirfd;
    std::memcpy(g_slots[i].name, name.c_str(), std::min<std::size_t>(name.size() + 1, sizeof g_slots[i].name));
    g_slots[i].name[NAME_MAX] = '\0';
    g_slots[i].state.store(2);
    return i;
  }
  return -1;  // more than kSlots at once: this one is removed by its destructor only
}

void unregister_temporary(int slot) {
  if (slot >= 0) g_slots[slot].state.store(0);
}

extern "C" void remove_temporaries_and_exit(int sig) {
  for (auto& s : g_slots)
    if (s.state.load() == 2) ::unlinkat(s.dirfd, s.name, 0);
  ::_exit(128 + sig);  // the shell's status for a death by signal: 130 SIGINT, 143 SIGTERM, 129 SIGHUP
}

// 64 unpredictable bits: the temporary's name part that no earlier run, no other process and no
// PID reused across containers (a PID-1 entrypoint is always 1) can have taken.
std::uint64_t random_bits() {
  std::uint64_t v = 0;
  if (::getrandom(&v, sizeof v, GRND_NONBLOCK) == static_cast<ssize_t>(sizeof v)) return v;
  static std::atomic<std::uint64_t> counter{0};
  const auto t = std::chrono::steady_clock::now().time_since_epoch().count();
  return (std::uint64_t(t) * 0x9e3779b97f4a7c15ull) ^ (std::uint64_t(::getpid()) << 32) ^ counter.fetch_add(1);
}

std::string hex(std::uint64_t v, int digits) {
  static const char* d = "0123456789abcdef";
  std::string s(digits, '0');
  for (int i = digits - 1; i >= 0; --i, v >>= 4) s[i] = d[v & 15];
  return s;
}

// The part of a temporary's name that names its target: the target's name where the whole
// temporary name fits NAME_MAX, else a hash of it (a valid name of up to 255 bytes must have a
// temporary too; issue 38: ".NAME.tmp.PID.N" was 13-16 bytes longer than the name).
constexpr const char* kTmpTag = ".bhcltmp.";
constexpr std::size_t kTmpExtra = 1 + 9 + 10 + 1 + 16;  // "." NAME ".bhcltmp." PID "." RANDOM
std::string temporary_key(const std::string& name) {
  if (name.size() + kTmpExtra <= NAME_MAX) return name;
  std::uint64_t h = 0xcbf29ce484222325ull;
  for (unsigned char c : name) h = (h ^ c) * 0x100000001b3ull;
  return "h" + hex(h, 16);
}

bool all_digits(const std::string& s) {
  return !s.empty() && std::all_of(s.begin(), s.end(), [](unsigned char c) { return c >= '0' && c <= '9'; });
}

// The PID in a temporary's name of this tool for the target key: ".KEY.bhcltmp.PID.HEX", or the
// older ".KEY.tmp.PID.N"; 0 for any other name.
long temporary_pid(const std::string& entry, const std::string& key) {
  for (const char* tag : {kTmpTag, ".tmp."}) {
    const std::string prefix = "." + key + tag;
    if (entry.size() <= prefix.size() || entry.compare(0, prefix.size(), prefix) != 0) continue;
    const std::string rest = entry.substr(prefix.size());
    const std::size_t dot = rest.find('.');
    if (dot == std::string::npos || !all_digits(rest.substr(0, dot)) || rest.size() - dot - 1 == 0 || dot > 9) continue;
    return std::atol(rest.substr(0, dot).c_str());
  }
  return 0;
}

// Temporaries of this tool for the same target that a process killed before its cleanup left
// (SIGKILL, a power loss): removed when their writer cannot be running, i.e. its PID is no live
// process, or is this process's own (a container's entrypoint is PID 1 in every run; this process
// writes no temporary of this target but the one it is about to make). They never block a run
// (the random part), this only keeps them from piling up.
void remove_stale_temporaries(int dirfd, const std::string& key) {
  const int fd = ::openat(dirfd, ".", O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) return;
  DIR* d = ::fdopendir(fd);
  if (!d) {
    ::close(fd);
    return;
  }
  std::vector<std::string> stale;
  while (const dirent* e = ::readdir(d)) {
    const std::string entry = e->d_name;
    const long pid = temporary_pid(entry, key);
    if (pid <= 0) continue;
    const bool gone = pid == ::getpid() || (::kill(static_cast<pid_t>(pid), 0) != 0 && errno == ESRCH);
    if (gone) stale.push_back(entry);
  }
  ::closedir(d);
  for (const auto& name : stale) {
    bool mine = false;  // one of this process's temporaries being written now (another thread)
    for (auto& s : g_slots)
      if (s.state.load() == 2 && name == s.name) mine = true;
    if (!mine) ::unlinkat(dirfd, name.c_str(), 0);
  }
}
}  // namespace

void install_temporary_cleanup() {
  for (int sig : {SIGINT, SIGTERM, SIGHUP}) {
    struct sigaction old {};
    if (::sigaction(sig, nullptr, &old) == 0 && old.sa_handler == SIG_IGN) continue;  // nohup: stays ignored
    struct sigaction sa {};
    sa.sa_handler = remove_temporaries_and_exit;
    sigemptyset(&sa.sa_mask);
    for (int other : {SIGINT, SIGTERM, SIGHUP}) sigaddset(&sa.sa_mask, other);  // one cleanup at a time
    ::sigaction(sig, &sa, nullptr);
  }
}

AtomicFile::AtomicFile(const std::string& path, const std::string& what) : path_(path), what_(what) {
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
  const std::string dir = slash == std::string::npos ? std::string(".") : slash == 0 ? std::string("/") : target_.substr(0, slash);
  name_ = slash == std::string::npos ? target_ : target_.substr(slash + 1);
  if (name_.empty()) throw Error(path + ": cannot write " + what + " (the path names a directory)");
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
  if (name_.size() > NAME_MAX) throw Error(path + ": cannot open for writing " + what + system_reason(ENAMETOOLONG));
  // The temporary and the rename go through the directory's descriptor, so that only the name's
  // own length counts (a path of 4090 characters has room for no longer one beside it).
  dirfd_ = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dirfd_ < 0) throw Error(path + ": cannot open for writing " + what + " (its directory: " + std::strerror(errno) + ")");
  const std::string key = temporary_key(name_);
  remove_stale_temporaries(dirfd_, key);
  int err = 0;
  for (int attempt = 0; attempt < 16 && fd_ < 0; ++attempt) {
    tmp_name_ = "." + key + kTmpTag + std::to_string(::getpid()) + "." + hex(random_bits(), 16);
    // Registered before it exists: a signal right after the open still finds it (an unlink of a
    // name not made yet does nothing; the random part is no other process's).
    slot_ = register_temporary(dirfd_, tmp_name_);
    // Read and write: a shared writable mapping (map_append) needs both.
    fd_ = ::openat(dirfd_, tmp_name_.c_str(), O_RDWR | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
    err = errno;
    if (fd_ >= 0) break;
    unregister_temporary(slot_);
    slot_ = -1;
    if (err != EEXIST) break;  // another name would fail the same way
  }
  if (fd_ < 0) {
    close_directory();
    throw Error(path + ": cannot open for writing " + what + system_reason(err));
  }
  tmp_ = (slash == std::string::npos ? std::string() : target_.substr(0, slash + 1)) + tmp_name_;
  if (had_old) (void)::fchmod(fd_, old.st_mode & 07777);  // keep the old file's permissions
}

AtomicFile::~AtomicFile() {
  unmap();
  close_direct();
  if (fd_ >= 0) ::close(fd_);
  if (!done_) remove_temporary();
  close_directory();
}

void AtomicFile::remove_temporary() {
  if (!tmp_name_.empty() && dirfd_ >= 0) ::unlinkat(dirfd_, tmp_name_.c_str(), 0);
  unregister_temporary(slot_);
  slot_ = -1;
}

void AtomicFile::close_directory() {
  unregister_temporary(slot_);
  slot_ = -1;
  if (dirfd_ >= 0) ::close(dirfd_);
  dirfd_ = -1;
}

void AtomicFile::unmap() {
  if (map_) ::munmap(map_, map_len_);
  map_ = nullptr;
  map_len_ = 0;
}

void AtomicFile::close_direct() {
  if (direct_fd_ >= 0) ::close(direct_fd_);
  direct_fd_ = -1;
}

void AtomicFile::fail(const std::string& step, int err) {
  unmap();
  close_direct();
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
  remove_temporary();
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

bool AtomicFile::reserve_after(std::uint64_t bytes) {
  const off_t at = static_cast<off_t>(size_);
  int r = 0;
  do r = ::fallocate(fd_, 0, at, static_cast<off_t>(bytes));
  while (r != 0 && errno == EINTR);
  if (r == 0) return true;
  const int err = errno;
  if (err == ENOSPC || err == EFBIG || err == EDQUOT) fail("", err);  // as the write would have
  (void)::ftruncate(fd_, at);  // no fallocate here (EOPNOTSUPP): whatever it reserved let go
  return false;
}

void* AtomicFile::map_append(std::size_t bytes) {
  if (fd_ < 0) throw Error(path_ + ": writing " + what_ + " after the file was closed");
  if (in_place_ || map_ || bytes == 0) return nullptr;
  const off_t at = static_cast<off_t>(size_);
  if (!reserve_after(bytes)) return nullptr;
  // From offset 0 (a mapping starts on a page): the bytes already written lie before the region.
  void* m = ::mmap(nullptr, size_ + bytes, PROT_READ | PROT_WRITE, MAP_SHARED, fd_, 0);
  if (m == MAP_FAILED || ::lseek(fd_, 0, SEEK_END) < 0) {
    if (m != MAP_FAILED) ::munmap(m, size_ + bytes);
    (void)::ftruncate(fd_, at);
    return nullptr;
  }
  map_ = m;
  map_len_ = size_ + bytes;
  size_ += bytes;
  return static_cast<char*>(m) + at;
}

std::size_t AtomicFile::open_direct(std::uint64_t reserve) {
  if (fd_ < 0) throw Error(path_ + ": writing " + what_ + " after the file was closed");
#ifdef O_DIRECT
  if (in_place_ || map_ || direct_fd_ >= 0) return 0;
  const int fd = ::openat(dirfd_, tmp_name_.c_str(), O_WRONLY | O_DIRECT | O_CLOEXEC);
  if (fd < 0) return 0;  // EINVAL: this file system has no O_DIRECT
  direct_fd_ = fd;
  if (reserve > 0) (void)reserve_after(reserve);  // without fallocate the writes reserve as they go
  return 4096;
#else
  (void)reserve;
  return 0;
#endif
}

void AtomicFile::write_direct(std::uint64_t offset, const void* data, std::size_t bytes) {
  if (direct_fd_ < 0) throw Error(path_ + ": internal error: a direct write without open_direct");
  const char* p = static_cast<const char*>(data);
  while (bytes > 0) {
    const ssize_t w = ::pwrite(direct_fd_, p, std::min<std::size_t>(bytes, std::size_t(1) << 30), static_cast<off_t>(offset));
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) fail("", w < 0 ? errno : ENOSPC);
    if (static_cast<std::size_t>(w) % 4096 != 0 && static_cast<std::size_t>(w) != bytes)
      fail("a short direct write", EIO);  // the rest would be misaligned
    p += w;
    bytes -= static_cast<std::size_t>(w);
    offset += static_cast<std::uint64_t>(w);
    size_ = std::max<std::uint64_t>(size_, offset);
  }
}

void AtomicFile::truncate(std::uint64_t size) {
  if (fd_ < 0) throw Error(path_ + ": writing " + what_ + " after the file was closed");
  int r = 0;
  do r = ::ftruncate(fd_, static_cast<off_t>(size));
  while (r != 0 && errno == EINTR);
  if (r != 0) fail("truncate", errno);
  size_ = size;
}

void AtomicFile::commit() {
  if (fd_ < 0) throw Error(path_ + ": writing " + what_ + " after the file was closed");
  unmap();         // its stores are the page cache's: the fsync below flushes them with the rest
  close_direct();  // its writes are on the disk already: the fsync below writes the metadata
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
    remove_temporary();
    done_ = true;
    throw Error(path_ + ": writing " + what_ + " failed (close)" + system_reason(err));
  }
  if (::renameat(dirfd_, tmp_name_.c_str(), dirfd_, name_.c_str()) != 0) {
    const int err = errno;
    remove_temporary();
    done_ = true;
    throw Error(path_ + ": writing " + what_ + " failed (rename of the temporary " + tmp_ + ")" + system_reason(err));
  }
  unregister_temporary(slot_);
  slot_ = -1;
  done_ = true;
}

}  // namespace bhcl
