// Block hashing: save / load round trip, and a damaged file is an error that names it, never a
// crash.
#include <cstring>
#include <fstream>
#include <random>

#include "blockhash/build.hpp"
#include "test_util.hpp"

#include <sys/stat.h>

using namespace bhcl;

namespace {

using bhcl::test::slurp;
using bhcl::test::spit;

// FNV-1a 64, the index file's checksum (lib/src/blockhash/io.cpp), so that a test can change a
// header field and still reach the check behind the checksum.
std::uint64_t fnv1a(const char* p, std::size_t n, std::uint64_t h = 0xcbf29ce484222325ull) {
  for (std::size_t i = 0; i < n; ++i) {
    h ^= static_cast<unsigned char>(p[i]);
    h *= 0x100000001b3ull;
  }
  return h;
}

// A version-5 block-hash file with header flags `set` or'ed in and its checksum made again.
std::string with_flags(std::string d, std::uint32_t set) {
  constexpr std::size_t kFlags = 8 + 4 * 3 + 4 * 5, kSum = 160, kHeader = 168;
  std::uint32_t flags = 0;
  std::memcpy(&flags, &d[kFlags], 4);
  flags |= set;
  std::memcpy(&d[kFlags], &flags, 4);
  const std::uint64_t sum = fnv1a(d.data() + kHeader, d.size() - kHeader, fnv1a(d.data(), kSum));
  std::memcpy(&d[kSum], &sum, 8);
  return d;
}

}  // namespace

TEST_CASE("blockhash io: save and load give the same index and the same answers") {
  auto pts = datasets::clustered(6000, 1, 6, 0.02f);
  auto qs = datasets::clustered(200, 2, 6, 0.02f);
  for (const char* pr : {"auto", "paper", "paper-cells"}) {
    CAPTURE(pr);
    BlockHashBuildParams bp;
    bp.preset = BlockHashBuildParams::parse_preset(pr);
    auto a = BlockHashIndex::build(test::runtime(), pts.data(), 6000, bp);
    std::string path = test::tmp_path(std::string("bh_io_") + pr + ".bhi");
    a->save(path);
    auto b = BlockHashIndex::load(test::runtime(), path);
    CHECK(b->L() == a->L());
    CHECK(b->P() == a->P());
    CHECK(b->B() == a->B());
    CHECK(b->X() == a->X());
    CHECK(b->info().preset == a->info().preset);
    CHECK(b->memory_bytes() == a->memory_bytes());
    CHECK(b->info().occupied_cells == a->info().occupied_cells);
    CHECK(b->structure().refs == a->structure().refs);
    CHECK(b->structure().thresholds == a->structure().thresholds);
    SearchParams p = test::knn_params(10);
    KnnResult ra = a->query(qs, p), rb = b->query(qs, p);
    CHECK(ra.ids == rb.ids);
    CHECK(ra.dist2 == rb.dist2);
  }
}

TEST_CASE("blockhash io: truncated, corrupt, foreign and missing files are errors") {
  auto pts = datasets::uniform(1500, 3);
  auto a = BlockHashIndex::build(test::runtime(), pts.data(), 1500);
  std::string path = test::tmp_path("bh_io_good.bhi"), bad = test::tmp_path("bh_io_bad.bhi");
  a->save(path);
  const std::string good = slurp(path);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), test::tmp_path("no_such.bhi")),
                       doctest::Contains("cannot open"), Error);
  spit(bad, "");
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("truncated"), Error);
  spit(bad, good.substr(0, good.size() - 7));
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("truncated"), Error);
  spit(bad, good + "x");
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("trailing"), Error);
  std::string flip = good;
  flip[flip.size() / 2] ^= 0x10;
  spit(bad, flip);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("checksum"), Error);
  std::string magic = good;
  magic[0] = 'X';
  spit(bad, magic);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("magic"), Error);
  std::string version = good;
  version[8] = 9;
  spit(bad, version);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("version"), Error);
  // Fuzz: random byte changes anywhere and random cuts; every outcome is a clean load or an
  // Error naming the file.
  std::mt19937_64 rng(7);
  int errors = 0;
  for (int it = 0; it < 300; ++it) {
    std::string d = good;
    if (it % 3 == 0) {
      d.resize(rng() % d.size());
    } else {
      int n = 1 + int(rng() % 4);
      for (int j = 0; j < n; ++j) d[rng() % (it % 3 == 1 ? std::min<std::size_t>(d.size(), 160) : d.size())] = char(rng());
    }
    spit(bad, d);
    try {
      auto idx = BlockHashIndex::load(test::runtime(), bad);
      CHECK(idx->size() == 1500);
    } catch (const Error& e) {
      ++errors;
      REQUIRE(std::string(e.what()).find(bad) != std::string::npos);
    }
  }
  CHECK(errors > 250);
}

