// Issue 22, classes 2 and 3: every output written atomically (a temporary beside the target,
// renamed when complete; a failed write names the file and the system's reason and leaves the old
// file intact), and the renderer's EXR keeps radiance beyond the half-float range.
#include <dirent.h>
#include <cstring>
#include <memory>
#include <signal.h>
#include <sys/resource.h>
#include <sys/stat.h>

#include <nlohmann/json.hpp>

#include "blockhash_cl/atomic_file.hpp"
#include "test_util.hpp"

#ifdef BHCL_HAVE_RENDER
#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfInputFile.h>

#include "exr_io.hpp"
#include "png_io.hpp"
#endif

namespace bhcl {
namespace {

using test::slurp;

// Temporaries of write_file (".NAME.bhcltmp.*") left in the test folder for `name`.
int leftover_temporaries(const std::string& name) {
  int count = 0;
  DIR* d = opendir(BHCL_TEST_TMP_DIR);
  REQUIRE(d != nullptr);
  const std::string prefix = "." + name + ".bhcltmp.";
  while (dirent* e = readdir(d))
    if (std::string(e->d_name).rfind(prefix, 0) == 0) ++count;
  closedir(d);
  return count;
}

// Runs fn in a forked child whose file-size limit is `limit` bytes (a full disk as the writer
// sees it: write() fails with EFBIG once the limit is reached). Returns the child's message:
// "ok" when fn returned, else the bhcl::Error's text.
template <typename Fn>
std::string under_size_limit(rlim_t limit, Fn fn) {
  const std::string msg = test::tmp_path("limit_msg_" + std::to_string(getpid()) + ".txt");
  const pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    signal(SIGXFSZ, SIG_IGN);
    std::string text = "ok";
    try {
      rlimit rl{limit, limit};
      setrlimit(RLIMIT_FSIZE, &rl);
      fn();
    } catch (const std::exception& e) {
      text = e.what();
    }
    rlimit rl{RLIM_INFINITY, RLIM_INFINITY};
    setrlimit(RLIMIT_FSIZE, &rl);  // lowering is allowed only one way for non-root: ignore failure
    FILE* f = std::fopen(msg.c_str(), "w");
    if (f) {
      std::fputs(text.c_str(), f);
      std::fclose(f);
    }
    _exit(0);
  }
  int status = 0;
  waitpid(pid, &status, 0);
  const std::string text = slurp(msg);
  std::remove(msg.c_str());
  return text;
}

}  // namespace

TEST_CASE("durability: write_file replaces atomically, and a failed write names the reason and keeps the old file") {
  const std::string name = "dur_target.bin";
  const std::string path = test::tmp_path(name);
  write_file(path, {"old contents"}, "the test file");
  REQUIRE(slurp(path) == "old contents");
  chmod(path.c_str(), 0640);
  // A write past the size limit (a full disk): an error naming the file and the reason.
  const std::string big(1 << 20, 'x');
  const std::string msg = under_size_limit(4096, [&] { write_file(path, {big}, "the test file"); });
  INFO(msg);
  CHECK(msg.find(path + ": writing the test file failed") != std::string::npos);
  CHECK(msg.find(std::strerror(EFBIG)) != std::string::npos);
  CHECK(slurp(path) == "old contents");
  CHECK(leftover_temporaries(name) == 0);
  // A successful write replaces the contents and keeps the permissions.
  write_file(path, {"new ", "contents"}, "the test file");
  CHECK(slurp(path) == "new contents");
  struct stat st {};
  REQUIRE(stat(path.c_str(), &st) == 0);
  CHECK((st.st_mode & 0777) == 0640);
  CHECK(leftover_temporaries(name) == 0);
  // Through a symbolic link the file it names is replaced; the link stays a link.
  const std::string link = test::tmp_path("dur_link.bin");
  std::remove(link.c_str());
  REQUIRE(symlink(path.c_str(), link.c_str()) == 0);
  write_file(link, {"via link"}, "the test file");
  CHECK(slurp(path) == "via link");
  struct stat ls {};
  REQUIRE(lstat(link.c_str(), &ls) == 0);
  CHECK(S_ISLNK(ls.st_mode));
  // A folder that does not exist: the reason.
  CHECK_THROWS_WITH_AS(write_file(test::tmp_path("no_such_dir/x.bin"), {"x"}, "the test file"),
                       doctest::Contains("No such file or directory"), Error);
}

