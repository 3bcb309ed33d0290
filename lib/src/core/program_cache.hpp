// The library's own cache of compiled programs, and the guards around PoCL's kernel cache.
//
// Why: building a program from source costs 0.07-0.1 s in every process even when PoCL's cache
// holds the result (PoCL re-reads and re-parses the bitcode), while a program created from its
// binary builds in about 1 ms. So each program built from source is kept, after its first
// launch (when PoCL has also compiled the work-group functions into the binary), as a file of
// the library's own: CACHE/<file stem>.<16 hex digits>.bin, keyed by a hash of the platform,
// the device, the driver version, the full option string and the source, and holding a checksum
// of what PoCL gave. It is written through the atomic writer (no partial file under its name).
// A file that fails its checks (cut short, emptied, another key, a bad checksum) is removed, the
// program is compiled again from source, and the user is told once.
//
// PoCL's own cache (POCL_CACHE_DIR, else $XDG_CACHE_HOME/pocl/kcache, else
// $HOME/.cache/pocl/kcache) holds the compiled kernels PoCL dlopen()s: a file there cut short by a
// crash or a power loss kills every later process with SIGBUS or SIGABRT inside PoCL. The library
// checks the files it is about to rely on (shared objects against their ELF headers, bitcode
// against its block lengths): the program's folder before a binary is loaded, the whole cache
// once before the first build from source; a damaged program folder is removed (PoCL then
// unpacks or compiles it again) and the user is told once. A PoCL cache folder that cannot be
// made or written (a read-only HOME) is replaced, for this process, by a private temporary one.
//
// Environment: BHCL_CACHE_DIR names the library's folder (default $XDG_CACHE_HOME/blockhash_cl,
// else $HOME/.cache/blockhash_cl); BHCL_PROGRAM_CACHE=0 turns the library's cache off.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace bhcl::detail {

// Prints "blockhash_cl: TEXT" on stderr the first time a message of this kind is given in the
// process (kind: a short tag such as "pocl-cache-damaged").
void note_once(const std::string& kind, const std::string& text);

// PoCL's kernel cache folder, as PoCL 3 picks it ("" when neither POCL_CACHE_DIR, XDG_CACHE_HOME
// nor HOME is set).
std::string pocl_cache_dir();

// Before the first OpenCL call of the process: when PoCL's cache folder cannot be made or written,
// points POCL_CACHE_DIR at a private temporary folder (removed at exit) and says so once; when
// even that fails, throws bhcl::Error naming both folders and the reasons.
void ensure_pocl_cache_usable();

// Why a compiled-kernel file of PoCL's cache cannot be loaded ("" when it looks whole): a shared
// object whose headers point past its end, bitcode whose blocks do, a bad magic, an empty file.
std::string pocl_file_damage(const std::string& path);

// Checks the PoCL cache folder of the program a PoCL binary came from (its path is inside the
// binary); removes it when a file there is damaged. Returns false when nothing could be checked.
bool check_pocl_program_folder(const std::vector<unsigned char>& pocl_binary);

// Checks every program folder of PoCL's cache (once per process; later calls return at once),
// removing the damaged ones.
void check_pocl_cache_once();

// The library's program cache.
class ProgramBinaryCache {
 public:
  // key: everything the compiled program depends on (platform, device, driver, options, source).
  ProgramBinaryCache(const std::string& file, const std::string& key);
  bool enabled() const { return !path_.empty(); }
  const std::string& path() const { return path_; }
  // The stored binary when the file is present and whole; a damaged file is removed (told once).
  std::optional<std::vector<unsigned char>> load() const;
  // Writes the binary (atomic writer); a folder that cannot be written is told once, not thrown.
  void store(const std::vector<unsigned char>& binary) const;

 private:
  std::string path_;
  std::uint64_t key_hash_ = 0, key_hash2_ = 0;
};

// FNV-1a, 64 bits (the cache's key hash and checksum: detects damage, not tampering).
std::uint64_t fnv1a64(const void* data, std::size_t bytes, std::uint64_t basis = 0xcbf29ce484222325ull);

}  // namespace bhcl::detail
