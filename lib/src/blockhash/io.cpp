// Save and load of a built block-hash index, and the structure's invariant check.
//
// File format (little-endian), version 5:
//   "BHCLIDX\0" magic, u32 version, u32 0x01020304 (byte-order check), u32 header bytes,
//   u32 preset (0 auto, 1 paper, 2 paper-cells), L, P, B, X, flags (guard, top count, direct, box skip, probes, box order; bit 64, new in 3, marked
//   the retired layout of blocks aligned to cells: refused on load),
//   u64 n_points, n_blocks, n_thresholds, n_table_starts, n_keys, n_buckets, n_refs,
//   f64 median cell points, median cell blocks, p90 cell blocks,
//   u64 id bound (one past the largest id issued; new in 5: after Index::remove the ids in order
//   and the blocks are the live ones, sparse in [0, id bound); version 4 held ids 0 .. N - 1),
//   u64 FNV-1a 64 checksum of every other byte of the file (the header before it, then the
//   payload; new in 4: version 3 covered the payload only, so a corrupt header passed),
//   payload: order (i32 x N), blocks (256 B each), boxes (32 B each), thresholds (f32),
//            table_starts (u32), keys (u32), buckets (16 B each), refs (i32), block keys (u64).
//   (the header also holds the query quantiser: f32 origin xyz, f32 scale, u32 bits, u32 seed,
//   and i32 the coordinate scale exponent of extreme-scale data, see knn.hpp; new in version 2.)
// A load refuses anything but a regular file, reads the header first and the payload only when
// the file's size is the one the header declares, then checks the checksum, every header field's
// range (no bits masked away) and every structural invariant (Structure::validate) before
// anything is used.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"
#include "core/byte_reader.hpp"

namespace bhcl::blockhash {
namespace {

constexpr char kMagic[8] = {'B', 'H', 'C', 'L', 'I', 'D', 'X', '\0'};
constexpr std::uint32_t kVersion = 5;
constexpr std::uint32_t kHeaderBytesV4 = 8 + 4 * 3 + 4 * 6 + 4 * 7 + 8 * 7 + 8 * 3 + 8;
constexpr std::uint32_t kHeaderBytes = kHeaderBytesV4 + 8;
std::uint32_t preset_code(BlockHashBuildParams::Preset p) {
  return p == BlockHashBuildParams::Preset::PaperCells ? 2u : (p == BlockHashBuildParams::Preset::Paper ? 1u : 0u);
}

std::uint32_t header_bytes(std::uint32_t version) { return version == 4 ? kHeaderBytesV4 : kHeaderBytes; }

std::uint64_t fnv1a(const unsigned char* p, std::size_t n, std::uint64_t h = 0xcbf29ce484222325ull) {
  for (std::size_t i = 0; i < n; ++i) {
    h ^= p[i];
    h *= 0x100000001b3ull;
  }
  return h;
}

struct Writer {
  std::string buf;
  template <typename T>
  void put(const T& v) { buf.append(reinterpret_cast<const char*>(&v), sizeof(T)); }
  template <typename T>
  void put_vec(const std::vector<T>& v) {
    buf.append(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T));
  }
};

// The payload's size from the header's array counts, overflow-safe.
std::uint64_t payload_bytes(const std::uint64_t n[7], const std::string& path) {
  static const char* names[7] = {"n_points", "n_blocks", "n_thresholds", "n_table_starts", "n_keys", "n_buckets", "n_refs"};
  const std::uint64_t elem[7] = {4, sizeof(bhcl_bh_block) + sizeof(bhcl_bh_box) + 8, 4, 4, 4, sizeof(bhcl_bh_bucket), 4};
  std::uint64_t need = 0;
  for (int i = 0; i < 7; ++i) {
    if (i == 0 && n[0] > 0x7ffffffeull) throw Error(path + ": block-hash index field 'n_points' = " + std::to_string(n[0]) + " is out of range");
    if (n[i] > (std::uint64_t(1) << 40)) throw Error(path + ": block-hash index field '" + names[i] + "' = " + std::to_string(n[i]) + " is out of range");
    need += n[i] * elem[i];
  }
  return need;
}

// The payload size a complete header declares (magic and version checked first, so that a foreign
// or old file gets the same message as from parse_structure).
std::uint64_t header_payload_bytes(const std::string& header, const std::string& path) {
  if (std::memcmp(header.data(), kMagic, 8) != 0) throw Error(path + ": not a block-hash index (bad magic)");
  std::uint32_t version = 0;
  std::memcpy(&version, header.data() + 8, 4);
  if (version != 4 && version != kVersion)
    throw Error(path + ": block-hash index version " + std::to_string(version) + ", this library reads versions 4 and " +
                std::to_string(kVersion) + " (rebuild the index)");
  std::uint64_t n[7];
  std::memcpy(n, header.data() + 72, sizeof n);  // after the 72 bytes of identity, parameters and quantiser
  return payload_bytes(n, path);
}

}  // namespace