TEST_CASE("durability: map_append's stores are the file's bytes, a size limit fails it as a write would, a device has none") {
  const std::string name = "dur_mapped.bin";
  const std::string path = test::tmp_path(name);
  write_file(path, {"old contents"}, "the test file");
  {
    // Destroyed without commit: the temporary removed, the old file intact.
    AtomicFile f(path, "the test file");
    f.write("HDR", 3);
    char* m = static_cast<char*>(f.map_append(4096 * 3));
    REQUIRE(m != nullptr);
    std::memset(m, 'x', 4096 * 3);
  }
  CHECK(slurp(path) == "old contents");
  CHECK(leftover_temporaries(name) == 0);
  {
    // Past the header (not on a page): the mapped bytes follow what was written, and a later
    // write follows them.
    AtomicFile f(path, "the test file");
    f.write("HDR", 3);
    char* m = static_cast<char*>(f.map_append(10));
    REQUIRE(m != nullptr);
    CHECK(f.size() == 13u);
    CHECK(f.map_append(4) == nullptr);  // one mapping a file
    std::memcpy(m, "0123456789", 10);
    f.write("END", 3);
    f.commit();
  }
  CHECK(slurp(path) == "HDR0123456789END");
  CHECK(leftover_temporaries(name) == 0);
  // Under a file-size limit (a full disk): the reservation fails with the write's message.
  const std::string msg = under_size_limit(4096, [&] {
    AtomicFile f(path, "the test file");
    f.map_append(std::size_t(1) << 20);
  });
  INFO(msg);
  CHECK(msg.find(path + ": writing the test file failed") != std::string::npos);
  CHECK(msg.find(std::strerror(EFBIG)) != std::string::npos);
  CHECK(slurp(path) == "HDR0123456789END");
  CHECK(leftover_temporaries(name) == 0);
  // A device is written in place: no mapping, the caller writes.
  AtomicFile dev("/dev/null", "the test file");
  CHECK(dev.map_append(16) == nullptr);
  dev.commit();
}

