// A file replaced atomically, written in pieces (issue 22): the bytes go to a temporary beside
// the target (".NAME.bhcltmp.PID.RANDOM" in the same directory, NAME replaced by a hash where
// the temporary's name would pass NAME_MAX; opened with O_EXCL, a new random part on EEXIST), and
// commit() flushes it to the disk
// (fsync), closes it and renames it over the target. Until then the old file is intact; a failure
// anywhere (a full disk, a size limit, no permission) is a bhcl::Error naming the file, what it
// held and the system's reason (strerror), and the temporary is removed, as is the temporary of
// an AtomicFile destroyed without commit(): no partial output ever stands under the target's
// name. A path through a symbolic link replaces the file it names; a path that names a device or
// FIFO (/dev/stdout) is written in place (nothing to replace; write_at is refused there).
// write_file (io.hpp) is the one-shot form. Temporaries of this tool for the same target left by
// a process that cannot be running any more (its PID gone, or this process's own PID: a
// container's PID 1) are removed when the next one is made (issue 38).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

namespace bhcl {

// For a program's main (bhcl): SIGINT, SIGTERM and SIGHUP (those not ignored) remove the
// temporaries being written and exit with 128 + the signal (130, 143, 129). Not installed by the
// library itself: a host program (Python) keeps its own handlers.
void install_temporary_cleanup();

class AtomicFile {
 public:
  AtomicFile(const std::string& path, const std::string& what);
  ~AtomicFile();  // without commit(): the temporary removed, the target untouched
  AtomicFile(const AtomicFile&) = delete;
  AtomicFile& operator=(const AtomicFile&) = delete;

  void write(const void* data, std::size_t bytes);  // appends
  // Overwrites bytes already written (a header whose sizes are known only at the end).
  void write_at(std::uint64_t offset, const void* data, std::size_t bytes);
  // The next `bytes` of the file (after what was written) as memory: reserved on the disk first
  // (fallocate: a full disk or a size limit fails here, as a write would, not as a SIGBUS in a
  // later store) and mapped shared, so that stores there are the file's contents with no copy
  // through write() (issue 37: a 400 MB result's write cost a third of the kernel). Counts as
  // written. Null, and nothing reserved, where the file cannot be mapped (a device or FIFO, a
  // file system without fallocate): the caller writes instead. At most one mapping per file,
  // unmapped at commit (before the flush) or destruction.
  void* map_append(std::size_t bytes);
  // O_DIRECT writes past the page cache (issue 37: on VMs whose fresh pages cost 1-2 ms a MB, a
  // 400 MB result's page-cache pages cost more than its disk write). Opens a second descriptor on
  // the temporary with O_DIRECT and returns the alignment its writes keep (offset, length and
  // memory: 4096), or 0 where it cannot (a device or FIFO, a file system that refuses O_DIRECT:
  // EINVAL on some): the caller writes as before. `reserve` bytes after what was written are
  // reserved first (fallocate; a full disk or a size limit fails here as a write would; none
  // where the file system has no fallocate). At most once a file, before any map_append.
  std::size_t open_direct(std::uint64_t reserve);
  // Whole aligned blocks at `offset` through the O_DIRECT descriptor; the file's size counts
  // them (the largest end written). A failure is the write's (the temporary removed). May run
  // on another thread than the rest, one call at a time.
  void write_direct(std::uint64_t offset, const void* data, std::size_t bytes);
  // The file cut to `size` bytes (after direct writes: the padding of the last block).
  void truncate(std::uint64_t size);
  std::uint64_t size() const { return size_; }
  bool in_place() const { return in_place_; }  // a device or FIFO: written directly
  void commit();
  const std::string& path() const { return path_; }

 private:
  [[noreturn]] void fail(const std::string& step, int err);
  void remove_temporary();
  void close_directory();
  void unmap();
  void close_direct();
  // Reserves `bytes` after what was written (fallocate): false, nothing kept, where the file
  // system has no fallocate; a full disk or a size limit fails here as a write would.
  bool reserve_after(std::uint64_t bytes);
  std::string path_, what_, target_, tmp_;
  std::string name_, tmp_name_;  // the target's and the temporary's names in the directory dirfd_
  int fd_ = -1, dirfd_ = -1;
  int direct_fd_ = -1;  // open_direct's descriptor on the temporary (-1: none)
  int slot_ = -1;                 // the signal handler's table entry (-1: none)
  bool in_place_ = false, done_ = false;
  std::uint64_t size_ = 0;
  void* map_ = nullptr;  // map_append's mapping: the file from offset 0, map_len_ bytes
  std::size_t map_len_ = 0;
};

}  // namespace bhcl
