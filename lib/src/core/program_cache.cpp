// The library's program binary cache and the checks on PoCL's kernel cache (program_cache.hpp).
#include "core/program_cache.hpp"

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <mutex>
#include <set>
#include <system_error>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include "blockhash_cl/atomic_file.hpp"
#include "blockhash_cl/error.hpp"

namespace fs = std::filesystem;

namespace bhcl::detail {

std::uint64_t fnv1a64(const void* data, std::size_t bytes, std::uint64_t basis) {
  const auto* p = static_cast<const unsigned char*>(data);
  std::uint64_t h = basis;
  for (std::size_t i = 0; i < bytes; ++i) {
    h ^= p[i];
    h *= 0x100000001b3ull;
  }
  return h;
}

void note_once(const std::string& kind, const std::string& text) {
  static std::mutex m;
  static std::set<std::string> told;
  std::lock_guard<std::mutex> lock(m);
  if (!told.insert(kind).second) return;
  std::fprintf(stderr, "blockhash_cl: %s\n", text.c_str());
  std::fflush(stderr);
}

namespace {

std::string env_or_empty(const char* name) {
  const char* v = std::getenv(name);
  return v && *v ? std::string(v) : std::string();
}

std::string reason_of(int err) { return std::strerror(err); }

// Why a folder cannot hold new files ("" when it can): made if missing, then a file created and
// removed in it (access() would say yes to root on a read-only file system).
std::string folder_unusable(const std::string& dir) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return ec.message();
  std::string probe = dir + "/.bhcl-probe-XXXXXX";
  std::vector<char> name(probe.begin(), probe.end());
  name.push_back('\0');
  const int fd = ::mkstemp(name.data());
  if (fd < 0) return reason_of(errno);
  ::close(fd);
  ::unlink(name.data());
  return "";
}

// The private PoCL cache of this process, removed at exit.
std::string& private_pocl_dir() {
  static std::string dir;
  return dir;
}
void remove_private_pocl_dir() {
  std::error_code ec;
  if (!private_pocl_dir().empty()) fs::remove_all(private_pocl_dir(), ec);
}

// Reads `bytes` bytes at `offset` (false when the file is shorter).
bool read_at(int fd, std::uint64_t offset, void* out, std::size_t bytes) {
  const ssize_t got = ::pread(fd, out, bytes, static_cast<off_t>(offset));
  return got == static_cast<ssize_t>(bytes);
}

template <typename T>
T load_le(const unsigned char* p) {
  T v;
  std::memcpy(&v, p, sizeof(T));  // the cache is the machine's own: little-endian x86/ARM
  return v;
}

std::string elf_damage(int fd, std::uint64_t size) {
  unsigned char h[64];
  if (size < sizeof h || !read_at(fd, 0, h, sizeof h)) return "shorter than an ELF header";
  if (std::memcmp(h, "\x7f" "ELF", 4) != 0) return "not an ELF file";
  if (h[4] != 2) return "";  // 32-bit objects: not what PoCL writes here; not judged
  const auto phoff = load_le<std::uint64_t>(h + 0x20), shoff = load_le<std::uint64_t>(h + 0x28);
  const auto phentsize = load_le<std::uint16_t>(h + 0x36), phnum = load_le<std::uint16_t>(h + 0x38);
  const auto shentsize = load_le<std::uint16_t>(h + 0x3a), shnum = load_le<std::uint16_t>(h + 0x3c);
  if (phoff + std::uint64_t(phentsize) * phnum > size) return "program headers past the end";
  if (shoff + std::uint64_t(shentsize) * shnum > size) return "section headers past the end";
  // Each loaded segment's bytes inside the file (a mapping past the end is the SIGBUS).
  for (unsigned i = 0; i < phnum && phentsize >= 56; ++i) {
    unsigned char ph[56];
    if (!read_at(fd, phoff + std::uint64_t(i) * phentsize, ph, sizeof ph)) return "program headers past the end";
    const auto off = load_le<std::uint64_t>(ph + 8), filesz = load_le<std::uint64_t>(ph + 32);
    if (off + filesz > size) return "a segment past the end";
  }
  return "";
}

// LLVM bitcode: the top-level blocks' lengths (32-bit words after each ENTER_SUBBLOCK) must end
// inside the file; a file cut short has a block that ends past it.
std::string bitcode_damage(int fd, std::uint64_t size) {
  unsigned char m[20];
  if (size < 8 || !read_at(fd, 0, m, 8)) return "shorter than a bitcode header";
  std::uint64_t begin = 4, end = size;
  if (load_le<std::uint32_t>(m) == 0x0B17C0DEu) {  // the wrapper: offset and size of the bitcode
    if (size < 20 || !read_at(fd, 0, m, 20)) return "a cut bitcode wrapper";
    const std::uint64_t off = load_le<std::uint32_t>(m + 8), len = load_le<std::uint32_t>(m + 12);
    if (off + len > size || len < 8) return "the wrapped bitcode ends past the file";
    if (!read_at(fd, off, m, 4)) return "a cut bitcode wrapper";
    begin = off + 4;
    end = off + len;
  }
  if (!(m[0] == 'B' && m[1] == 'C' && m[2] == 0xC0 && m[3] == 0xDE)) return "not LLVM bitcode";
  std::uint64_t bit = begin * 8;  // top level: abbreviation ids of 2 bits
  int blocks = 0;
  while (bit / 8 + 4 <= end) {
    unsigned char w[16] = {};
    const std::uint64_t byte = bit / 8;
    if (!read_at(fd, byte, w, std::min<std::uint64_t>(sizeof w, end - byte))) return "cut inside a block header";
    std::uint64_t b = bit - byte * 8;
    auto take = [&](int n) {
      std::uint64_t v = 0;
      for (int i = 0; i < n; ++i, ++b) v |= std::uint64_t((w[b / 8] >> (b % 8)) & 1u) << i;
      return v;
    };
    auto vbr = [&](int n) {
      std::uint64_t v = 0;
      for (int shift = 0; shift < 64 && b + n <= 8 * (sizeof w - 4); shift += n - 1) {
        const std::uint64_t chunk = take(n);
        v |= (chunk & ((1u << (n - 1)) - 1)) << shift;
        if (!(chunk >> (n - 1))) break;
      }
      return v;
    };
    if (take(2) != 1) break;  // not ENTER_SUBBLOCK: the padding after the last block
    vbr(8);                   // block id
    vbr(4);                   // its abbreviation width
    b = (b + 31) / 32 * 32;   // aligned to a word, then the block's length in words
    const std::uint64_t len_at = byte + b / 8;
    unsigned char lw[4];
    if (len_at + 4 > end || !read_at(fd, len_at, lw, 4)) return "cut inside a block header";
    const std::uint64_t block_end = len_at + 4 + 4ull * load_le<std::uint32_t>(lw);
    if (block_end > end) return "a block ends past the end of the file";
    bit = block_end * 8;
    ++blocks;
  }
  return blocks ? "" : "no bitcode block";
}

// The program folder of a PoCL cache file: the two levels below the cache's root (XX/YYYY...).
fs::path program_folder_of(const fs::path& root, const fs::path& file) {
  const fs::path rel = file.lexically_relative(root);
  auto it = rel.begin();
  if (it == rel.end()) return {};
  fs::path out = root / *it++;
  if (it == rel.end()) return {};
  return out / *it;
}

bool is_checked_name(const fs::path& p) {
  const std::string ext = p.extension().string();
  return ext == ".so" || ext == ".bc";
}

// The first damaged file under `folder` (its path and why), or none.
std::optional<std::pair<std::string, std::string>> first_damage_in(const fs::path& folder) {
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(folder, ec); !ec && it != fs::recursive_directory_iterator();
       it.increment(ec)) {
    if (!it->is_regular_file(ec) || !is_checked_name(it->path())) continue;
    const std::string why = pocl_file_damage(it->path().string());
    if (!why.empty()) return std::make_pair(it->path().string(), why);
  }
  return std::nullopt;
}

