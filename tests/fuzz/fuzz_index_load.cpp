// libFuzzer target: parsing a saved block-hash index must accept or reject any bytes with
// bhcl::Error, never crash or read out of bounds. The checksum test is off so that inputs reach
// the header, size and structural checks behind it; whatever is accepted must be a valid
// structure (Structure::validate ran): every block reference a bucket holds lies inside the
// block array (reference slots no bucket reaches, e.g. padding, are never read and may hold
// anything).
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  try {
    auto s = bhcl::blockhash::parse_structure(std::string(reinterpret_cast<const char*>(data), size),
                                              "fuzz input", false);
    for (const auto& bk : s->buckets) {
      for (std::uint32_t r = 0; r < bk.n_refs; ++r) {
        const std::int32_t b = s->refs.at(std::size_t(bk.first_ref) + r);
        if (b < 0 || static_cast<std::size_t>(b) >= s->blocks.size()) std::abort();
      }
    }
  } catch (const bhcl::Error&) {
  }
  return 0;
}
