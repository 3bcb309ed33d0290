// libFuzzer target: the point-file parser must accept or reject any bytes with bhcl::Error,
// never crash, and whatever it accepts must be finite and a whole number of points.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  try {
    std::vector<float> xyz = bhcl::parse_points(data, size, "fuzz input");
    if (xyz.size() % 3 != 0) std::abort();
    for (float v : xyz)
      if (!std::isfinite(v)) std::abort();
  } catch (const bhcl::Error&) {
  }
  return 0;
}