TEST_CASE("durability: direct (O_DIRECT) writes are the file's bytes, a failed one fails the file, a refusal leaves it to write()") {
  const std::string name = "dur_direct.bin";
  const std::string path = test::tmp_path(name);
  write_file(path, {"old contents"}, "the test file");
  std::string want(3 * 4096 + 100, '\0');
  for (std::size_t i = 0; i < want.size(); ++i) want[i] = static_cast<char>('a' + i % 23);
  void* mem = nullptr;
  REQUIRE(posix_memalign(&mem, 4096, 4 * 4096) == 0);
  std::unique_ptr<char, decltype(&std::free)> buf(static_cast<char*>(mem), &std::free);
  std::memcpy(buf.get(), want.data(), want.size());
  std::size_t align = 0;
  {
    AtomicFile f(path, "the test file");
    align = f.open_direct(want.size());
    INFO("O_DIRECT alignment here: " << align);
    if (align == 0) {
      f.write(want.data(), want.size());  // refused (this file system): the caller writes as before
    } else {
      CHECK(align == 4096u);
      CHECK(f.open_direct(0) == 0u);  // once a file
      f.write_direct(4096, buf.get() + 4096, 3 * 4096);  // out of order: offsets, not appends
      f.write_direct(0, buf.get(), 4096);
      CHECK(f.size() == 4u * 4096);
      f.truncate(want.size());  // the last block's padding cut off
      CHECK(f.size() == want.size());
    }
    f.commit();
  }
  CHECK(slurp(path) == want);
  CHECK(leftover_temporaries(name) == 0);
  {
    AtomicFile f(path, "the test file");  // destroyed without commit: nothing left, the old file kept
    if (f.open_direct(0)) f.write_direct(0, buf.get(), 4096);
  }
  CHECK(slurp(path) == want);
  CHECK(leftover_temporaries(name) == 0);
  if (align) {
    // Under a file-size limit (a full disk): the reservation fails as a write would, and so does a
    // direct write past the limit with nothing reserved.
    std::string msg = under_size_limit(4096, [&] {
      AtomicFile f(path, "the test file");
      f.open_direct(std::size_t(1) << 20);
    });
    INFO(msg);
    CHECK(msg.find(path + ": writing the test file failed (" + std::strerror(EFBIG) + ")") != std::string::npos);
    msg = under_size_limit(4096, [&] {
      AtomicFile f(path, "the test file");
      REQUIRE(f.open_direct(0) == 4096u);
      f.write_direct(0, buf.get(), 4096);
      f.write_direct(4096, buf.get() + 4096, 4096);
      f.commit();
    });
    INFO(msg);
    CHECK(msg.find(path + ": writing the test file failed (" + std::strerror(EFBIG) + ")") != std::string::npos);
    CHECK(slurp(path) == want);
    CHECK(leftover_temporaries(name) == 0);
  }
  // A device: no direct descriptor, written in place.
  AtomicFile dev("/dev/null", "the test file");
  CHECK(dev.open_direct(16) == 0u);
  dev.write("x", 1);
  dev.commit();
}