std::size_t Structure::device_bytes() const {
  return blocks.size() * sizeof(bhcl_bh_block) + boxes.size() * sizeof(bhcl_bh_box) +
         block_keys.size() * 8 +
         thresholds.size() * sizeof(float) + table_starts.size() * 4 + keys.size() * 4 +
         buckets.size() * sizeof(bhcl_bh_bucket) + refs.size() * 4;
}

void Structure::validate(const std::string& what) const {
  auto fail = [&](const std::string& why) { throw Error(what + ": invalid block-hash index: " + why); };
  const BlockHashBuildInfo& in = info;
  if (in.L < 1 || in.L > 64) fail("L = " + std::to_string(in.L) + " out of [1, 64]");
  if (in.P < 1 || in.P > BHCL_BH_MAX_P) fail("P = " + std::to_string(in.P) + " out of range");
  if (in.B < 1 || in.B > 65535) fail("B = " + std::to_string(in.B) + " out of range");
  if (in.X < 1 || in.X > BHCL_BH_BLOCK_SLOTS) fail("X = " + std::to_string(in.X) + " out of range");
  if (n_points < 1 || n_points > 0x7ffffffeu) fail("N = " + std::to_string(n_points) + " out of range");
  const std::size_t nb = (n_points + in.X - 1) / in.X;
  if (order.size() != n_points) fail("order has " + std::to_string(order.size()) + " entries");
  if (blocks.size() != nb || boxes.size() != nb) fail("block count differs from ceil(N / X)");
  std::vector<bool> seen(n_points, false);
  for (std::size_t i = 0; i < n_points; ++i) {
    std::int32_t o = order[i];
    if (o < 0 || std::size_t(o) >= n_points || seen[o]) fail("order is not a permutation (entry " + std::to_string(i) + ")");
    seen[o] = true;
  }
  for (std::size_t b = 0; b < nb; ++b) {
    const bhcl_bh_box& box = boxes[b];
    const std::size_t first = b * in.X;
    const std::size_t cnt = std::min<std::size_t>(in.X, n_points - first);
    if (box.count != std::int32_t(cnt) || box.first != std::int32_t(first))
      fail("box " + std::to_string(b) + " has count/first " + std::to_string(box.count) + "/" + std::to_string(box.first));
    for (std::size_t j = 0; j < cnt; ++j) {
      const bhcl_bh_block& blk = blocks[b];
      if (blk.id[j] != order[first + j]) fail("block " + std::to_string(b) + " slot " + std::to_string(j) + " id differs from order");
      float p[3] = {blk.x[j], blk.y[j], blk.z[j]};
      if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2]))
        fail("block " + std::to_string(b) + " slot " + std::to_string(j) + " is not finite");
      if (p[0] < box.lo_x || p[0] > box.hi_x || p[1] < box.lo_y || p[1] > box.hi_y || p[2] < box.lo_z || p[2] > box.hi_z)
        fail("block " + std::to_string(b) + " has a point outside its box");
    }
  }
  if (block_keys.size() != nb) fail("block key count differs from the block count");
  for (std::size_t b = 1; b < nb; ++b)
    if (block_keys[b - 1] > block_keys[b]) fail("block keys are not ascending");
  if (q_bits < 1 || q_bits > 21) fail("hilbert bits = " + std::to_string(q_bits) + " out of [1, 21]");
  if (!std::isfinite(q_scale) || q_scale < 0 || !std::isfinite(q_origin[0]) || !std::isfinite(q_origin[1]) || !std::isfinite(q_origin[2]))
    fail("the quantiser is not finite");
  if (in.hilbert_seed > 64) fail("hilbert seed " + std::to_string(in.hilbert_seed) + " out of [0, 64]");
  if (thresholds.size() != std::size_t(in.L) * 3 * in.P) fail("threshold count differs from L * 3 * P");
  for (int t = 0; t < in.L; ++t)
    for (int d = 0; d < 3; ++d) {
      const float* th = thr(t, d);
      for (int i = 0; i < in.P; ++i)
        if (std::isnan(th[i]) || (i && !(th[i - 1] <= th[i])))
          fail("thresholds of table " + std::to_string(t) + " dimension " + std::to_string(d) + " are not ascending");
    }
  const std::uint64_t side = std::uint64_t(in.P) + 1, cells = side * side * side;
  if (table_starts.size() != std::size_t(in.L) + 1) fail("table_starts has the wrong length");
  if (in.direct_addressing) {
    if (!keys.empty()) fail("a directly addressed index has directory keys");
    if (buckets.size() != in.L * cells) fail("bucket count differs from L (P+1)^3");
    if (refs.size() != buckets.size() * std::size_t(in.B)) fail("ref count differs from buckets * B");
  } else {
    if (buckets.size() != keys.size()) fail("bucket and key counts differ");
    if (table_starts[0] != 0 || table_starts[in.L] != keys.size()) fail("table_starts do not span the keys");
    for (int t = 0; t < in.L; ++t) {
      if (table_starts[t] > table_starts[t + 1]) fail("table_starts are not ascending");
      for (std::uint32_t i = table_starts[t]; i < table_starts[t + 1]; ++i)
        if (keys[i] >= cells || (i > table_starts[t] && keys[i - 1] >= keys[i]))
          fail("directory keys of table " + std::to_string(t) + " are not ascending cell keys");
    }
  }
  for (std::size_t i = 0; i < buckets.size(); ++i) {
    const bhcl_bh_bucket& bk = buckets[i];
    if (bk.n_refs > std::uint32_t(in.B) || std::uint64_t(bk.first_ref) + bk.n_refs > refs.size())
      fail("bucket " + std::to_string(i) + " refers outside the reference array");
    if (in.direct_addressing && bk.first_ref != i * std::size_t(in.B)) fail("bucket " + std::to_string(i) + " is not at its slot");
    for (std::uint32_t r = 0; r < bk.n_refs; ++r) {
      std::int32_t b = refs[bk.first_ref + r];
      if (b < 0 || std::size_t(b) >= nb) fail("bucket " + std::to_string(i) + " holds block " + std::to_string(b));
    }
  }
}

