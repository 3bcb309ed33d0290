// Bounds-checked reads of a saved file's bytes held in memory, for the indexes' loaders (the grid's
// and the block layout's): each read says which file, which field and at which byte the data ran
// out, and an array of no entries copies nothing (memcpy's pointers must not be null even for no
// bytes; the grid's copy of this reader lacked that, found by fuzz_grid_load under UBSan).
#pragma once

#include <cstdint>
#include <cstring>
#include <string>

#include "blockhash_cl/error.hpp"

namespace bhcl::detail {

struct ByteReader {
  const std::string& data;  // the file's bytes
  const std::string& what;  // the file, for the messages
  const char* kind;         // what the file holds ("grid index"), for the messages
  std::size_t pos = 0;      // the next byte

  template <typename T>
  T get(const char* field) {
    if (data.size() - pos < sizeof(T))
      throw Error(what + ": truncated " + kind + " (field '" + field + "' at byte " + std::to_string(pos) + ")");
    T v;
    std::memcpy(&v, data.data() + pos, sizeof(T));
    pos += sizeof(T);
    return v;
  }
  // n elements into v (any vector of trivially copyable elements), resized to n.
  template <typename V>
  void get_n(V& v, std::uint64_t n, const char* field) {
    using T = typename V::value_type;
    if (n > (data.size() - pos) / sizeof(T))
      throw Error(what + ": truncated " + kind + " (array '" + field + "' of " + std::to_string(n) +
                  " elements at byte " + std::to_string(pos) + ")");
    v.resize(static_cast<std::size_t>(n));
    if (n) std::memcpy(v.data(), data.data() + pos, static_cast<std::size_t>(n) * sizeof(T));
    pos += static_cast<std::size_t>(n) * sizeof(T);
  }
};

}  // namespace bhcl::detail