TEST_CASE("durability: bhcl knn's direct outputs (O_DIRECT) are the bytes of the mapped path, over many slices, raw and NPY") {
  const std::vector<float> pts = datasets::uniform(20000, 95);
  const std::string P = test::write_points("dio_p.f32", pts);
  // The test folder, and /dev/shm where it exists (tmpfs: O_DIRECT refused on older kernels, the
  // mapped path then; taken on newer ones).
  std::vector<std::string> dirs = {test::tmp_path("dio_")};
  struct stat st {};
  if (::stat("/dev/shm", &st) == 0 && S_ISDIR(st.st_mode)) dirs.push_back("/dev/shm/bhcl_dio_" + std::to_string(getpid()) + "_");
  for (const std::string& O : dirs) {
    for (const char* method : {"kdtree", "blockhash"}) {
      for (const char* ext : {".raw", ".npy"}) {
        // k = 7: 28-byte rows, so that slices end inside a block and carry its part to the next.
        auto with = [&](const std::string& tag) {
          return std::string("knn --points ") + P + " --queries " + P + " --method " + method +
                 " --quiet --k 7 --out-ids " + O + "ids" + tag + ext + " --out-dist2 " + O + "d2" + tag + ext +
                 " --out-counts " + O + "c" + tag + ext;
        };
        test::run_bhcl_ok(with("M"), "BHCL_DIRECT_OUTPUT=0");  // the mapped path, one slice
        test::run_bhcl_ok(with("D"), "BHCL_DIRECT_OUTPUT=1 BHCL_SLICE_ROWS=999");  // direct, 21 slices
        test::run_bhcl_ok(with("1"), "BHCL_DIRECT_OUTPUT=1");  // direct, one slice
        // Tapered: 20 slices of 985 (the rest spread evenly), then one of 300 (the write no search
        // hides); the stats' launch count says the taper was taken (one launch a slice here).
        const std::string stats = O + "taper_stats.json";
        test::run_bhcl_ok(with("T") + " --stats " + stats,
                          "BHCL_DIRECT_OUTPUT=1 BHCL_SLICE_ROWS=1000 BHCL_LAST_SLICE_ROWS=300");
        const nlohmann::json js = nlohmann::json::parse(slurp(stats));
        CHECK(js.at("batches").get<int>() == 21);
        // The slice buffers were made beside the reading (the raw queries declare their count by
        // size): the search took all four from there, where the output is direct.
        const int ahead = js.at("stages").at("output_buffers_ahead").get<int>();
        CHECK((ahead == 4 || ahead == 0));
        if (O.rfind("/dev/shm", 0) != 0) CHECK(ahead == 4);
        std::remove(stats.c_str());
        for (const char* f : {"ids", "d2", "c"}) {
          INFO(O << " " << method << " " << f << ext);
          const std::string m = slurp(O + f + "M" + ext);
          CHECK(m.size() > 20000u);
          CHECK(slurp(O + f + "D" + ext) == m);
          CHECK(slurp(O + f + "1" + ext) == m);
          CHECK(slurp(O + f + "T" + ext) == m);
        }
        for (const char* f : {"ids", "d2", "c"})
          for (const char* tag : {"M", "D", "1", "T"}) {
            std::remove((O + f + tag + ext).c_str());
            const std::string file = O + f + tag + ext;
            CHECK(leftover_temporaries(file.substr(file.find_last_of('/') + 1)) == 0);  // (the test folder's)
          }
      }
    }
  }
  // A failed write is still an error: under a file-size limit the direct output's reservation
  // fails before the search, exit 1 with the file and the reason, the old file as it was.
  const std::string O = dirs[0];
  test::run_bhcl_ok("knn --points " + P + " --queries " + P + " --method kdtree --quiet --k 7 --out-ids " + O +
                    "old_ids.raw --out-dist2 " + O + "old_d2.raw");
  const std::string old_ids = slurp(O + "old_ids.raw");
  const std::string cmd = "sh -c 'trap \"\" XFSZ; ulimit -f 128; BHCL_DIRECT_OUTPUT=1 BHCL_SLICE_ROWS=1000 exec \"" +
                          std::string(BHCL_TOOL_PATH) + "\" knn --points " + P + " --queries " + P +
                          " --method kdtree --quiet --k 7 --out-ids " + O + "old_ids.raw --out-dist2 " + O +
                          "old_d2.raw' > " + O + "log.txt 2>&1";
  const int status = std::system(cmd.c_str());
  const std::string log = slurp(O + "log.txt");
  INFO(log);
  CHECK(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 1);
  CHECK(log.find(std::strerror(EFBIG)) != std::string::npos);
  CHECK(slurp(O + "old_ids.raw") == old_ids);
  CHECK(leftover_temporaries("dio_old_ids.raw") == 0);
  CHECK(leftover_temporaries("dio_old_d2.raw") == 0);
}

TEST_CASE("durability: bhcl outputs and --save-index under a full disk keep the old files") {
  const std::vector<float> pts = datasets::uniform(20000, 91);
  const std::string P = test::write_points("dur_p.f32", pts);
  const std::string O = test::tmp_path("dur_");
  const std::string ids = O + "ids.raw", d2 = O + "d2.raw", idx = O + "saved.bhi";
  const std::string base = "knn --points " + P + " --queries " + P + " --k 8 --quiet --out-ids " + ids +
                           " --out-dist2 " + d2;
  REQUIRE(test::run_bhcl(base + " --method blockhash --save-index " + idx) == 0);
  const std::string old_ids = slurp(ids), old_idx = slurp(idx);
  REQUIRE(old_ids.size() == 20000u * 8 * 4);
  // The same run under a 64 KiB file-size limit: every output is larger than that.
  const std::string cmd = "sh -c 'trap \"\" XFSZ; ulimit -f 128; exec \"" + std::string(BHCL_TOOL_PATH) + "\" " +
                          base + " --method blockhash --save-index " + idx + "' > " + O + "log.txt 2>&1";
  const int status = std::system(cmd.c_str());
  const std::string log = slurp(O + "log.txt");
  INFO(log);
  CHECK(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 1);
  // bhcl's own message (not, say, the OpenCL compiler's): the file, what it held, the reason.
  CHECK(log.find(": writing the ") != std::string::npos);
  CHECK(log.find(std::string("failed (") + std::strerror(EFBIG) + ")") != std::string::npos);
  CHECK(slurp(ids) == old_ids);
  CHECK(slurp(idx) == old_idx);
  CHECK(leftover_temporaries("dur_ids.raw") == 0);
  CHECK(leftover_temporaries("dur_saved.bhi") == 0);
  // The kept index still loads and answers.
  CHECK(test::run_bhcl("knn --points " + P + " --queries " + P + " --k 8 --quiet --method blockhash --load-index " +
                       idx + " --out-ids " + O + "ids2.raw --out-dist2 " + O + "d22.raw") == 0);
}

