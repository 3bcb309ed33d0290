// The bhcl tool: bad input exits non-zero with one clear line; knn writes the documented files.
#include "test_util.hpp"

#include <nlohmann/json.hpp>

#include "blockhash_cl/config.hpp"

using namespace bhcl;

namespace {

using test::write_points;

}  // namespace

TEST_CASE("cli: knn bruteforce writes ids, distances and stats") {
  auto [pts, qs, P, Q] = test::cli_inputs("cli", 2000, 61, 50, 62);
  std::string I = test::tmp_path("cli_ids.i32"), D = test::tmp_path("cli_d2.f32"),
              S = test::tmp_path("cli_stats.json");
  std::string out = test::run_bhcl_ok("knn --points " + P + " --queries " + Q +
                              " --k 7 --method bruteforce --out-ids " + I + " --out-dist2 " + D +
                              " --stats " + S);
  auto ids = test::read_raw<std::int32_t>(I);
  auto d2 = test::read_raw<float>(D);
  REQUIRE(ids.size() == 50 * 7);
  REQUIRE(d2.size() == 50 * 7);
  SearchParams p = test::knn_params(7);
  KnnResult ref = reference::knn_float(pts.data(), 2000, qs.data(), 50, p);
  CHECK(ids == ref.ids);
  CHECK(d2 == ref.dist2);
  std::ifstream s(S);
  const nlohmann::json j = nlohmann::json::parse(s);  // throws (fails the test) unless valid JSON
  INFO(j.dump(2));
  CHECK(j.at("method") == "bruteforce");
  CHECK(j.at("exact") == true);
  CHECK(j.at("N") == 2000);
  CHECK(j.at("n") == 50);
  CHECK(j.at("k") == 7);
  CHECK(j.at("version") == BHCL_VERSION_STRING);
  CHECK(j.at("command") == "knn");
  CHECK(j.at("max_radius").is_null());  // unbounded
  CHECK(j.at("search").at("k") == 7);
  CHECK(j.at("search").at("local_size").get<int>() > 0);  // the default resolved
  CHECK(!j.at("search").contains("A"));                   // an exact method: no A
  CHECK(j.at("build").is_object());
  for (const char* key : {"build_s", "query_s", "compile_s", "wall_s", "queries_per_s"})
    CHECK_MESSAGE(j.at(key).get<double>() >= 0, key);
  CHECK(j.at("neighbours_found") == 50 * 7);
  CHECK(j.at("device").get<std::string>().size() > 0);
}

TEST_CASE("cli: the stats of a block-hash run carry the build and search parameters used") {
  auto names = method_names();
  if (std::find(names.begin(), names.end(), "blockhash") == names.end()) return;
  auto pts = datasets::uniform(3000, 63);
  std::string P = write_points("clibh_p.f32", pts);
  std::string I = test::tmp_path("clibh_ids.i32"), D = test::tmp_path("clibh_d2.f32"),
              S = test::tmp_path("clibh_stats.json");
  std::string out = test::run_bhcl_ok("knn --points " + P + " --queries " + P + " --k 5 --method blockhash --A 3 --X 8 "
                          "--preset paper --seed 7 --max-radius 0.5 --out-ids " + I + " --out-dist2 " + D +
                          " --stats " + S);
  std::ifstream s(S);
  const nlohmann::json j = nlohmann::json::parse(s);
  INFO(j.dump(2));
  const auto& b = j.at("build");
  CHECK(b.at("preset") == "paper");
  CHECK(b.at("X") == 8);
  CHECK(b.at("seed") == 7);
  for (const char* key : {"L", "P", "B"}) CHECK_MESSAGE(b.at(key).get<int>() > 0, key);  // derived
  const auto& sp = j.at("search");
  CHECK(sp.at("A") == 3.0);
  CHECK(sp.at("k") == 5);
  CHECK(sp.at("max_radius").get<double>() == doctest::Approx(0.5));
  CHECK(sp.at("neighbour_probes").is_number_integer());  // 0, 1 or 2 as used
  CHECK(j.at("exact") == false);  // the paper's tables at A = 3
  // The default (the grid, exact): the run's "exact" says so.
  test::run_bhcl_ok("knn --points " + P + " --queries " + P + " --k 5 --method blockhash --out-ids " + I +
                    " --out-dist2 " + D + " --stats " + S);
  std::ifstream s2(S);
  const nlohmann::json j2 = nlohmann::json::parse(s2);
  CHECK(j2.at("search").at("exact") == true);
  CHECK(j2.at("exact") == true);
}