void save_structure(const Structure& s, const std::string& path) { save_structure(s, path, -1); }

void save_structure(const Structure& s, const std::string& path, std::int64_t id_bound) {
  const BlockHashBuildInfo& in = s.info;
  Writer payload;
  payload.put_vec(s.order);
  payload.put_vec(s.blocks);
  payload.put_vec(s.boxes);
  payload.put_vec(s.thresholds);
  payload.put_vec(s.table_starts);
  payload.put_vec(s.keys);
  payload.put_vec(s.buckets);
  payload.put_vec(s.refs);
  payload.put_vec(s.block_keys);
  Writer h;
  h.buf.append(kMagic, 8);
  h.put(kVersion);
  h.put(std::uint32_t(0x01020304));
  h.put(kHeaderBytes);
  std::uint32_t flags = (in.guard_thresholds ? 1u : 0u) | (in.keep_top_count ? 2u : 0u) |
                        (in.direct_addressing ? 4u : 0u) | (in.box_skip ? 8u : 0u) |
                        (in.neighbour_probes ? 16u : 0u) | (in.box_order ? 32u : 0u);
  for (std::uint32_t v : {preset_code(in.preset),
                          std::uint32_t(in.L), std::uint32_t(in.P), std::uint32_t(in.B),
                          std::uint32_t(in.X), flags})
    h.put(v);
  for (float v : {s.q_origin[0], s.q_origin[1], s.q_origin[2], s.q_scale}) h.put(v);
  h.put(std::uint32_t(s.q_bits));
  h.put(std::uint32_t(in.hilbert_seed));
  h.put(std::int32_t(s.scale_exp));
  for (std::uint64_t v : {std::uint64_t(s.n_points), std::uint64_t(s.blocks.size()),
                          std::uint64_t(s.thresholds.size()), std::uint64_t(s.table_starts.size()),
                          std::uint64_t(s.keys.size()), std::uint64_t(s.buckets.size()),
                          std::uint64_t(s.refs.size())})
    h.put(v);
  for (double v : {in.median_cell_points, in.median_cell_blocks, in.p90_cell_blocks}) h.put(v);
  h.put(std::uint64_t(id_bound < 0 ? std::int64_t(s.n_points) : id_bound));
  const std::uint64_t head = fnv1a(reinterpret_cast<const unsigned char*>(h.buf.data()), h.buf.size());
  h.put(fnv1a(reinterpret_cast<const unsigned char*>(payload.buf.data()), payload.buf.size(), head));
  write_file(path, {h.buf, payload.buf}, "the block-hash index");
}

