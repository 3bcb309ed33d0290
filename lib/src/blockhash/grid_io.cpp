// Save and load of a grid-layout block-hash index.
//
// File format (little-endian), version 3:
//   "BHCLGRID" magic, u32 version, u32 0x01020304 (byte-order check),
//   u64 n_points, i32 coordinate scale exponent (knn.hpp), f64 target cell points,
//   f32 ox, oy, oz, h, inv_h, margin, u32 nx, ny, nz,
//   u32 directory kind (0 direct, 4 two-level: grid_search.h), u64 directory entries,
//   u64 id bound (one past the largest id issued), f64 the mean cell population of the last
//   tuned build (0: none), u64 merges, compactions, update rebuilds, retunes (the update counters),
//   u64 FNV-1a 64 checksum of every other byte of the file (header before it, then payload),
//   payload: the directory (u32 x entries), x, y, z (f32 x N each), ids (i32 x N).
// Version 3 holds an index after updates (Index::insert/remove): the ids are the live ids, sparse in
// [0, id bound), and the holes of removed points not yet compacted (x = y = z = +inf, id
// BHCL_EMPTY_SLOT_ID) stay where they are, so that a loaded index examines the same slots and
// answers as the saved one. n_points counts the slots, holes included.
// Version 2 (read, not written) had no id bound nor counters: ids 0 .. N - 1, no holes.
// Version 1 (read, not written) had no directory fields either: a direct table of cells + 1 entries.
// A load reads the header, checks the file's size against it before reading the payload, then the
// checksum and every invariant the kernel relies on (Grid::validate) before anything is used.
#include <sys/stat.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <vector>

#include "bhcl_shared.h"
#include "blockhash/grid.hpp"
#include "blockhash/grid_io.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"
#include "core/byte_reader.hpp"