TEST_CASE("durability: kill -9 during --save-index over an existing index leaves the old index whole") {
  // Before: a 0-byte file. The save goes to a temporary renamed over the target, so a kill at any
  // moment leaves the old index (or the new one, the same bytes: the build is deterministic).
  const std::vector<float> pts = datasets::uniform(200000, 95);
  const std::string P = test::write_points("kill_p.f32", pts);
  const std::string idx = test::tmp_path("kill_saved.bhi");
  const std::string args = "knn --points " + P + " --queries " + P + " --k 4 --quiet --method blockhash --out-ids " +
                           test::tmp_path("kill_ids.raw") + " --out-dist2 " + test::tmp_path("kill_d2.raw") +
                           " --save-index " + idx;
  REQUIRE(test::run_bhcl(args) == 0);
  const std::string old_idx = slurp(idx);
  REQUIRE(old_idx.size() > 200000u * 12);
  for (int ms : {100, 300, 600, 1000, 1500, 2500}) {
    const pid_t pid = fork();
    REQUIRE(pid >= 0);
    if (pid == 0) {
      execl("/bin/sh", "sh", "-c", ("exec \"" + std::string(BHCL_TOOL_PATH) + "\" " + args + " > /dev/null 2>&1").c_str(),
            static_cast<char*>(nullptr));
      _exit(127);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(ms));
    kill(pid, SIGKILL);
    int status = 0;
    waitpid(pid, &status, 0);
    INFO("killed after " << ms << " ms");
    CHECK(slurp(idx) == old_idx);
  }
}

// The rows of an NPY file's header: its shape's first number, checked against the file's size.
std::size_t npy_rows_checked(const std::string& bytes, std::size_t item) {
  REQUIRE(bytes.size() >= 10);
  REQUIRE(bytes.compare(0, 6, "\x93NUMPY") == 0);
  const std::size_t hlen = static_cast<unsigned char>(bytes[8]) | (static_cast<unsigned char>(bytes[9]) << 8);
  const std::string h = bytes.substr(10, hlen);
  const std::size_t at = h.find("'shape': (");
  REQUIRE(at != std::string::npos);
  const std::size_t rows = std::stoull(h.substr(at + 10));
  CHECK(bytes.size() == 10 + hlen + rows * item);
  CHECK((10 + hlen) % 64 == 0);
  return rows;
}

TEST_CASE("durability: bhcl knn's NPY outputs (the header stored through the mapping) are the raw rows behind a valid header, for 1 query and past 2 MiB") {
  const std::vector<float> pts = datasets::uniform(20000, 94);
  const std::string P = test::write_points("hd_p.f32", pts);
  const std::string Q1 = test::write_points("hd_q1.f32", std::vector<float>(pts.begin(), pts.begin() + 3));
  const std::string O = test::tmp_path("hd_");
  // k = 32 over 20000 queries: 2.56 MB a file (advised MADV_HUGEPAGE); one query: 128 bytes.
  for (const auto& [Q, n] : {std::pair<std::string, std::size_t>{P, 20000}, {Q1, 1}}) {
    for (const char* ext : {".raw", ".npy"}) {
      const std::string cmd = "knn --points " + P + " --queries " + Q + " --method kdtree --quiet --k 32 --out-ids " +
                              O + "ids" + ext + " --out-dist2 " + O + "d2" + ext + " --out-counts " + O + "c" + ext;
      REQUIRE(test::run_bhcl(cmd) == 0);
    }
    for (const auto& [f, item] : {std::pair<const char*, std::size_t>{"ids", 128}, {"d2", 128}, {"c", 4}}) {
      INFO(f << " n=" << n);
      const std::string npy = slurp(O + f + ".npy"), raw = slurp(O + f + ".raw");
      REQUIRE(npy_rows_checked(npy, item) == n);
      CHECK(raw.size() == n * item);
      CHECK(npy.compare(npy.size() - raw.size(), raw.size(), raw) == 0);
    }
  }
}

