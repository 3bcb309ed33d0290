// libFuzzer target: the point-file parsers (raw, text, PLY, NPY, and the sniffing that picks one)
// must accept or reject any bytes with bhcl::Error, never crash, and whatever they accept must be
// finite and a whole number of points.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  for (bhcl::PointFormat f : {bhcl::PointFormat::Auto, bhcl::PointFormat::Raw, bhcl::PointFormat::Text,
                              bhcl::PointFormat::Ply, bhcl::PointFormat::Npy}) {
    try {
      std::vector<float> xyz = bhcl::parse_points(data, size, "fuzz input", f, true);
      if (xyz.size() % 3 != 0) std::abort();
      for (float v : xyz)
        if (!std::isfinite(v)) std::abort();
    } catch (const bhcl::Error&) {
    }
  }
  return 0;
}
