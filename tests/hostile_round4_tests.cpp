// Issue 38's hostile round: temporaries and signals, crafted index files, locales, thread limits,
// a FLT_MAX text point, --device digits past the integer range, render --out /dev/null. Each test
// reproduces the defect as the issue found it on main and checks the fixed behaviour.
#include <cfloat>
#include <clocale>
#include <csignal>
#include <cstring>

#include <dirent.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include "blockhash/build.hpp"
#include "blockhash/grid.hpp"
#include "blockhash/grid_io.hpp"
#include "blockhash_cl/atomic_file.hpp"
#include "blockhash_cl/numbers.hpp"
#include "blockhash_cl/parallel.hpp"
#include "test_util.hpp"

namespace bhcl {
namespace {

std::string slurp_file(const std::string& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}
void spit_file(const std::string& p, const std::string& d) { std::ofstream(p, std::ios::binary) << d; }

std::vector<std::string> entries_with(const std::string& dir, const std::string& part) {
  std::vector<std::string> out;
  if (DIR* d = opendir(dir.c_str())) {
    while (dirent* e = readdir(d))
      if (std::string(e->d_name).find(part) != std::string::npos) out.push_back(e->d_name);
    closedir(d);
  }
  return out;
}

// A fresh folder under the test folder.
std::string fresh_dir(const std::string& name) {
  const std::string d = test::tmp_path(name + "_" + std::to_string(getpid()));
  std::system(("rm -rf '" + d + "'").c_str());
  REQUIRE(mkdir(d.c_str(), 0755) == 0);
  return d;
}

// --- temporaries and signals

TEST_CASE("atomic file: a name of 250 bytes and a path of 4090 characters are written") {
  const std::string dir = fresh_dir("long_names");
  const std::string name250(250, 'n');
  write_file(dir + "/" + name250, {std::string("hello")}, "a test file");
  CHECK(slurp_file(dir + "/" + name250) == "hello");
  CHECK(entries_with(dir, "tmp").empty());
  // A path of 4090 characters: folders of 200 characters down to it, then the name.
  std::string deep = dir;
  while (deep.size() + 1 + 200 + 1 + 20 < 4090) {
    deep += "/" + std::string(200, 'd');
    REQUIRE(mkdir(deep.c_str(), 0755) == 0);
  }
  const std::string file = deep + "/" + std::string(4090 - deep.size() - 1, 'f');
  REQUIRE(file.size() == 4090);
  write_file(file, {std::string("deep")}, "a test file");
  CHECK(slurp_file(file) == "deep");
  // A name past NAME_MAX is refused naming it, before anything is written.
  CHECK_THROWS_WITH_AS(write_file(dir + "/" + std::string(256, 'x'), {std::string("x")}, "a test file"),
                       doctest::Contains("File name too long"), Error);
  std::system(("rm -rf '" + dir + "'").c_str());
}

TEST_CASE("atomic file: stale temporaries of this process's PID never block a write and are removed") {
  // A container's entrypoint is PID 1 in every run: the temporaries a killed run left carry the
  // PID of the next run. Here the child's own PID stands for it, with both naming schemes.
  const std::string dir = fresh_dir("stale_tmp");
  const std::string target = dir + "/out.bin";
  const pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    const std::string me = std::to_string(getpid());
    for (int k = 0; k < 200; ++k) spit_file(dir + "/.out.bin.tmp." + me + "." + std::to_string(k), "stale");
    spit_file(dir + "/.out.bin.bhcltmp." + me + ".0123456789abcdef", "stale");
    try {
      write_file(target, {std::string("fresh")}, "a test file");
    } catch (const std::exception& e) {
      std::fprintf(stderr, "%s\n", e.what());
      _exit(1);
    }
    _exit(0);
  }
  int status = 0;
  REQUIRE(waitpid(pid, &status, 0) == pid);
  REQUIRE(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 0);
  CHECK(slurp_file(target) == "fresh");
  CHECK(entries_with(dir, "tmp").empty());
  // A temporary of a live other process (this one, the parent) is left alone.
  const std::string live = dir + "/.out.bin.bhcltmp." + std::to_string(getppid()) + ".00000000000000aa";
  spit_file(live, "in use");
  write_file(target, {std::string("again")}, "a test file");
  CHECK(std::ifstream(live).good());
  std::system(("rm -rf '" + dir + "'").c_str());
}

TEST_CASE("atomic file: SIGINT, SIGTERM and SIGHUP remove the temporaries and exit 130, 143, 129") {
  for (const auto& [sig, code] : {std::pair<int, int>{SIGINT, 130}, {SIGTERM, 143}, {SIGHUP, 129}}) {
    const std::string dir = fresh_dir("signal_tmp_" + std::to_string(sig));
    int ready[2];
    REQUIRE(pipe(ready) == 0);
    const pid_t pid = fork();
    REQUIRE(pid >= 0);
    if (pid == 0) {
      close(ready[0]);
      install_temporary_cleanup();
      AtomicFile a(dir + "/result.bin", "a test file");
      AtomicFile b(dir + "/other.bin", "a test file");
      a.write("partial", 7);
      b.write("partial", 7);
      (void)!write(ready[1], "r", 1);
      for (;;) pause();
    }
    close(ready[1]);
    char c = 0;
    REQUIRE(read(ready[0], &c, 1) == 1);
    close(ready[0]);
    CHECK(entries_with(dir, "tmp").size() == 2);  // the two temporaries exist while writing
    kill(pid, sig);
    int status = 0;
    REQUIRE(waitpid(pid, &status, 0) == pid);
    INFO("signal " << sig);
    REQUIRE(WIFEXITED(status));
    CHECK(WEXITSTATUS(status) == code);
    CHECK(entries_with(dir, "tmp").empty());
    CHECK(!std::ifstream(dir + "/result.bin").good());
    std::system(("rm -rf '" + dir + "'").c_str());
  }
}

// --- crafted index files

std::uint64_t fnv1a(const char* p, std::size_t n, std::uint64_t h = 0xcbf29ce484222325ull) {
  for (std::size_t i = 0; i < n; ++i) h = (h ^ static_cast<unsigned char>(p[i])) * 0x100000001b3ull;
  return h;
}
// Grid file version 3 (grid_io.cpp): the header is 132 bytes, the checksum at 132, the payload at 140.
constexpr std::size_t kGridH = 48, kGridInvH = 52, kGridBound = 84, kGridSum = 132, kGridPayload = 140;
void grid_checksum(std::string& d) {
  const std::uint64_t s = fnv1a(d.data() + kGridPayload, d.size() - kGridPayload, fnv1a(d.data(), kGridSum));
  std::memcpy(&d[kGridSum], &s, 8);
}
template <typename T>
T field_at(const std::string& d, std::size_t at) {
  T v;
  std::memcpy(&v, d.data() + at, sizeof v);
  return v;
}
template <typename T>
void set_field(std::string& d, std::size_t at, T v) { std::memcpy(&d[at], &v, sizeof v); }

std::vector<float> cloud(std::size_t n, unsigned seed) {
  std::vector<float> p(3 * n);
  std::uint64_t s = seed * 0x9e3779b97f4a7c15ull + 1;
  for (auto& v : p) {
    s = s * 6364136223846793005ull + 1442695040888963407ull;
    v = float((s >> 40) & 0xffffff) / float(1 << 24);
  }
  return p;
}

TEST_CASE("grid index: a changed cell side with its checksum recomputed is refused naming the field") {
  const std::vector<float> pts = cloud(3000, 1);
  auto a = BlockHashIndex::build(test::runtime(), pts.data(), 3000, BlockHashBuildParams{});
  REQUIRE(a->info().grid);
  const std::string path = test::tmp_path("crafted_h.bhidx"), bad = test::tmp_path("crafted_h_bad.bhidx");
  a->save(path);
  const std::string good = slurp_file(path);
  {  // h alone (inv_h as saved): the search bounds cells by h and assigns them by inv_h
    std::string d = good;
    set_field(d, kGridH, field_at<float>(d, kGridH) * 1.5f);
    grid_checksum(d);
    spit_file(bad, d);
    CHECK_THROWS_WITH_AS(BlockHashIndex::load(test::runtime(), bad), doctest::Contains("field 'inv_h' is not 1 / h"), Error);
  }
  {  // both, consistently: the cells no longer hold their points
    std::string d = good;
    const float h = field_at<float>(d, kGridH) * 1.5f;
    set_field(d, kGridH, h);
    set_field(d, kGridInvH, 1.0f / h);
    grid_checksum(d);
    spit_file(bad, d);
    CHECK_THROWS_AS(BlockHashIndex::load(test::runtime(), bad), Error);
  }
  {  // the saved file itself still loads and answers as the index that saved it
    auto b = BlockHashIndex::load(test::runtime(), path);
    const std::vector<float> qs = cloud(200, 2);
    test::require_identical(b->query(qs, test::knn_params(8)), a->query(qs, test::knn_params(8)),
                            "the reloaded grid");
  }
  std::remove(path.c_str());
  std::remove(bad.c_str());
}

TEST_CASE("grid and block index: an id bound of 2^31 - 2 allocates nothing by it and is refused against the points") {
  const std::vector<float> pts = cloud(2000, 3);
  const std::string path = test::tmp_path("crafted_bound.bhidx"), bad = test::tmp_path("crafted_bound_bad.bhidx");
  {  // the grid
    auto a = BlockHashIndex::build(test::runtime(), pts.data(), 2000, BlockHashBuildParams{});
    a->save(path);
    std::string d = slurp_file(path);
    set_field<std::uint64_t>(d, kGridBound, 0x7ffffffeull);
    grid_checksum(d);
    spit_file(bad, d);
    // Parsing needs memory of the order of the file, not of the bound (8 GiB before the fix).
    CHECK(test::with_memory_limit(std::size_t(512) << 20, [&] { blockhash::parse_grid(d, bad); }) == 0);
    CHECK_THROWS_WITH_AS(make_index("blockhash", test::runtime(), pts.data(), 2000, MethodOptions().set("load-index", bad)),
                         doctest::Contains("of ids 0 .. 2147483645"), Error);
  }
  {  // the block layouts: the id bound is the header's field before its checksum (io.cpp)
    BlockHashBuildParams bp;
    bp.grid = 0;
    auto a = BlockHashIndex::build(test::runtime(), pts.data(), 2000, bp);
    a->save(path);
    std::string d = slurp_file(path);
    const std::uint32_t hb = field_at<std::uint32_t>(d, 16);
    set_field<std::uint64_t>(d, hb - 16, 0x7ffffffeull);
    CHECK(test::with_memory_limit(std::size_t(512) << 20, [&] { blockhash::parse_structure(d, bad, false); }) == 0);
  }
  std::remove(path.c_str());
  std::remove(bad.c_str());
}

// --- environment

TEST_CASE("select_device: indexes past the integer range name no device, never 'stoul'") {
  for (const std::string spec : {"0:99999999999999999999", "99999999999999999999:0", "cpu:99999999999999999999"}) {
    const std::string m = test::error_of([&] { select_device(spec); });
    INFO(m);
    CHECK(m.find("stoul") == std::string::npos);
    CHECK(m.find("no OpenCL device matches '" + spec + "'") != std::string::npos);
  }
  std::string out;
  CHECK(test::run_bhcl("devices --device 0:99999999999999999999", &out) == 1);
  CHECK(out.find("stoul") == std::string::npos);
  CHECK(test::run_bhcl("knn --points x --queries x --k 1 --out-ids /dev/null", &out, "BHCL_DEVICE=0:99999999999999999999") != 0);
  CHECK(out.find("stoul") == std::string::npos);
}

// A locale whose decimal point is a comma, built with localedef into a private LOCPATH (no root
// needed; the locales package ships localedef and the de_DE source). False where it cannot be.
bool comma_locale() {
  static int made = -1;
  if (made < 0) {
    const std::string dir = test::tmp_path("locales");
    mkdir(dir.c_str(), 0755);
    const std::string cmd = "localedef -i de_DE -f UTF-8 '" + dir + "/de_DE.UTF-8' > /dev/null 2>&1";
    made = std::system(cmd.c_str()) == 0 || std::ifstream(dir + "/de_DE.UTF-8/LC_NUMERIC").good();
    setenv("LOCPATH", dir.c_str(), 1);
  }
  return made && std::setlocale(LC_ALL, "de_DE.UTF-8") != nullptr;
}

TEST_CASE("numbers: options, point files and messages read '.' under a comma-decimal locale") {
  if (!comma_locale()) {
    test::report_skip("localedef cannot build de_DE.UTF-8 here (the locales package)");
    return;
  }
  REQUIRE(std::string(std::localeconv()->decimal_point) == ",");
  const OptionInfo* a = nullptr;
  for (const OptionInfo& o : method_info("blockhash").options)
    if (o.name == "A") a = &o;
  REQUIRE(a != nullptr);
  std::string why;
  double got = 0;
  try {
    got = a->parse("8.5", "A").number;
  } catch (const std::exception& e) {
    why = e.what();
  }
  const std::string path = test::tmp_path("locale_points.txt");
  spit_file(path, "0.5 1.25 2.75\n-3.5e-1 4 5\n");
  std::vector<float> pts;
  std::string read_error;
  try {
    pts = read_points_file(path);
  } catch (const std::exception& e) {
    read_error = e.what();
  }
  std::setlocale(LC_ALL, "C");
  CHECK(why == "");
  CHECK(got == 8.5);
  CHECK(read_error == "");
  CHECK(pts == std::vector<float>{0.5f, 1.25f, 2.75f, -0.35f, 4, 5});
  std::remove(path.c_str());
}

TEST_CASE("numbers: from_chars parsing as strtod in the C locale, and out-of-range cases") {
  using detail::NumberParse;
  double v = 0;
  CHECK(detail::parse_double("+1.5", v) == NumberParse::Ok);
  CHECK(v == 1.5);
  CHECK(detail::parse_double("0x1.8p1", v) == NumberParse::Ok);
  CHECK(v == 3.0);
  CHECK(detail::parse_double("-inf", v) == NumberParse::Ok);
  CHECK(v == -INFINITY);
  CHECK(detail::parse_double("1e999", v) == NumberParse::OutOfRange);
  CHECK(v == INFINITY);
  CHECK(detail::parse_double("1,5", v) == NumberParse::NotNumber);
  CHECK(detail::parse_double("+-1", v) == NumberParse::NotNumber);
  CHECK(detail::parse_double("", v) == NumberParse::NotNumber);
  unsigned long long u = 0;
  CHECK(detail::parse_integer("99999999999999999999", u) == NumberParse::OutOfRange);
  CHECK(detail::parse_integer("12x", u) == NumberParse::NotNumber);
  CHECK(detail::parse_integer("-1", u) == NumberParse::NotNumber);
  CHECK(detail::format_general(0.1, 17) == "0.10000000000000001");
}

TEST_CASE("text point file: 3.4028235e+38 (FLT_MAX as numpy prints it) is accepted, what rounds to inf refused") {
  const std::string path = test::tmp_path("flt_max_points.txt");
  spit_file(path, "3.4028235e+38 -3.4028235e+38 0\n");
  const std::vector<float> pts = read_points_file(path);
  CHECK(pts == std::vector<float>{FLT_MAX, -FLT_MAX, 0});
  spit_file(path, "3.4028236e+38 0 0\n");  // past FLT_MAX + half an ulp: rounds to inf
  CHECK_THROWS_WITH_AS(read_points_file(path), doctest::Contains("beyond the float range"), Error);
  std::remove(path.c_str());
}

TEST_CASE("parallel: threads the OS cannot start never abort, the work runs on those that did") {
  // An address space too small for one more thread's stack (8 MiB): std::thread throws
  // std::system_error; before the fix that destroyed joinable threads (std::terminate).
  for (int shape = 0; shape < 3; ++shape) {
    INFO("shape " << shape);
    const int rc = test::with_memory_limit(std::size_t(4) << 20, [shape] {
      std::vector<int> hit(64, 0);
      if (shape == 0) {
        detail::parallel_for(64, [&](std::size_t b, std::size_t e) { for (std::size_t i = b; i < e; ++i) hit[i] += 1; }, 8, 1);
      } else if (shape == 1) {
        detail::parallel_chunks(64, 4, 8, [&](std::size_t, std::size_t b, std::size_t e) { for (std::size_t i = b; i < e; ++i) hit[i] += 1; });
      } else {
        detail::parallel_tasks(64, [&](std::size_t i) { hit[i] += 1; });
      }
      for (int h : hit)
        if (h != 1) throw Error("an element was not done exactly once");
    });
    CHECK(rc == 0);
  }
}

TEST_CASE("render --out /dev/null writes the PNG preview to the device, never /dev/null.png") {
  if (!std::ifstream("/dev/null").good() || access("/dev", W_OK) != 0) {
    test::report_skip("/dev is not writable here: /dev/null.png could not be made either way");
    return;
  }
  std::remove("/dev/null.png");
  test::run_bhcl_ok("render --out /dev/null --photons 2000 --size 16x16 --quiet");
  struct stat st {};
  CHECK(stat("/dev/null.png", &st) != 0);
  REQUIRE(stat("/dev/null", &st) == 0);
  CHECK(S_ISCHR(st.st_mode));
  std::remove("/dev/null.png");
}

}  // namespace
}  // namespace bhcl