TEST_CASE("blockhash io: every header byte is covered: any change to it is refused") {
  auto pts = datasets::clustered(1200, 5, 4, 0.02f);
  auto a = BlockHashIndex::build(test::runtime(), pts.data(), 1200);
  const std::string path = test::tmp_path("bh_io_hdr.bhi"), bad = test::tmp_path("bh_io_hdr_bad.bhi");
  a->save(path);
  const std::string good = slurp(path);
  // The block layouts' header is the first 160 bytes (io.cpp): flags, B, the quantiser, the
  // Hilbert seed, the medians, the high bits of L/P/B/X. Version 3 checked the payload only.
  for (std::size_t byte = 0; byte < std::min<std::size_t>(160, good.size()); ++byte) {
    for (unsigned char bit : {0x01, 0x80}) {
      std::string d = good;
      d[byte] = char(d[byte] ^ bit);
      spit(bad, d);
      INFO("byte " << byte << " bit " << int(bit));
      CHECK_THROWS_AS(BlockHashIndex::load(test::runtime(), bad), Error);
    }
  }
  // A version 3 file of the block layouts is refused naming both versions.
  BlockHashBuildParams blocks;
  blocks.grid = 0;
  auto c = BlockHashIndex::build(test::runtime(), pts.data(), 1200, blocks);
  c->save(path);
  std::string v3 = slurp(path);
  v3[8] = 3;
  spit(bad, v3);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad),
                       doctest::Contains("version 3, this library reads versions 4 and 5"), Error);
  // The grid's header (80 bytes with its checksum) likewise.
  REQUIRE(a->info().grid);
  for (std::size_t byte = 0; byte < 80; ++byte) {
    std::string d = good;
    d[byte] = char(d[byte] ^ 0x01);
    spit(bad, d);
    INFO("grid header byte " << byte);
    CHECK_THROWS_AS(BlockHashIndex::load(test::runtime(), bad), Error);
  }
}

TEST_CASE("blockhash io: a directory, a FIFO or a device is refused before it is read") {
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), test::tmp_path("")), doctest::Contains("is a directory"), Error);
  const std::string fifo = test::tmp_path("bh_io_fifo");
  std::remove(fifo.c_str());
  REQUIRE(mkfifo(fifo.c_str(), 0600) == 0);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), fifo), doctest::Contains("is a FIFO"), Error);
  if (std::ifstream("/dev/zero").good())
    CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), "/dev/zero"), doctest::Contains("character device"), Error);
  for (const std::string& p : {test::tmp_path(""), fifo})
    CHECK_THROWS_WITH_AS(read_points_file(p), doctest::Contains("not a point file"), Error);
  if (std::ifstream("/dev/zero").good())  // once read as "empty"
    CHECK_THROWS_WITH_AS(read_points_file("/dev/zero"), doctest::Contains("is a character device, not a point file"), Error);
}

TEST_CASE("blockhash io: a consistent file with broken invariants is refused by validation") {
  // Structural checks stand behind the checksum: rebuild the checksum after damaging a field.
  auto pts = datasets::uniform(800, 4);
  BlockHashBuildParams bp;
  bp.P = 4;
  bp.grid = 0;  // auto's L tables
  auto a = BlockHashIndex::build(test::runtime(), pts.data(), 800, bp);
  blockhash::Structure s = a->structure();
  s.refs[0] = 1 << 20;  // a block that does not exist
  std::string path = test::tmp_path("bh_io_invalid.bhi");
  blockhash::save_structure(s, path);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), path), doctest::Contains("holds block"), Error);
  s = a->structure();
  s.order[3] = s.order[4];
  blockhash::save_structure(s, path);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), path), doctest::Contains("permutation"), Error);
  s = a->structure();
  REQUIRE(s.thresholds[0] < s.thresholds[1]);
  std::swap(s.thresholds[0], s.thresholds[1]);
  blockhash::save_structure(s, path);
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), path), doctest::Contains("ascending"), Error);
}

TEST_CASE("blockhash io: a saved index of the retired layout of blocks aligned to cells is refused naming the file") {
  // Files of that layout carry header flag 64 (io.cpp); this library cannot answer from them.
  auto pts = datasets::uniform(600, 5);
  BlockHashBuildParams bp;
  bp.grid = 0;
  auto a = BlockHashIndex::build(test::runtime(), pts.data(), 600, bp);
  const std::string path = test::tmp_path("bh_io_retired.bhi"), old = test::tmp_path("bh_io_retired_cells.bhi");
  a->save(path);
  spit(old, with_flags(slurp(path), 64));
  const std::string why = old + ": a block-hash index of the retired layout";
  CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), old), doctest::Contains(why.c_str()), Error);
  // The same bytes without the flag load: the refusal is the flag's, not a damaged file's.
  spit(old, with_flags(slurp(path), 0));
  CHECK(BlockHashIndex::load(test::runtime(), old)->size() == 600);
  std::remove(path.c_str());
  std::remove(old.c_str());
}
