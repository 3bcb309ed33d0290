// The caches compiled kernels live in (issue 38, "Environment"; issue 37's program binary cache):
// PoCL's kernel cache cut short or emptied (a crash, a power loss), the library's own program
// binaries cut short or emptied, and a PoCL cache folder that cannot be made. Each case runs bhcl
// in a child process with its own cache folders: on main the damaged caches killed every later
// run with SIGBUS or SIGABRT inside PoCL, and an unmakeable folder gave "no OpenCL device".
#include <doctest/doctest.h>

#include <filesystem>
#include <string>
#include <vector>

#include <sys/stat.h>

#include "core/program_cache.hpp"
#include "test_util.hpp"

namespace fs = std::filesystem;
using namespace bhcl;

namespace {

// A fresh, empty folder under the tests' tmp folder.
std::string fresh_folder(const std::string& name) {
  const std::string dir = test::tmp_path(name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

// Every file under dir whose name ends in `suffix`.
std::vector<fs::path> files_ending(const std::string& dir, const std::string& suffix) {
  std::vector<fs::path> out;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    const std::string s = e.path().string();
    if (e.is_regular_file() && s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0)
      out.push_back(e.path());
  }
  return out;
}

void cut_to_half(const fs::path& p) { fs::resize_file(p, fs::file_size(p) / 2); }

std::size_t occurrences(const std::string& text, const std::string& what) {
  std::size_t n = 0;
  for (std::size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
  return n;
}

// One bhcl knn run (brute force, k = 4) over small inputs; its ids file's bytes.
struct KnnRun {
  std::string P, Q, ids, d2;
  explicit KnnRun(const std::string& stem) {
    const test::CliInputs in = test::cli_inputs(stem, 3000, 11, 200, 12);
    P = in.P;
    Q = in.Q;
    ids = test::tmp_path(stem + "_ids.i32");
    d2 = test::tmp_path(stem + "_d2.f32");
  }
  int run(const std::string& env, std::string* out) const {
    return test::run_bhcl("knn --points " + P + " --queries " + Q + " --method bruteforce --k 4 --quiet --out-ids " +
                              ids + " --out-dist2 " + d2,
                          out, env);
  }
};

// A case with both caches in fresh folders of its own (PoCL's and the library's program binaries),
// filled by a first run whose ids every later run must give again.
struct BothCaches {
  std::string pocl, mine, env;
  KnnRun k;
  std::string want;
  explicit BothCaches(const std::string& stem)
      : pocl(fresh_folder(stem + "_pocl")),
        mine(fresh_folder(stem + "_lib")),
        env("POCL_CACHE_DIR=" + pocl + " BHCL_CACHE_DIR=" + mine),
        k(stem) {
    std::string out;
    REQUIRE(k.run(env, &out) == 0);
    want = test::slurp(k.ids);
  }
  ~BothCaches() {
    fs::remove_all(pocl);
    fs::remove_all(mine);
  }
  // A run after damage: status 0, `told` said exactly once, the first run's ids; its output in out.
  void expect_recovered(const std::string& told, std::string& out) const {
    const int rc = k.run(env, &out);
    INFO(out);
    CHECK(rc == 0);
    CHECK(occurrences(out, told) == 1);
    CHECK(test::slurp(k.ids) == want);
  }
};

}  // namespace

TEST_CASE("pocl_cache_cut_short_or_emptied_is_recompiled_not_a_crash") {
  const std::string pocl = fresh_folder("pcache_cut_pocl");
  // The library's binary cache off: the build from source meets PoCL's damaged files.
  const std::string env = "POCL_CACHE_DIR=" + pocl + " BHCL_PROGRAM_CACHE=0";
  const KnnRun k("pcache_cut");
  std::string out;
  REQUIRE(k.run(env, &out) == 0);
  const std::string want = test::slurp(k.ids);
  auto sos = files_ending(pocl, ".so");
  REQUIRE(!sos.empty());
  for (const auto& p : sos) cut_to_half(p);
  int rc = k.run(env, &out);
  INFO(out);
  CHECK(rc == 0);
  CHECK(occurrences(out, "damaged compiled kernel") == 1);  // told once
  CHECK(out.find(pocl) != std::string::npos);                // naming the cache folder
  CHECK(test::slurp(k.ids) == want);
  // Repaired: the next run is silent.
  rc = k.run(env, &out);
  CHECK(rc == 0);
  CHECK(out.find("damaged") == std::string::npos);
  // Emptied, bitcode included.
  for (const auto& p : files_ending(pocl, ".so")) fs::resize_file(p, 0);
  for (const auto& p : files_ending(pocl, ".bc")) fs::resize_file(p, 0);
  rc = k.run(env, &out);
  CHECK(rc == 0);
  CHECK(occurrences(out, "damaged compiled kernel") == 1);
  CHECK(test::slurp(k.ids) == want);
  fs::remove_all(pocl);
}

TEST_CASE("pocl_cache_damage_under_a_cached_program_binary_is_recompiled") {
  const BothCaches c("pcache_bin");
  REQUIRE(!files_ending(c.mine, ".bin").empty());
  for (const auto& p : files_ending(c.pocl, ".so")) cut_to_half(p);
  std::string out;
  c.expect_recovered("damaged compiled kernel", out);
}

TEST_CASE("program_binary_cut_short_or_emptied_is_recompiled_and_replaced") {
  const BothCaches c("pbin");
  const auto bins = files_ending(c.mine, ".bin");
  REQUIRE(bins.size() == 1);  // one program: bruteforce at k <= 8
  std::string out;
  for (const bool empty : {false, true}) {
    CAPTURE(empty);
    if (empty) fs::resize_file(bins[0], 0);
    else cut_to_half(bins[0]);
    c.expect_recovered("is damaged", out);
    CHECK(out.find(bins[0].string()) != std::string::npos);
    // Replaced by the recompiled program: the next run loads it, silently.
    REQUIRE(fs::exists(bins[0]));
    CHECK(c.k.run(c.env, &out) == 0);
    CHECK(out.find("damaged") == std::string::npos);
  }
  // One flipped byte: the checksum catches it.
  std::string bytes = test::slurp(bins[0].string());
  bytes[bytes.size() / 2] = static_cast<char>(bytes[bytes.size() / 2] ^ 0x40);
  test::spit(bins[0].string(), bytes);
  c.expect_recovered("checksum does not match", out);
}

TEST_CASE("unmakeable_pocl_cache_folder_falls_back_to_a_private_one") {
  const std::string mine = fresh_folder("pcache_ro_lib");
  // /proc takes no new folders, not even from root (a read-only HOME is the user's case).
  const std::string bad = "/proc/bhcl-no-such-folder/kcache";
  const KnnRun k("pcache_ro");
  std::string out;
  const int rc = k.run("POCL_CACHE_DIR=" + bad + " BHCL_CACHE_DIR=" + mine, &out);
  INFO(out);
  REQUIRE(rc == 0);
  CHECK(occurrences(out, "cannot be used") == 1);
  CHECK(out.find("'" + bad + "'") != std::string::npos);
  const std::string tag = "private temporary folder '";
  const std::size_t at = out.find(tag);
  REQUIRE(at != std::string::npos);
  const std::string priv = out.substr(at + tag.size(), out.find('\'', at + tag.size()) - at - tag.size());
  CHECK(!fs::exists(priv));  // removed at exit
  fs::remove_all(mine);
}

TEST_CASE("pocl_file_damage_names_cut_and_empty_files") {
  // A whole shared object (the C library) passes; cut copies of it do not.
  const std::string dir = fresh_folder("pfile_damage");
  const std::string libc = "/lib/x86_64-linux-gnu/libc.so.6";
  if (!fs::exists(libc)) {
    test::report_skip("no " + libc);
    return;
  }
  const std::string so = dir + "/k.so";
  fs::copy_file(libc, so);
  CHECK(detail::pocl_file_damage(so) == "");
  cut_to_half(so);
  CHECK(detail::pocl_file_damage(so) != "");
  fs::resize_file(so, 0);
  CHECK(detail::pocl_file_damage(so) == "empty");
  test::spit(dir + "/p.bc", "BC\xC0\xDE");  // a magic, no block
  CHECK(detail::pocl_file_damage(dir + "/p.bc") != "");
  test::spit(dir + "/q.bc", "not bitcode at all");
  CHECK(detail::pocl_file_damage(dir + "/q.bc") == "not LLVM bitcode");
  fs::remove_all(dir);
}

// The grid kNN programs (one per option string) dumped under dir.
static std::size_t grid_knn_programs(const std::string& dir) {
  std::size_t n = 0;
  for (const fs::path& f : files_ending(dir, ".options")) n += f.filename().string().rfind("blockhash_grid_knn.", 0) == 0;
  return n;
}

TEST_CASE("prepare_knn builds the grid's kNN program before any index, the one the query then uses") {
  // Every program this process builds is dumped (BHCL_DUMP_PROGRAMS) the first time its
  // (file, options) is built on a context; a fresh runtime has its own context.
  const std::string dir = fresh_folder("prepare_knn_dump");
  REQUIRE(setenv("BHCL_DUMP_PROGRAMS", dir.c_str(), 1) == 0);
  auto rt = std::make_shared<Runtime>();
  SearchParams p;
  p.k = 10;
  prepare_knn("blockhash", *rt, {}, p);
  CHECK(grid_knn_programs(dir) == 1);
  // The index's query asks for the same program: nothing more is built (a second file would be
  // another option string, i.e. prepare_knn built a program the query does not use).
  const std::vector<float> pts = datasets::uniform(20000, 5);
  auto index = make_index("blockhash", rt, pts.data(), pts.size() / 3);
  KnnResult r;
  index->query(pts.data(), 1000, p, r);
  CHECK(grid_knn_programs(dir) == 1);
  // Methods whose programs depend on their points build nothing ahead; the block layouts neither.
  prepare_knn("kdtree", *rt, {}, p);
  MethodOptions tables;
  tables.set("grid", "0");
  prepare_knn("blockhash", *rt, tables, p);
  CHECK(grid_knn_programs(dir) == 1);
  unsetenv("BHCL_DUMP_PROGRAMS");
  // Bad options are the build's errors.
  MethodOptions bad;
  bad.set("grid", "7");
  CHECK_THROWS_AS(prepare_knn("blockhash", *rt, bad, p), Error);
}