TEST_CASE("durability: bhcl knn writes its results in slices as they finish, the same bytes as one slice, and a failure partway leaves no partial output") {
  const std::vector<float> pts = datasets::uniform(20000, 93);
  const std::string P = test::write_points("sl_p.f32", pts);
  const std::string O = test::tmp_path("sl_");
  const std::string common = "knn --points " + P + " --queries " + P + " --method kdtree --quiet";
  // kNN: one slice against 20 (BHCL_SLICE_ROWS = 1000), raw and NPY.
  for (const char* ext : {".raw", ".npy"}) {
    const std::string knn = common + " --k 8 --out-ids " + O + "ids%" + ext + " --out-dist2 " + O + "d2%" + ext +
                            " --out-counts " + O + "c%" + ext;
    auto with = [&](const std::string& tag) {
      std::string c = knn;
      for (std::size_t at; (at = c.find('%')) != std::string::npos;) c.replace(at, 1, tag);
      return c;
    };
    REQUIRE(test::run_bhcl(with("1")) == 0);
    REQUIRE(test::run_bhcl(with("N"), nullptr, "BHCL_SLICE_ROWS=1000") == 0);
    for (const char* f : {"ids", "d2", "c"}) {
      const std::string one = slurp(O + f + "1" + ext), many = slurp(O + f + "N" + ext);
      INFO(f << ext);
      CHECK(one.size() > 0);
      CHECK(one == many);
    }
    if (std::string(ext) == ".npy") CHECK(npy_rows_checked(slurp(O + "idsN.npy"), 32) == 20000u);
  }
  // Radius: the FAISS layout, one slice against 20; the NPY header of the ids (their number known
  // only at the end) rewritten with the true length.
  for (const char* ext : {".raw", ".npy"}) {
    auto with = [&](const std::string& tag) {
      return common + " --radius 0.05 --out-offsets " + O + "ro" + tag + ext + " --out-ids " + O + "ri" + tag + ext +
             " --out-dist2 " + O + "rd" + tag + ext + " --out-counts " + O + "rc" + tag + ext;
    };
    REQUIRE(test::run_bhcl(with("1")) == 0);
    REQUIRE(test::run_bhcl(with("N"), nullptr, "BHCL_SLICE_ROWS=1000") == 0);
    for (const char* f : {"ro", "ri", "rd", "rc"}) {
      INFO(f << ext);
      CHECK(slurp(O + f + "1" + ext) == slurp(O + f + "N" + ext));
    }
    if (std::string(ext) == ".npy") {
      const std::string offs = slurp(O + "roN.npy");
      REQUIRE(npy_rows_checked(offs, 8) == 20001u);
      std::int64_t total = 0;
      std::memcpy(&total, offs.data() + offs.size() - 8, 8);
      CHECK(total > 20000);
      CHECK(npy_rows_checked(slurp(O + "riN.npy"), 4) == static_cast<std::size_t>(total));
      CHECK(npy_rows_checked(slurp(O + "rdN.npy"), 4) == static_cast<std::size_t>(total));
    }
  }
#if BHCL_HAVE_FLANN
  // A failure partway (the file-size limit reached after a few slices were written: a full disk
  // as the writer sees it): exit 1 with the file and the system's reason, the old files as they
  // were, no temporary. Before, --out-ids kept a partial file that read as valid rows. (FLANN, a
  // host method: PoCL's compiler also writes files at run time, and fails first under the limit.)
  const std::string old_ids = slurp(O + "ids1.raw");
  const std::string cmd = "sh -c 'trap \"\" XFSZ; ulimit -f 128; BHCL_SLICE_ROWS=1000 exec \"" +
                          std::string(BHCL_TOOL_PATH) + "\" knn --points " + P + " --queries " + P +
                          " --method flann --quiet --k 8 --out-ids " + O + "ids1.raw --out-dist2 " +
                          O + "d21.raw' > " + O + "log.txt 2>&1";
  const int status = std::system(cmd.c_str());
  const std::string log = slurp(O + "log.txt");
  INFO(log);
  CHECK(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 1);
  CHECK(log.find(O + "ids1.raw: writing the raw array failed (" + std::strerror(EFBIG) + ")") != std::string::npos);
  CHECK(slurp(O + "ids1.raw") == old_ids);
  CHECK(leftover_temporaries("sl_ids1.raw") == 0);
  CHECK(leftover_temporaries("sl_d21.raw") == 0);
#endif
}