void remove_damaged_folder(const fs::path& folder, const std::string& file, const std::string& why) {
  std::error_code ec;
  fs::remove_all(folder, ec);
  note_once("pocl-cache-damaged",
            "PoCL's kernel cache '" + pocl_cache_dir() + "' held a damaged compiled kernel ('" + file + "': " +
                why + (ec ? "; it could not be removed: " + ec.message()
                          : "); its program folder was removed and is compiled again"));
}

}  // namespace

std::string pocl_cache_dir() {
  if (std::string d = env_or_empty("POCL_CACHE_DIR"); !d.empty()) return d;
  if (std::string x = env_or_empty("XDG_CACHE_HOME"); !x.empty()) return x + "/pocl/kcache";
  if (std::string h = env_or_empty("HOME"); !h.empty()) return h + "/.cache/pocl/kcache";
  return "";
}

void ensure_pocl_cache_usable() {
  static std::once_flag once;
  std::call_once(once, [] {
    const std::string dir = pocl_cache_dir();
    const std::string why = dir.empty() ? "neither POCL_CACHE_DIR, XDG_CACHE_HOME nor HOME is set"
                                        : folder_unusable(dir);
    if (why.empty()) return;
    std::string tmp = env_or_empty("TMPDIR");
    if (tmp.empty()) tmp = "/tmp";
    std::string templ = tmp + "/bhcl-pocl-cache-XXXXXX";
    std::vector<char> name(templ.begin(), templ.end());
    name.push_back('\0');
    if (!::mkdtemp(name.data()))
      throw Error("PoCL's kernel cache folder '" + dir + "' cannot be used (" + why +
                  "), nor a private one under '" + tmp + "' (" + reason_of(errno) +
                  "): set POCL_CACHE_DIR to a writable folder");
    private_pocl_dir() = name.data();
    std::atexit(remove_private_pocl_dir);
    ::setenv("POCL_CACHE_DIR", name.data(), 1);
    note_once("pocl-cache-private", "PoCL's kernel cache folder '" + dir + "' cannot be used (" + why +
                                        "); this process compiles into a private temporary folder '" +
                                        name.data() + "' (set POCL_CACHE_DIR to a writable folder to keep them)");
  });
}

