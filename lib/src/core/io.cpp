#include "blockhash_cl/io.hpp"

#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>

#include "blockhash_cl/error.hpp"

namespace bhcl {

std::vector<float> parse_points(const void* data, std::size_t size, const std::string& what,
                                bool require_finite) {
  if (size % 12 != 0) {
    std::ostringstream os;
    os << what << ": size " << size << " bytes is not a multiple of 12 (raw float32 x y z per point)";
    throw Error(os.str());
  }
  std::vector<float> xyz(size / 4);
  if (size) std::memcpy(xyz.data(), data, size);
  if (require_finite) {
    for (std::size_t i = 0; i < xyz.size(); ++i) {
      if (!std::isfinite(xyz[i])) {
        std::ostringstream os;
        os << what << ": point " << i / 3 << " has a non-finite coordinate " << "xyz"[i % 3]
           << " = " << xyz[i];
        throw Error(os.str());
      }
    }
  }
  return xyz;
}

std::vector<float> read_points_file(const std::string& path, bool require_finite) {
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  if (!in) throw Error(path + ": cannot open point file (" + std::strerror(errno) + ")");
  std::streamoff size = in.tellg();
  if (size < 0) throw Error(path + ": cannot read the file size");
  std::vector<char> bytes(static_cast<std::size_t>(size));
  in.seekg(0);
  if (size > 0 && !in.read(bytes.data(), size))
    throw Error(path + ": read failed after " + std::to_string(in.gcount()) + " bytes");
  return parse_points(bytes.data(), bytes.size(), path, require_finite);
}

void write_raw_file(const std::string& path, const void* data, std::size_t bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) throw Error(path + ": cannot open for writing (" + std::strerror(errno) + ")");
  out.write(static_cast<const char*>(data), static_cast<std::streamsize>(bytes));
  if (!out) throw Error(path + ": write failed");
}

void write_points_file(const std::string& path, const std::vector<float>& xyz) {
  write_raw_file(path, xyz.data(), xyz.size() * sizeof(float));
}

}  // namespace bhcl