TEST_CASE("cli: bad input exits non-zero with one clear line") {
  auto pts = datasets::uniform(100, 71);
  std::string P = write_points("bad_p.f32", pts);
  std::string I = test::tmp_path("bad_ids"), D = test::tmp_path("bad_d2");
  std::string common = " --out-ids " + I + " --out-dist2 " + D + " --method bruteforce";

  struct Case {
    std::string args, expect;
    int rc;
  };
  std::string ragged = test::tmp_path("ragged.f32");
  {
    std::ofstream f(ragged, std::ios::binary);
    f << std::string(13, 'x');
  }
  auto nan_pts = pts;
  nan_pts[3 * 17 + 2] = NAN;
  std::string NP = write_points("nan_p.f32", nan_pts);
  std::string E = write_points("empty.f32", {});
  std::vector<Case> cases = {
      {"knn --points /no/such/file.f32 --queries " + P + " --k 3" + common, "/no/such/file.f32: cannot open", 1},
      {"knn --points " + ragged + " --queries " + P + " --k 3" + common, "not a multiple of 12", 1},
      {"knn --points " + NP + " --queries " + P + " --k 3" + common, "point 17 has a non-finite coordinate z", 1},
      {"knn --points " + P + " --queries " + NP + " --k 3" + common, "point 17 has a non-finite", 1},
      {"knn --points " + E + " --queries " + P + " --k 3" + common, "empty", 1},
      {"knn --points " + P + " --queries " + P + " --k 0" + common, "--k must be in [1, 256]", 2},
      {"knn --points " + P + " --queries " + P + " --k 257" + common, "--k must be in [1, 256]", 2},
      {"knn --points " + P + " --queries " + P + " --k x" + common, "--k expects an integer", 2},
      {"knn --points " + P + " --queries " + P + " --k 3 --method nope --out-ids " + I + " --out-dist2 " + D, "unknown method 'nope'", 1},
      {"knn --points " + P + " --queries " + P + " --k 3 --bogus 1" + common, "unknown option --bogus", 2},
      {"knn --points " + P + " --k 3" + common, "missing required option --queries", 2},
      {"knn --points " + P + " --queries " + P + " --k 3 --device no-such-dev" + common, "no OpenCL device matches", 1},
      {"knn --points " + P + " --queries " + P + " --k 3 --max-radius -2" + common, "--max-radius", 2},
      {"knn --points " + P + " --queries " + P + " --k 3 --method kdtree --save-index " + I + ".idx --out-ids " + I + " --out-dist2 " + D, "--save-index does not apply to method kdtree (only to blockhash)", 2},
      {"frobnicate", "unknown command", 2},
  };
  for (const auto& c : cases) {
    std::string out;
    int rc = test::run_bhcl(c.args, &out);
    INFO("bhcl " << c.args << "\n" << out);
    CHECK(rc == c.rc);
    CHECK(out.find(c.expect) != std::string::npos);
    CHECK(out.find("terminate") == std::string::npos);
  }
}

TEST_CASE("cli: --version prints the library version") {
  std::string out;
  CHECK(test::run_bhcl("--version", &out) == 0);
  CHECK(out.find(BHCL_VERSION_STRING) != std::string::npos);
}