std::string pocl_file_damage(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return "cannot be read: " + reason_of(errno);
  struct stat st {};
  std::string why;
  if (::fstat(fd, &st) != 0) why = "cannot be read: " + reason_of(errno);
  else if (st.st_size == 0) why = "empty";
  else if (fs::path(path).extension() == ".so") why = elf_damage(fd, static_cast<std::uint64_t>(st.st_size));
  else why = bitcode_damage(fd, static_cast<std::uint64_t>(st.st_size));
  ::close(fd);
  return why;
}

bool check_pocl_program_folder(const std::vector<unsigned char>& bin) {
  // PoCL's binary ("poclbin") names its program's folder as XX/YYYY... (letters A-P) near its start.
  const std::string root = pocl_cache_dir();
  if (root.empty() || bin.size() < 16 || std::memcmp(bin.data(), "poclbin", 7) != 0) return false;
  const std::size_t scan = std::min<std::size_t>(bin.size(), 512);
  auto letter = [&](std::size_t i) { return i < scan && bin[i] >= 'A' && bin[i] <= 'P'; };
  for (std::size_t i = 8; i + 4 < scan; ++i) {
    if (!(letter(i) && letter(i + 1) && bin[i + 2] == '/' && letter(i + 3))) continue;
    std::size_t e = i + 3;
    while (letter(e)) ++e;
    if (e >= scan || bin[e] != 0 || e - i < 20) continue;
    const fs::path folder = fs::path(root) / std::string(bin.begin() + i, bin.begin() + e);
    if (auto d = first_damage_in(folder)) remove_damaged_folder(folder, d->first, d->second);
    return true;
  }
  return false;
}

void check_pocl_cache_once() {
  static std::once_flag once;
  std::call_once(once, [] {
    const std::string root = pocl_cache_dir();
    std::error_code ec;
    if (root.empty() || !fs::is_directory(root, ec)) return;
    std::vector<std::pair<fs::path, std::pair<std::string, std::string>>> damaged;
    for (auto it = fs::recursive_directory_iterator(root, ec); !ec && it != fs::recursive_directory_iterator();
         it.increment(ec)) {
      if (!it->is_regular_file(ec) || !is_checked_name(it->path())) continue;
      const fs::path folder = program_folder_of(root, it->path());
      if (folder.empty() || (!damaged.empty() && damaged.back().first == folder)) continue;
      const std::string why = pocl_file_damage(it->path().string());
      if (!why.empty()) damaged.push_back({folder, {it->path().string(), why}});
    }
    for (const auto& [folder, d] : damaged) remove_damaged_folder(folder, d.first, d.second);
  });
}