#ifdef BHCL_HAVE_RENDER
TEST_CASE("durability: EXR and PNG writers keep the old image when the write fails") {
  render::Image img(64, 64);
  for (std::size_t i = 0; i < img.rgb.size(); ++i) img.rgb[i] = float(i % 97) / 97.0f;
  const std::string exr = test::tmp_path("dur_img.exr"), png = test::tmp_path("dur_img.png");
  render::write_exr(exr, img);
  render::write_png(png, render::tonemap(img, 1.0f));
  const std::string old_exr = slurp(exr), old_png = slurp(png);
  REQUIRE(!old_exr.empty());
  REQUIRE(!old_png.empty());
  render::Image big(512, 512);
  for (std::size_t i = 0; i < big.rgb.size(); ++i) big.rgb[i] = float((i * 7919) % 1013) / 13.0f;
  std::string msg = under_size_limit(1024, [&] { render::write_exr(exr, big); });
  CHECK(msg.find(exr + ": writing the OpenEXR image failed") != std::string::npos);
  CHECK(msg.find(std::strerror(EFBIG)) != std::string::npos);
  msg = under_size_limit(1024, [&] { render::write_png(png, render::tonemap(big, 1.0f)); });
  CHECK(msg.find(png + ": writing the PNG failed") != std::string::npos);
  CHECK(slurp(exr) == old_exr);
  CHECK(slurp(png) == old_png);
  CHECK(leftover_temporaries("dur_img.exr") == 0);
  CHECK(leftover_temporaries("dur_img.png") == 0);
}

TEST_CASE("renderer: radiance beyond the half-float range is written as float32 EXR, never +inf") {
  auto channel_type = [](const std::string& path) {
    Imf::InputFile f(path.c_str());
    return f.header().channels().findChannel("R")->type;
  };
  render::Image img(4, 4);
  for (auto& v : img.rgb) v = 0.5f;
  const std::string path = test::tmp_path("bright.exr");
  // In range: half channels, as before.
  render::write_exr(path, img);
  CHECK(channel_type(path) == Imf::HALF);
  // An emitter seen directly at 1e6 (beyond 65504): float32 channels, the value kept.
  img.rgb[0] = 1e6f;
  img.rgb[5] = 3e38f;
  CHECK(render::needs_float_exr(img));
  render::write_exr(path, img);
  CHECK(channel_type(path) == Imf::FLOAT);
  render::Image back = render::read_exr(path);
  CHECK(back.rgb[0] == 1e6f);
  CHECK(back.rgb[5] == 3e38f);
  for (float v : back.rgb) CHECK(std::isfinite(v));
  // Half asked for explicitly: +inf, with a warning (kept for callers that want small files).
  render::write_exr(path, img, render::ExrPixels::Half);
  CHECK(channel_type(path) == Imf::HALF);
  CHECK(std::isinf(render::read_exr(path).rgb[0]));
}
#endif

}  // namespace bhcl