TEST_CASE("cli: every command's --help exits 0 and lists each option with its meaning and default") {
  std::string out;
  CHECK(test::run_bhcl("--help", &out) == 0);
  for (const char* cmd : {"knn", "eval", "render", "demo", "devices"})
    CHECK_MESSAGE(out.find(cmd) != std::string::npos, cmd);
  struct Expect {
    std::string cmd;
    std::vector<std::string> shown;
  };
  std::vector<std::string> index_options = {
      "--k INT=10", "--max-radius NUM=inf", "--A NUM=0", "--probes", "--local-size", "--max-batch",
      "--preset NAME=auto", "--L ", "--P ", "--B ", "--X ", "--seed INT=1", "--load-index", "--save-index"};
  // Every build option of every registered method, with its declared default.
  for (const MethodInfo& m : methods())
    for (const OptionInfo* o : m.build_options())
      index_options.push_back("--" + o->name + (o->def.empty() ? std::string(" ") : "") +
                              (o->kind == OptionInfo::Kind::Integer ? " INT=" + o->def : ""));
  std::vector<Expect> cases = {
      {"knn", {"--points FILE REQUIRED", "--queries FILE REQUIRED", "--method NAME REQUIRED",
               "--out-ids FILE REQUIRED", "--out-dist2 FILE REQUIRED", "--out-counts", "--stats", "--device"}},
      {"eval", {"--points FILE REQUIRED", "--method NAME REQUIRED", "--truth NAME=", "--stats", "--device"}},
      {"render", {"--out IMAGE.exr REQUIRED", "--scene SCENE=cornell", "--photons INT=200000", "--size WxH=512x512",
                  "--compare", "--compare-A LIST=4,8,16", "--quiet", "--k INT=50"}},
      {"demo", {"--N INT=200000", "--n INT=20000", "--k INT=50", "--out-dir DIR=bhcl-demo", "--no-render"}},
      {"devices", {"--device SPEC"}},
  };
  for (auto c : cases) {
    if (c.cmd == "knn" || c.cmd == "eval")
      for (const auto& o : index_options) c.shown.push_back(o);
    int rc = test::run_bhcl(c.cmd + " --help", &out);
    INFO("bhcl " << c.cmd << " --help\n" << out);
    CHECK(rc == 0);
    for (const auto& s : c.shown) CHECK_MESSAGE(out.find(s) != std::string::npos, s);
    // Each option line carries its meaning: no line is only an option name.
    std::istringstream lines(out);
    for (std::string line; std::getline(lines, line);) {
      if (line.rfind("  --", 0) != 0) continue;
      std::size_t gap = line.find("  ", 4);
      CHECK_MESSAGE((gap != std::string::npos && line.find_first_not_of(' ', gap) != std::string::npos), line);
    }
  }
}

TEST_CASE("cli: missing --method, an option the method does not read, an out-of-range integer") {
  auto pts = datasets::uniform(100, 81);
  std::string P = write_points("usage_p.f32", pts);
  std::string I = test::tmp_path("usage_ids"), D = test::tmp_path("usage_d2");
  const std::string base = "knn --points " + P + " --queries " + P + " --out-ids " + I + " --out-dist2 " + D;
  struct Case {
    std::string args, expect;
  };
  std::vector<Case> cases = {
      {base + " --k 3", "missing required option --method"},
      {base + " --k 3 --method kdtree --A 4", "--A does not apply to method kdtree"},
      {base + " --k 3 --method bruteforce --threads 2", "--threads does not apply to method bruteforce"},
      {base + " --k 3 --method kdtree --L 4", "--L does not apply to method kdtree"},
      {base + " --k 99999999999999999999 --method kdtree", "--k must be in [1, 256]"},
      {base + " --k 4294967299 --method kdtree", "--k must be in [1, 256]"},  // 2^32 + 3: not narrowed to 3
      {base + " --k 3 --method blockhash --X 17", "--X must be in [1, 16] (or -1)"},
      {base + " --k 3 --method blockhash --seed -1", "--seed must be >= 0"},
      {base + " --k 3 --method kdtree --max-batch -5", "--max-batch must be >= 0"},
      {base + " --k 3 --method kdtree --k", "option --k needs a value"},
      {"eval --points " + P + " --queries " + P + " --method kdtree --truth bruteforce --threads 2",
       "--threads does not apply to method kdtree and bruteforce"},
      {"render --out " + I + ".exr --method bruteforce --A 4", "--A does not apply to method bruteforce"},
      {"demo --N 0", "--N must be in [1, "},
  };
  for (const auto& c : cases) {
    std::string out;
    int rc = test::run_bhcl(c.args, &out);
    INFO("bhcl " << c.args << "\n" << out);
    CHECK(rc == 2);
    CHECK(out.find(c.expect) != std::string::npos);
    CHECK(std::count(out.begin(), out.end(), '\n') == 1);  // one line
  }
}

TEST_CASE("cli: devices lists the OpenCL devices and the pick") {
  std::string out;
  int rc = test::run_bhcl("devices", &out);
  INFO(out);
  CHECK(rc == 0);
  CHECK(out.find("selected") != std::string::npos);
}