namespace {
constexpr char kMagic[8] = {'B', 'H', 'C', 'L', 'P', 'R', 'G', '1'};
constexpr std::size_t kHeader = 8 + 4 * 8;  // magic, key hash, second key hash, size, checksum

std::string library_cache_dir() {
  if (env_or_empty("BHCL_PROGRAM_CACHE") == "0") return "";
  if (std::string d = env_or_empty("BHCL_CACHE_DIR"); !d.empty()) return d;
  if (std::string x = env_or_empty("XDG_CACHE_HOME"); !x.empty()) return x + "/blockhash_cl";
  if (std::string h = env_or_empty("HOME"); !h.empty()) return h + "/.cache/blockhash_cl";
  return "";
}
}  // namespace

ProgramBinaryCache::ProgramBinaryCache(const std::string& file, const std::string& key) {
  const std::string dir = library_cache_dir();
  if (dir.empty()) return;
  key_hash_ = fnv1a64(key.data(), key.size());
  key_hash2_ = fnv1a64(key.data(), key.size(), 0x84222325cbf29ce4ull);  // a second, independent basis
  char hex[17];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(key_hash_));
  path_ = dir + "/" + file.substr(0, file.rfind('.')) + "." + hex + ".bin";
}

std::optional<std::vector<unsigned char>> ProgramBinaryCache::load() const {
  if (!enabled()) return std::nullopt;
  std::ifstream in(path_, std::ios::binary);
  if (!in) return std::nullopt;  // not cached yet
  std::vector<unsigned char> all((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  std::string why;
  if (in.bad()) why = "cannot be read";
  else if (all.size() < kHeader) why = all.empty() ? "empty" : "cut short inside its header";
  else if (std::memcmp(all.data(), kMagic, 8) != 0) why = "not a blockhash_cl program file";
  else if (load_le<std::uint64_t>(&all[8]) != key_hash_ || load_le<std::uint64_t>(&all[16]) != key_hash2_)
    why = "it holds another program";
  else if (load_le<std::uint64_t>(&all[24]) != all.size() - kHeader) why = "cut short or extended";
  else if (load_le<std::uint64_t>(&all[32]) != fnv1a64(all.data() + kHeader, all.size() - kHeader))
    why = "its checksum does not match";
  if (why.empty()) return std::vector<unsigned char>(all.begin() + kHeader, all.end());
  std::error_code ec;
  fs::remove(path_, ec);
  note_once("program-cache-damaged", "the compiled program '" + path_ + "' is damaged (" + why +
                                         "); it was removed and the program is compiled again from source");
  return std::nullopt;
}

void ProgramBinaryCache::store(const std::vector<unsigned char>& binary) const {
  if (!enabled() || binary.empty()) return;
  const std::string dir = fs::path(path_).parent_path().string();
  try {
    std::error_code ec;
    fs::create_directories(dir, ec);
    if (ec) throw Error(dir + ": " + ec.message());
    unsigned char h[kHeader];
    std::memcpy(h, kMagic, 8);
    const std::uint64_t fields[4] = {key_hash_, key_hash2_, binary.size(), fnv1a64(binary.data(), binary.size())};
    std::memcpy(h + 8, fields, sizeof fields);
    AtomicFile f(path_, "a compiled program");
    f.write(h, sizeof h);
    f.write(binary.data(), binary.size());
    f.commit();
  } catch (const std::exception& e) {
    // A cache that cannot be written costs speed, not answers: said once, not thrown.
    note_once("program-cache-unwritable", "the program cache folder '" + dir + "' cannot be written (" +
                                              e.what() + "); programs are compiled from source in every process "
                                              "(set BHCL_CACHE_DIR to a writable folder, or BHCL_PROGRAM_CACHE=0)");
  }
}

}  // namespace bhcl::detail