std::unique_ptr<Structure> load_structure(const std::string& path) { return load_structure(path, nullptr); }

std::unique_ptr<Structure> load_structure(const std::string& path, std::int64_t* id_bound) {
  const std::uint64_t size = regular_file_size(path, "a block-hash index");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path + ": cannot open the block-hash index");
  // The header first; the payload only when the file is as long as the header says (a large
  // foreign file is never read whole).
  // The header's length depends on the version (at byte 8): read as much as the longest.
  std::string data(static_cast<std::size_t>(std::min<std::uint64_t>(size, kHeaderBytes)), '\0');
  in.read(data.data(), static_cast<std::streamsize>(data.size()));
  std::uint32_t version = kVersion;
  if (data.size() >= 12) std::memcpy(&version, data.data() + 8, 4);
  const std::uint32_t hb = header_bytes(version);
  if (data.size() >= hb) {
    const std::uint64_t need = hb + header_payload_bytes(data, path);
    if (size != need)
      throw Error(path + ": block-hash index is " + std::to_string(size) + " bytes, its header says " +
                  std::to_string(need) + (size < need ? " (truncated)" : " (trailing bytes)"));
    const std::size_t had = data.size();
    data.resize(static_cast<std::size_t>(size));
    in.read(data.data() + had, static_cast<std::streamsize>(size - had));
  }
  if (!in) throw Error(path + ": reading the block-hash index failed");
  return parse_structure(data, path, true, id_bound);
}