TEST_CASE("cli: knn bruteforce on the Stanford bunny agrees with the exact reference") {
  const std::string bunny = test::data_file("bunny.xyz.f32");
  if (bunny.empty()) {
    test::report_skip("bunny.xyz.f32 is not in BHCL_DATA_DIR (unset, or the file absent)");
    return;
  }
  auto pts = read_points_file(bunny);
  const std::size_t N = pts.size() / 3;
  // Every 50th bunny point, nudged off the surface, as queries.
  std::vector<float> qs;
  for (std::size_t i = 0; i < N; i += 50)
    for (int d = 0; d < 3; ++d) qs.push_back(pts[3 * i + d] + 1e-4f * float(d + 1));
  std::string Q = write_points("bunny_q.f32", qs);
  std::string I = test::tmp_path("bunny_ids"), D = test::tmp_path("bunny_d2");
  std::string out = test::run_bhcl_ok("knn --points " + bunny + " --queries " + Q +
                              " --k 16 --method bruteforce --out-ids " + I + " --out-dist2 " + D);
  KnnResult r;
  r.resize(qs.size() / 3, 16);
  r.ids = test::read_raw<std::int32_t>(I);
  r.dist2 = test::read_raw<float>(D);
  for (std::size_t q = 0; q < r.n; ++q) r.counts[q] = 16;
  SearchParams p = test::knn_params(16);
  test::check_exact_vs_double(r, pts.data(), N, qs.data(), r.n, p);
}

TEST_CASE("cli: PoCL's kernel cache: the build tree's, the user's cache directory when installed, or POCL_CACHE_DIR") {
  // Run from the build tree: the build tree's cache (the one ctest also sets).
  std::string out;
  REQUIRE(test::run_bhcl("devices", &out, "-u POCL_CACHE_DIR") == 0);
  INFO(out);
  const char* build_cache = std::getenv("POCL_CACHE_DIR");
  if (build_cache) CHECK(out.find(std::string("PoCL kernel cache: ") + build_cache) != std::string::npos);
  // A copy outside the build tree stands for the installed bhcl.
  char tmpl[] = "/tmp/bhcl_cache_test_XXXXXX";
  REQUIRE(mkdtemp(tmpl) != nullptr);
  const std::string dir = tmpl, exe = dir + "/bhcl", log = dir + "/out.txt";
  REQUIRE(std::system(("cp \"" BHCL_TOOL_PATH "\" \"" + exe + "\"").c_str()) == 0);
  auto run = [&](const std::string& env) {
    int status = std::system(("env " + env + " \"" + exe + "\" devices > \"" + log + "\" 2>&1").c_str());
    std::ifstream in(log);
    std::stringstream ss;
    ss << in.rdbuf();
    INFO(ss.str());
    CHECK(WIFEXITED(status));
    CHECK(WEXITSTATUS(status) == 0);
    return ss.str();
  };
  std::string o = run("-u POCL_CACHE_DIR XDG_CACHE_HOME=" + dir + "/xdg");
  CHECK(o.find("PoCL kernel cache: " + dir + "/xdg/blockhash_cl/pocl") != std::string::npos);
  CHECK(std::ifstream(dir + "/xdg/blockhash_cl/pocl").good());  // made
  o = run("-u POCL_CACHE_DIR -u XDG_CACHE_HOME HOME=" + dir + "/home");
  CHECK(o.find("PoCL kernel cache: " + dir + "/home/.cache/blockhash_cl/pocl") != std::string::npos);
  o = run("POCL_CACHE_DIR=" + dir + "/mine XDG_CACHE_HOME=" + dir + "/xdg");
  CHECK(o.find("PoCL kernel cache: " + dir + "/mine") != std::string::npos);
  std::system(("rm -rf \"" + dir + "\"").c_str());
}