namespace bhcl::blockhash {
namespace {

constexpr std::uint32_t kVersion = 3;
constexpr std::size_t kHeaderV1 = 8 + 4 + 4 + 8 + 4 + 8 + 6 * 4 + 3 * 4;
constexpr std::size_t kHeaderV2 = kHeaderV1 + 4 + 8;
constexpr std::size_t kHeader = kHeaderV2 + 8 + 8 + 4 * 8;
constexpr std::int32_t kHoleId = BHCL_EMPTY_SLOT_ID;

std::uint64_t fnv1a(const char* p, std::size_t n, std::uint64_t h = 0xcbf29ce484222325ull) {
  for (std::size_t i = 0; i < n; ++i) {
    h ^= static_cast<unsigned char>(p[i]);
    h *= 0x100000001b3ull;
  }
  return h;
}

template <typename T>
void put(std::string& b, const T& v) { b.append(reinterpret_cast<const char*>(&v), sizeof(T)); }
template <typename T>
void put_n(std::string& b, const T* v, std::size_t n) { b.append(reinterpret_cast<const char*>(v), n * sizeof(T)); }

// Every invariant of the kernel (Grid::validate) and those of the ids after updates: each slot a
// live id in [0, id_bound), no id twice, or a hole (BHCL_EMPTY_SLOT_ID with x = y = z = +inf, which
// no search returns). Grid::validate takes ids 0 .. n - 1 and finite points, so it checks a copy
// without the holes and with each id replaced by its rank (the directory's starts moved down by the
// holes before them); the saved directory itself must then also start at 0, span the slots and
// not decrease.
void validate_ids(const Grid& g, GridIdState& st, const std::string& what) {
  auto bad = [&](const std::string& m) { throw Error(what + ": corrupt grid index: " + m); };
  const std::size_t n = g.n_points, bound = std::size_t(st.id_bound);
  std::size_t holes = 0;
  for (std::size_t i = 0; i < n; ++i) holes += g.ids[i] == kHoleId ? 1 : 0;
  if (holes == 0 && bound == n) {  // no update left a trace: ids 0 .. n - 1 (checked there)
    g.validate(what);
    st.live = n;
    st.holes = 0;
    return;
  }
  if (bound < n - holes) bad("the id bound " + std::to_string(bound) + " is below the " + std::to_string(n - holes) + " live points");
  if (holes == n) bad("every slot is a hole");
  // The live ids sorted (their ranks by binary search), never a table over [0, id bound): a
  // crafted bound of 2^31 - 2 in a 79 KB file then allocates nothing past the file's own arrays
  // (issue 38: 8 GiB, std::bad_alloc).
  std::vector<std::int32_t> live;
  live.reserve(n - holes);
  for (std::size_t i = 0; i < n; ++i) {
    const std::int32_t id = g.ids[i];
    if (id == kHoleId) {
      if (!(std::isinf(g.x[i]) && g.x[i] > 0 && std::isinf(g.y[i]) && g.y[i] > 0 && std::isinf(g.z[i]) && g.z[i] > 0))
        bad("the hole at position " + std::to_string(i) + " is not at +inf");
      continue;
    }
    if (id < 0 || std::size_t(id) >= bound) bad("id " + std::to_string(id) + " at position " + std::to_string(i) + " is outside [0, id bound " + std::to_string(bound) + ")");
    live.push_back(id);
  }
  std::sort(live.begin(), live.end());
  for (std::size_t i = 1; i < live.size(); ++i)
    if (live[i] == live[i - 1]) bad("id " + std::to_string(live[i]) + " appears twice");
  auto rank = [&](std::int32_t id) {
    return static_cast<std::int32_t>(std::lower_bound(live.begin(), live.end(), id) - live.begin());
  };
  // hb[i]: holes among slots [0, i).
  std::vector<std::uint32_t> hb(n + 1, 0);
  for (std::size_t i = 0; i < n; ++i) hb[i + 1] = hb[i] + (g.ids[i] == kHoleId ? 1u : 0u);
  auto moved = [&](std::uint32_t v) { return v - hb[std::min<std::size_t>(v, n)]; };  // v > n stays > n - holes
  Grid t;
  t.geom = g.geom;
  const std::size_t m = n - holes;
  t.n_points = m;
  t.starts.resize(g.starts.size());
  const std::size_t top = g.geom.sparse ? Grid::top_entries(g.ncells()) : 0;
  for (std::size_t e = 0; e < g.starts.size(); ++e) {
    const std::uint32_t v = g.starts[e];
    if (e < top)  // a segment: its index into the directory, or EMPTY | the start of its cells
      t.starts[e] = (v & BHCL_GRID_EMPTY_SEG) ? (BHCL_GRID_EMPTY_SEG | moved(v & ~BHCL_GRID_EMPTY_SEG)) : v;
    else
      t.starts[e] = moved(v);
  }
  t.x.resize(m + kGridPad, INFINITY);
  t.y.resize(m + kGridPad, INFINITY);
  t.z.resize(m + kGridPad, INFINITY);
  t.ids.resize(m + kGridPad, -1);
  for (std::size_t i = 0, w = 0; i < n; ++i) {
    if (g.ids[i] == kHoleId) continue;
    t.x[w] = g.x[i];
    t.y[w] = g.y[i];
    t.z[w] = g.z[i];
    t.ids[w] = rank(g.ids[i]);
    ++w;
  }
  t.validate(what);
  // The copy's directory is sound, so the saved one's entries can be read: they must span the
  // slots themselves (a run of holes before the first cell or after the last would pass the copy).
  const std::size_t nc = g.ncells();
  if (g.start(0) != 0 || g.start(nc) != n) bad("the cell table does not span the points");
  for (std::size_t c = 0, prev = 0; c <= nc; ++c) {
    const std::size_t v = g.start(c);
    if (v < prev) bad("the cell table decreases at cell " + std::to_string(c));
    prev = v;
  }
  st.live = m;
  st.holes = holes;
}

// The geometry's fields against each other (issue 38: a file whose cell side was changed and its
// checksum recomputed loaded, and answered 90 % of the rows wrong on the exact default): the
// search assigns cells by inv_h and bounds them by h, so inv_h must be the build's 1 / h exactly;
// the margin must cover the rounding at the grid's magnitudes as the build's does (its lower part,
// from the origin, the far corner and h; the build adds the points' extent).
void check_geometry(const bhcl_grid_geom& g, const std::string& what) {
  auto bad = [&](const std::string& m) { throw Error(what + ": corrupt grid index: " + m); };
  if (!(g.h > 0) || !std::isfinite(g.h)) bad("field 'h' (the cell side) is not a positive finite number");
  if (g.inv_h != 1.0f / g.h) bad("field 'inv_h' is not 1 / h (the cell side's two fields disagree)");
  const float o[3] = {g.ox, g.oy, g.oz};
  const std::uint32_t dims[3] = {g.nx, g.ny, g.nz};
  double mag = 0;
  for (int d = 0; d < 3; ++d) {
    if (!std::isfinite(o[d])) bad("the origin is not finite");
    mag = std::max({mag, std::fabs(double(o[d])), std::fabs(double(o[d]) + double(dims[d]) * g.h)});
  }
  const double need = (mag + double(g.h)) * std::ldexp(1.0, -20);
  if (!(double(g.margin) >= need * (1 - 1e-6)) || !std::isfinite(g.margin))
    bad("field 'margin' " + std::to_string(g.margin) + " is below the rounding slack of the grid's magnitudes");
}

// Every stored point within its cell's slabs along each axis (lowered by the margin, as the search
// bounds a cell: bhcl_grid_slabs): Grid::validate checks the assignment by inv_h, this the bound
// by h, so a crafted geometry that moves the cells away from the points is refused rather than
// searched inexactly. Holes (+inf) are in no cell.
void check_points_in_cells(const Grid& g, const std::string& what) {
  const bhcl_grid_geom& q = g.geom;
  for (std::size_t i = 0; i < g.n_points; ++i) {
    if (g.ids[i] == kHoleId) continue;
    const float p[3] = {g.x[i], g.y[i], g.z[i]};
    const float o[3] = {q.ox, q.oy, q.oz};
    const std::uint32_t dims[3] = {q.nx, q.ny, q.nz};
    for (int d = 0; d < 3; ++d) {
      const std::uint32_t c = bhcl_grid_cell(p[d], o[d], q.inv_h, dims[d]);
      if (bhcl_grid_slabs(p[d], o[d], q.h, q.margin, c, c) > 0.0f)
        throw Error(what + ": corrupt grid index: point " + std::to_string(i) + " lies outside its cell by more than the margin (fields 'ox' .. 'margin' disagree with the points)");
    }
  }
}

}  // namespace

void save_grid(const GridFile& f, const std::string& path) { save_grid(f, GridIdState{}, path); }

void save_grid(const GridFile& f, const GridIdState& st, const std::string& path) {
  const Grid& g = f.grid;
  std::string h;
  h.append(kGridMagic, 8);
  put(h, kVersion);
  put(h, std::uint32_t(0x01020304));
  put(h, std::uint64_t(g.n_points));
  put(h, std::int32_t(f.scale_exp));
  put(h, f.target_cell_points);
  const float gf[6] = {g.geom.ox, g.geom.oy, g.geom.oz, g.geom.h, g.geom.inv_h, g.geom.margin};
  put_n(h, gf, 6);
  const std::uint32_t dims[3] = {g.geom.nx, g.geom.ny, g.geom.nz};
  put_n(h, dims, 3);
  put(h, std::uint32_t(g.geom.sparse));
  put(h, std::uint64_t(g.starts.size()));
  put(h, std::uint64_t(st.id_bound < 0 ? std::int64_t(g.n_points) : st.id_bound));
  put(h, st.tuned_mean);
  for (std::uint64_t c : {st.merges, st.compactions, st.update_rebuilds, st.retunes}) put(h, c);
  std::string p;
  p.reserve(g.starts.size() * 4 + g.n_points * 16);
  put_n(p, g.starts.data(), g.starts.size());
  put_n(p, g.x.data(), g.n_points);
  put_n(p, g.y.data(), g.n_points);
  put_n(p, g.z.data(), g.n_points);
  put_n(p, g.ids.data(), g.n_points);
  std::uint64_t sum = fnv1a(p.data(), p.size(), fnv1a(h.data(), h.size()));
  std::string tail;
  put(tail, sum);
  write_file(path, {h, tail, p}, "the block-hash index");
}

bool is_grid_file(const std::string& path) {
  // Only a regular file is opened (a FIFO would block); anything else is the block loader's to
  // refuse with its message.
  struct stat st;
  if (::stat(path.c_str(), &st) != 0 || !S_ISREG(st.st_mode)) return false;
  std::ifstream in(path, std::ios::binary);
  char m[8] = {};
  return in.read(m, 8) && std::memcmp(m, kGridMagic, 8) == 0;
}

GridFile parse_grid(const std::string& data, const std::string& what) {
  GridIdState st;
  return parse_grid(data, what, &st);
}

GridFile parse_grid(const std::string& data, const std::string& what, GridIdState* ids, bool verify_checksum) {
  GridIdState st;
  detail::ByteReader in{data, what, "grid index"};
  if (data.size() < 8 || std::memcmp(data.data(), kGridMagic, 8) != 0)
    throw Error(what + ": not a block-hash grid index (bad magic)");
  in.pos = 8;
  const auto version = in.get<std::uint32_t>("version");
  if (version < 1 || version > kVersion)
    throw Error(what + ": grid index version " + std::to_string(version) + ", this library reads versions 1 to " + std::to_string(kVersion));
  const std::size_t header = version == 1 ? kHeaderV1 : version == 2 ? kHeaderV2 : kHeader;
  if (data.size() < header + 8)
    throw Error(what + ": truncated grid index (" + std::to_string(data.size()) + " bytes, the header alone is " + std::to_string(header + 8) + ")");
  if (in.get<std::uint32_t>("byte order") != 0x01020304u) throw Error(what + ": grid index of another byte order");
  GridFile f;
  Grid& g = f.grid;
  const auto n = in.get<std::uint64_t>("n_points");
  if (n == 0 || n >= (std::uint64_t(1) << 31) - 1) throw Error(what + ": grid index point count " + std::to_string(n) + " out of range");
  g.n_points = static_cast<std::size_t>(n);
  f.scale_exp = in.get<std::int32_t>("scale exponent");
  if (f.scale_exp < -300 || f.scale_exp > 300) throw Error(what + ": grid index scale exponent out of range");
  f.target_cell_points = in.get<double>("target cell points");
  g.geom.ox = in.get<float>("ox");
  g.geom.oy = in.get<float>("oy");
  g.geom.oz = in.get<float>("oz");
  g.geom.h = in.get<float>("h");
  g.geom.inv_h = in.get<float>("inv_h");
  g.geom.margin = in.get<float>("margin");
  g.geom.nx = in.get<std::uint32_t>("nx");
  g.geom.ny = in.get<std::uint32_t>("ny");
  g.geom.nz = in.get<std::uint32_t>("nz");
  std::uint64_t entries = 0;
  const double cells = double(g.geom.nx) * g.geom.ny * g.geom.nz;
  if (g.geom.nx == 0 || g.geom.ny == 0 || g.geom.nz == 0 || cells > 2147483000.0)
    throw Error(what + ": grid index dimensions out of range");
  if (version == 1) {
    entries = std::uint64_t(cells) + 1;
  } else {
    g.geom.sparse = in.get<std::uint32_t>("directory kind");
    entries = in.get<std::uint64_t>("directory entries");
    if (g.geom.sparse != 0 && g.geom.sparse != BHCL_GRID_SEG_BITS)
      throw Error(what + ": grid index directory kind " + std::to_string(g.geom.sparse) + " unknown");
    if (entries >= BHCL_GRID_EMPTY_SEG) throw Error(what + ": grid index directory size out of range");
  }
  st.id_bound = std::int64_t(n);
  if (version >= 3) {
    const auto bound = in.get<std::uint64_t>("id bound");
    if (bound < 1 || bound > 0x7ffffffeull)
      throw Error(what + ": grid index id bound " + std::to_string(bound) + " out of range (1 .. 2^31 - 2)");
    st.id_bound = std::int64_t(bound);
    st.tuned_mean = in.get<double>("tuned mean cell population");
    if (!(st.tuned_mean >= 0) || !std::isfinite(st.tuned_mean))
      throw Error(what + ": grid index tuned mean cell population is not a finite number >= 0");
    st.merges = in.get<std::uint64_t>("merges");
    st.compactions = in.get<std::uint64_t>("compactions");
    st.update_rebuilds = in.get<std::uint64_t>("update rebuilds");
    st.retunes = in.get<std::uint64_t>("retunes");
  }
  const std::uint64_t want_sum = in.get<std::uint64_t>("checksum");
  const std::uint64_t expect = header + 8 + entries * 4 + n * 16;
  if (data.size() < expect)
    throw Error(what + ": truncated grid index (" + std::to_string(data.size()) + " bytes, its header declares " + std::to_string(expect) + ")");
  if (data.size() > expect)
    throw Error(what + ": grid index with trailing bytes (" + std::to_string(data.size()) + " bytes, its header declares " + std::to_string(expect) + ")");
  std::uint64_t sum = fnv1a(data.data() + header + 8, data.size() - header - 8, fnv1a(data.data(), header));
  if (verify_checksum && sum != want_sum) throw Error(what + ": grid index checksum mismatch (the file is corrupt)");
  in.get_n(g.starts, std::size_t(entries), "directory");
  in.get_n(g.x, g.n_points, "x");
  in.get_n(g.y, g.n_points, "y");
  in.get_n(g.z, g.n_points, "z");
  in.get_n(g.ids, g.n_points, "ids");
  g.x.resize(g.n_points + kGridPad, INFINITY);
  g.y.resize(g.n_points + kGridPad, INFINITY);
  g.z.resize(g.n_points + kGridPad, INFINITY);
  g.ids.resize(g.n_points + kGridPad, -1);
  check_geometry(g.geom, what);
  validate_ids(g, st, what);
  check_points_in_cells(g, what);
  g.dbox = grid_points_box(g, 0);
  build_grid_occupancy(g, 0);
  if (ids) *ids = st;
  return f;
}

GridFile load_grid(const std::string& path) {
  GridIdState st;
  return load_grid(path, &st);
}

GridFile load_grid(const std::string& path, GridIdState* ids) {
  const std::uint64_t size = regular_file_size(path, "a block-hash grid index");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path + ": cannot open the grid index (" + std::strerror(errno) + ")");
  std::string data(static_cast<std::size_t>(size), '\0');
  if (size && !in.read(&data[0], static_cast<std::streamsize>(size)))
    throw Error(path + ": read failed after " + std::to_string(in.gcount()) + " bytes");
  return parse_grid(data, path, ids);
}

}  // namespace bhcl::blockhash
