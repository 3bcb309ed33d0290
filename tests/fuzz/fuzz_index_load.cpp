// libFuzzer target: parsing a saved block-hash index must accept or reject any bytes with
// bhcl::Error, never crash or read out of bounds. The checksum test is off so that inputs reach
// the header, size and structural checks behind it; whatever is accepted must be a valid
// structure (Structure::validate ran) whose every block reference lies inside the block array.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "blockhash_build.hpp"
#include "blockhash_cl/error.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  try {
    auto s = bhcl::blockhash::parse_structure(std::string(reinterpret_cast<const char*>(data), size),
                                              "fuzz input", false);
    for (int ref : s->refs)
      if (ref >= static_cast<long>(s->blocks.size())) std::abort();
  } catch (const bhcl::Error&) {
  }
  return 0;
}