TEST_CASE("cli: knn and eval draw progress on a terminal, and the sliced query answers the same") {
  if (std::system("command -v script > /dev/null 2>&1") != 0) {
    MESSAGE("util-linux `script` not found: no pseudo-terminal to test the progress bar on");
    return;
  }
  const std::string P = write_points("prog_p.f32", datasets::uniform(40000, 71));
  const std::string Q = write_points("prog_q.f32", datasets::uniform(70000, 72));  // 3 slices
  const std::string O = test::tmp_path("prog_");
  const std::string args = "knn --points " + P + " --queries " + Q + " --method kdtree --k 5 --out-ids ";
  // `script` gives bhcl a pseudo-terminal as stderr, as a user's shell would; returns what it
  // printed.
  auto on_terminal = [&](const std::string& tail) {
    const std::string log = O + "tty.txt";
    const std::string cmd = "script -qec '\"" + std::string(BHCL_TOOL_PATH) + "\" " + args + tail +
                            "' /dev/null > " + log + " 2>&1";
    REQUIRE(std::system(cmd.c_str()) == 0);
    std::ifstream in(log);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
  };
  const std::string tty = on_terminal(O + "ids_tty --out-dist2 " + O + "d2_tty");
  CHECK(tty.find("build kdtree (40000 points)") != std::string::npos);
  CHECK(tty.find("query kdtree (70000 queries)") != std::string::npos);
  CHECK(tty.find("100.0%") != std::string::npos);
  std::string out;
  REQUIRE(test::run_bhcl(args + O + "ids --out-dist2 " + O + "d2", &out) == 0);
  CHECK(out.find("query kdtree (") == std::string::npos);  // no bar when stderr is not a terminal
  CHECK(test::read_raw<std::int32_t>(O + "ids_tty") == test::read_raw<std::int32_t>(O + "ids"));
  CHECK(test::read_raw<float>(O + "d2_tty") == test::read_raw<float>(O + "d2"));
  // --quiet silences the bars on a terminal too.
  CHECK(on_terminal(O + "ids_q --out-dist2 " + O + "d2_q --quiet").find("query kdtree (") == std::string::npos);
}

TEST_CASE("cli: a failed write of any output is an error, never an empty file and status 0") {
  if (!std::ifstream("/dev/full").good()) {
    MESSAGE("/dev/full not present: the full-disk case cannot be tested here");
    return;
  }
  // A full disk shows only when the file is flushed at close: /dev/full takes the open and the
  // buffered write and fails the flush, as a full disk does for small outputs.
  CHECK_THROWS_WITH_AS(write_file("/dev/full", {"a few bytes"}, "the test"), doctest::Contains("/dev/full: writing the test failed"), Error);
  const std::string P = write_points("full_p.f32", datasets::uniform(3000, 81));
  const std::string O = test::tmp_path("full_");
  // Names that end like the formats they ask for, all pointing at /dev/full.
  for (const char* name : {"full.npy", "full.exr", "full.png", "full.json", "full.idx", "full.raw"}) {
    std::remove((O + name).c_str());
    REQUIRE(symlink("/dev/full", (O + name).c_str()) == 0);
  }
  const std::string knn = "knn --points " + P + " --queries " + P + " --k 4 --quiet ";
  const std::string ok = " --out-ids " + O + "i --out-dist2 " + O + "d";
  const std::vector<std::pair<std::string, std::string>> cases = {
      {knn + "--method kdtree --out-ids " + O + "full.raw --out-dist2 " + O + "d", "full.raw: writing"},
      {knn + "--method kdtree --out-ids " + O + "i --out-dist2 " + O + "full.npy", "full.npy: writing"},
      {knn + "--method kdtree" + ok + " --out-counts " + O + "full.raw", "full.raw: writing"},
      {knn + "--method kdtree" + ok + " --stats " + O + "full.json", "full.json: writing the stats"},
      {knn + "--method blockhash" + ok + " --save-index " + O + "full.idx", "full.idx: writing the block-hash index"},
      {"eval --points " + P + " --queries " + P + " --method blockhash --quiet --stats " + O + "full.json", "full.json: writing the stats"},
      {"render --out " + O + "full.exr --png " + O + "r.png --photons 2000 --size 16x16 --quiet", "full.exr: writing the OpenEXR image failed"},
      {"render --out " + O + "r.exr --png " + O + "full.png --photons 2000 --size 16x16 --quiet", "full.png: writing the PNG failed"},
  };
  for (const auto& [args, expect] : cases) {
    std::string out;
    int rc = test::run_bhcl(args, &out);
    INFO("bhcl " << args << "\n" << out);
    CHECK(rc == 1);
    CHECK(out.find(expect) != std::string::npos);
  }
}