std::unique_ptr<Structure> parse_structure(const std::string& data, const std::string& path,
                                           bool verify_checksum, std::int64_t* id_bound) {
  detail::ByteReader r{data, path, "block-hash index"};
  char magic[8];
  for (char& c : magic) c = r.get<char>("magic");
  if (std::memcmp(magic, kMagic, 8) != 0) throw Error(path + ": not a block-hash index (bad magic)");
  std::uint32_t version = r.get<std::uint32_t>("version");
  if (version != 4 && version != kVersion)
    throw Error(path + ": block-hash index version " + std::to_string(version) + ", this library reads versions 4 and " + std::to_string(kVersion));
  if (r.get<std::uint32_t>("byte order") != 0x01020304u) throw Error(path + ": block-hash index of another byte order");
  if (r.get<std::uint32_t>("header bytes") != header_bytes(version)) throw Error(path + ": block-hash index header size differs");
  auto s = std::make_unique<Structure>();
  BlockHashBuildInfo& info = s->info;
  std::uint32_t preset = r.get<std::uint32_t>("preset");
  if (preset > 2) throw Error(path + ": block-hash index has an unknown preset " + std::to_string(preset));
  info.preset = preset == 2 ? BlockHashBuildParams::Preset::PaperCells
                            : (preset ? BlockHashBuildParams::Preset::Paper : BlockHashBuildParams::Preset::Auto);
  // Every field in its range, nothing masked away: a corrupt header is refused, never read as
  // other parameters.
  auto field = [&](const char* name, std::uint32_t lo, std::uint32_t hi) {
    std::uint32_t v = r.get<std::uint32_t>(name);
    if (v < lo || v > hi)
      throw Error(path + ": block-hash index field '" + name + "' = " + std::to_string(v) + " is out of range [" +
                  std::to_string(lo) + ", " + std::to_string(hi) + "]");
    return static_cast<int>(v);
  };
  info.L = field("L", 1, 1u << 16);
  info.P = field("P", 1, BHCL_BH_MAX_P);
  info.B = field("B", 1, 1u << 24);
  info.X = field("X", 1, BHCL_BH_BLOCK_SLOTS);
  std::uint32_t flags = r.get<std::uint32_t>("flags");
  info.guard_thresholds = flags & 1;
  info.keep_top_count = flags & 2;
  info.direct_addressing = flags & 4;
  info.box_skip = flags & 8;
  info.neighbour_probes = flags & 16;
  info.box_order = flags & 32;
  if (flags & 64)
    throw Error(path + ": a block-hash index of the retired layout of blocks aligned to cells (the grid, auto's "
                "default, replaced it): build the index again and save it");
  if (flags > 127) throw Error(path + ": block-hash index has unknown flags " + std::to_string(flags));
  for (int d = 0; d < 3; ++d) s->q_origin[d] = r.get<float>("quantiser origin");
  s->q_scale = r.get<float>("quantiser scale");
  if (!std::isfinite(s->q_origin[0]) || !std::isfinite(s->q_origin[1]) || !std::isfinite(s->q_origin[2]) ||
      !std::isfinite(s->q_scale) || s->q_scale < 0)
    throw Error(path + ": block-hash index has a non-finite quantiser");
  s->q_bits = field("hilbert bits", 1, 21);
  info.hilbert_seed = field("hilbert seed", 0, 1u << 24);
  s->scale_exp = r.get<std::int32_t>("scale exponent");
  if (s->scale_exp < -300 || s->scale_exp > 300)
    throw Error(path + ": block-hash index has an impossible scale exponent " + std::to_string(s->scale_exp));
  std::uint64_t n[7];
  const char* names[7] = {"n_points", "n_blocks", "n_thresholds", "n_table_starts", "n_keys", "n_buckets", "n_refs"};
  for (int i = 0; i < 7; ++i) n[i] = r.get<std::uint64_t>(names[i]);
  info.median_cell_points = r.get<double>("median_cell_points");
  info.median_cell_blocks = r.get<double>("median_cell_blocks");
  info.p90_cell_blocks = r.get<double>("p90_cell_blocks");
  std::uint64_t bound = n[0];
  if (version >= 5) {
    bound = r.get<std::uint64_t>("id bound");
    if (bound < n[0] || bound > 0x7ffffffeull)
      throw Error(path + ": block-hash index field 'id bound' = " + std::to_string(bound) + " is out of range [" +
                  std::to_string(n[0]) + ", 2^31 - 2]");
  }
  std::uint64_t checksum = r.get<std::uint64_t>("checksum");
  const std::uint64_t need = payload_bytes(n, path);
  const std::uint64_t have = data.size() - r.pos;
  if (have != need)
    throw Error(path + ": block-hash index payload is " + std::to_string(have) + " bytes, the header says " +
                std::to_string(need) + (have < need ? " (truncated)" : " (trailing bytes)"));
  const std::uint64_t head = fnv1a(reinterpret_cast<const unsigned char*>(data.data()), r.pos - 8);
  if (verify_checksum &&
      fnv1a(reinterpret_cast<const unsigned char*>(data.data() + r.pos), have, head) != checksum)
    throw Error(path + ": block-hash index checksum mismatch (corrupt file)");
  s->n_points = static_cast<std::size_t>(n[0]);
  r.get_n(s->order, n[0], "order");
  r.get_n(s->blocks, n[1], "blocks");
  r.get_n(s->boxes, n[1], "boxes");
  r.get_n(s->thresholds, n[2], "thresholds");
  r.get_n(s->table_starts, n[3], "table_starts");
  r.get_n(s->keys, n[4], "keys");
  r.get_n(s->buckets, n[5], "buckets");
  r.get_n(s->refs, n[6], "refs");
  r.get_n(s->block_keys, n[1], "block_keys");
  info.n_points = s->n_points;
  info.n_blocks = s->blocks.size();
  if (bound == n[0]) {
    s->validate(path);
  } else {
    // Sparse ids (an index saved after removals): each id in [0, bound) at most once; validate
    // sees them replaced by their ranks (0 .. N - 1, the invariants it checks), then they return.
    auto fail = [&](const std::string& why) { throw Error(path + ": invalid block-hash index: " + why); };
    // The ranks come from the sorted ids, not a table over [0, bound): a crafted bound of 2^31 - 2
    // in a file of a few KB then allocates nothing past the file's own arrays (issue 38: 8 GiB).
    for (std::size_t i = 0; i < s->order.size(); ++i) {
      const std::int32_t o = s->order[i];
      if (o < 0 || std::uint64_t(o) >= bound) fail("order entry " + std::to_string(i) + " = " + std::to_string(o) + " is outside [0, id bound)");
    }
    std::vector<std::int32_t> live(s->order.begin(), s->order.end());
    std::sort(live.begin(), live.end());
    for (std::size_t i = 1; i < live.size(); ++i)
      if (live[i] == live[i - 1]) fail("order is not a set of distinct ids (id " + std::to_string(live[i]) + " twice)");
    auto to_rank = [&](std::int32_t id) {
      const auto it = std::lower_bound(live.begin(), live.end(), id);
      return it != live.end() && *it == id ? static_cast<std::int32_t>(it - live.begin()) : -1;
    };
    for (auto& o : s->order) o = to_rank(o);
    for (std::size_t b = 0; b < s->blocks.size(); ++b)
      for (std::int32_t j = 0; j < std::min<std::int32_t>(s->boxes[b].count, BHCL_BH_BLOCK_SLOTS); ++j)
        s->blocks[b].id[j] = to_rank(s->blocks[b].id[j]);
    s->validate(path);
    for (auto& o : s->order) o = live[std::size_t(o)];
    for (std::size_t b = 0; b < s->blocks.size(); ++b)
      for (std::int32_t j = 0; j < s->boxes[b].count; ++j) s->blocks[b].id[j] = live[std::size_t(s->blocks[b].id[j])];
  }
  if (id_bound) *id_bound = static_cast<std::int64_t>(bound);
  return s;
}

}  // namespace bhcl::blockhash