TEST_CASE("cli: outputs never destroy inputs or each other, and misused options are refused before any work") {
  const std::vector<float> pts = datasets::uniform(2000, 83);
  const std::string P = write_points("guard_p.f32", pts);
  const std::string Q = write_points("guard_q.f32", datasets::uniform(50, 84));
  const std::string O = test::tmp_path("guard_");
  const std::string idx = O + "saved.bhi";
  REQUIRE(test::run_bhcl("knn --points " + P + " --queries " + Q + " --method blockhash --out-ids " + O +
                         "i --out-dist2 " + O + "d --save-index " + idx + " --quiet") == 0);
  // Another name for --points: a symlink, and a path through "..".
  const std::string link = O + "link_to_points.f32";
  std::remove(link.c_str());
  REQUIRE(symlink(P.c_str(), link.c_str()) == 0);
  const std::string dotted = test::tmp_path("../tmp/guard_p.f32");
  const std::string knn = "knn --points " + P + " --queries " + Q + " --quiet ";
  struct Case { std::string args, expect; };
  const std::vector<Case> cases = {
      {knn + "--method kdtree --out-ids " + P + " --out-dist2 " + O + "d", "--out-ids " + P + " is the input --points"},
      {knn + "--method kdtree --out-ids " + link + " --out-dist2 " + O + "d", "is the input --points"},
      {knn + "--method kdtree --out-ids " + O + "i --out-dist2 " + Q, "is the input --queries"},
      {knn + "--method kdtree --out-ids " + O + "i --out-dist2 " + O + "d --stats " + dotted, "is the input --points"},
      {knn + "--method kdtree --out-ids " + O + "same --out-dist2 " + O + "same", "--out-dist2 and --out-ids name the same file"},
      {knn + "--method blockhash --out-ids " + O + "i --out-dist2 " + O + "d --load-index " + idx + " --save-index " + idx, "--save-index " + idx + " is the input --load-index"},
      {knn + "--method blockhash --out-ids " + O + "i --out-dist2 " + O + "d --save-index " + P, "is the input --points"},
      {"eval --points " + P + " --queries " + Q + " --method blockhash --stats " + Q, "--stats " + Q + " is the input --queries"},
      // Build options beside --load-index would be ignored: refused.
      {knn + "--method blockhash --out-ids " + O + "i --out-dist2 " + O + "d --load-index " + idx + " --L 3", "--L does not apply with --load-index"},
      {knn + "--method blockhash --out-ids " + O + "i --out-dist2 " + O + "d --load-index " + idx + " --preset paper", "--preset does not apply with --load-index"},
      // Integers are range-checked, never narrowed or wrapped.
      {knn + "--method blockhash --out-ids " + O + "i --out-dist2 " + O + "d --L 4294967297", "--L must be in [1, 64] (or -1), got 4294967297"},
      {knn + "--method flann --out-ids " + O + "i --out-dist2 " + O + "d --threads 4294967296", "--threads must be in [0, 65536]"},
      {knn + "--method blockhash --out-ids " + O + "i --out-dist2 " + O + "d --P -2", "--P must be in [1, 1024] (or -1), got -2"},
      {"demo --N -1 --no-render", "--N must be in [1,"},
      // The renderer's outputs, the derived PNG included.
      {"render --scene " + O + "scene.obj --out " + O + "scene.obj --photons 100 --size 8x8", "--out " + O + "scene.obj is the input --scene"},
      {"render --out " + O + "r.png --photons 100 --size 8x8", "the PNG beside --out and --out name the same file"},
      {"render --out " + O + "r.exr --png " + O + "r.json --stats " + O + "r.json --photons 100 --size 8x8", "--stats and --png name the same file"},
  };
  {
    std::ifstream src(std::string(BHCL_SCENES_DIR) + "/cornell-specular.obj");
    std::ofstream dst(O + "scene.obj");
    dst << src.rdbuf();
  }
  for (const auto& c : cases) {
    std::string out;
    const int rc = test::run_bhcl(c.args, &out);
    INFO("bhcl " << c.args << "\n" << out);
    CHECK(rc == 2);
    CHECK(out.find(c.expect) != std::string::npos);
  }
  // The inputs are intact.
  CHECK(read_points_file(P) == pts);
}
