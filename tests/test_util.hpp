// The test helper module (test_util.cpp): the runtime, generated data, result checks, running bhcl.
// Every test file includes it instead of declaring fixtures of its own.
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <future>
#include <thread>
#include <limits>
#include <memory>
#include <array>
#include <set>
#include <sstream>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>
#include <string>
#include <vector>

#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/cornell_box.hpp"

namespace bhcl::test {

inline std::shared_ptr<Runtime> runtime() { return default_runtime(); }

// Search parameters asking for the k nearest (the rest the defaults).
inline SearchParams knn_params(int k) {
  SearchParams p;
  p.k = k;
  return p;
}

// A named point set with its queries.
struct PointSet {
  std::string name;
  std::vector<float> points, queries;
};
// A named case of a test's own: points and queries.
struct NamedCase {
  const char* name;
  std::vector<float> pts, qs;
};
// Queries for a point set: uniform over its box grown by 10 %, exact copies of points (distance
// 0 ties, duplicates), and points moved by a tiny jitter (near-ties); `each` of every kind.
std::vector<float> queries_for(const std::vector<float>& pts, std::uint64_t seed, std::size_t each = 100);
// The point sets every exact method is checked on: uniform, clustered, duplicates, identical,
// flat, collinear, offset (names as listed).
std::vector<PointSet> exact_point_sets();
// A radius that cuts many rows short: the median distance to the 8th neighbour.
float cutting_radius(const PointSet& s);
// Bit-exact equality of two results (ids, counts, distances including +inf), naming the first
// differing entry.
void require_identical(const KnnResult& r, const KnnResult& ref, const std::string& what);
// Answers `qs` through the buffer-level call (enqueue_query on the runtime's queue, caller-owned
// buffers, examined too when p.count_examined) and reads every row back.
KnnResult buffer_query(const Index& index, const std::vector<float>& qs, const SearchParams& p);
// An exact index on a point set equals the float reference for k in {1, 8, 10, 50, 100, 256},
// with and without the cutting radius.
void check_index_on_set(const Index& index, const PointSet& s);

// Every row valid under the contract: ids in range and unique, distances sorted by (d2, id),
// each distance equal to the kernel arithmetic's distance of its id, within max_radius, the
// tail -1/+inf, count consistent.
inline void check_contract(const KnnResult& r, const float* points, std::size_t N,
                           const float* queries, const SearchParams& p) {
  const float r2 = std::isinf(p.max_radius) ? INFINITY : p.max_radius * p.max_radius;
  for (std::size_t q = 0; q < r.n; ++q) {
    int c = r.counts[q];
    REQUIRE(c >= 0);
    REQUIRE(c <= r.k);
    std::set<int> seen;
    for (int j = 0; j < r.k; ++j) {
      int id = r.id(q, j);
      float d = r.d2(q, j);
      if (j >= c) {
        REQUIRE(id == -1);
        REQUIRE(std::isinf(d));
        continue;
      }
      REQUIRE(id >= 0);
      REQUIRE(static_cast<std::size_t>(id) < N);
      REQUIRE(seen.insert(id).second);
      // The kernels' float arithmetic; beyond the float range (extreme scales) +inf, ordered by
      // the true distance.
      const float expect = reference::dist2_float(points + 3 * id, queries + 3 * q);
      const bool beyond = std::isinf(expect) || (expect != 0 && expect < 1e-30f);
      if (!beyond) REQUIRE(d == expect);
      REQUIRE(d <= r2);
      if (j > 0) {
        float pd = r.d2(q, j - 1);
        REQUIRE(pd <= d);
        if (pd == d && r.id(q, j - 1) > id) {
          // Only where scaled-back distances collapse (beyond the float range: +inf, or below
          // the normal range) may equal entries leave index order; they keep true-distance order.
          REQUIRE((std::isinf(d) || d < std::numeric_limits<float>::min()));
          REQUIRE(reference::dist2_double(points, r.id(q, j - 1), queries + 3 * q) <=
                  reference::dist2_double(points, id, queries + 3 * q));
        }
      }
    }
  }
}

// An exact result against the double-precision reference: same counts; at each rank the same
// id, or an id whose true distance ties the reference's within float rounding (relative 4e-7).
inline void check_exact_vs_double(const KnnResult& r, const float* points, std::size_t N,
                                  const float* queries, std::size_t n, const SearchParams& p) {
  check_contract(r, points, N, queries, p);
  KnnResult truth = reference::knn_double(points, N, queries, n, p);
  std::size_t swapped = 0;
  for (std::size_t q = 0; q < n; ++q) {
    REQUIRE(r.counts[q] == truth.counts[q]);
    for (int j = 0; j < r.counts[q]; ++j) {
      int a = r.id(q, j), b = truth.id(q, j);
      if (a == b) continue;
      double da = reference::dist2_double(points, a, queries + 3 * q);
      double db = reference::dist2_double(points, b, queries + 3 * q);
      INFO("query " << q << " rank " << j << " id " << a << " (d2 " << da << ") vs reference id "
                    << b << " (d2 " << db << ")");
      REQUIRE(std::abs(da - db) <= 4e-7 * std::max(da, db));
      ++swapped;
    }
  }
  MESSAGE("ranks differing from the double reference only by float-rounding ties: " << swapped);
}

// Runs `bhcl ARGS` (with `env`, e.g. "POCL_MAX_PTHREAD_COUNT=1", set for it), capturing
// stdout+stderr. Returns the exit status.
inline int run_bhcl(const std::string& args, std::string* output = nullptr, const std::string& env = "") {
  // The pid keeps parallel test processes (ctest -j) apart: std::rand() unseeded gives every
  // process the same sequence.
  std::string log = std::string(BHCL_TEST_TMP_DIR) + "/bhcl_out_" + std::to_string(getpid()) + "_" +
                    std::to_string(std::rand()) + ".txt";
  std::string cmd = (env.empty() ? std::string() : "env " + env + " ") + "\"" + BHCL_TOOL_PATH +
                    "\" " + args + " > \"" + log + "\" 2>&1";
  int status = std::system(cmd.c_str());
  std::ifstream in(log);
  std::stringstream ss;
  ss << in.rdbuf();
  if (output) *output = ss.str();
  std::remove(log.c_str());
  if (status == -1) return -1;
  return WIFEXITED(status) ? WEXITSTATUS(status) : 128;
}

// Runs `bhcl ARGS` as run_bhcl does and requires it to succeed (the output shown when it does
// not); returns the output.
inline std::string run_bhcl_ok(const std::string& args, const std::string& env = "") {
  std::string out;
  const int rc = run_bhcl(args, &out, env);
  INFO(out);
  REQUIRE(rc == 0);
  return out;
}

// The message of the bhcl::Error that f() throws; a test failure when it throws none.
template <typename F>
std::string error_of(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  FAIL("no bhcl::Error thrown");
  return {};
}

// The contract's exact radius answer: every point with dist2_float <= r2[q] (r2: one squared
// radius per query, or one for all), each slice sorted by (distance, id).
RadiusResult reference_radius_slices(const std::vector<float>& pts, const std::vector<float>& qs,
                                     const std::vector<float>& r2);
// a and b slice for slice: the same offsets, counts and ids, the same distances to the bit.
void require_same_slices(const RadiusResult& a, const RadiusResult& b, const std::string& what);

// A file of the real point sets (bunny, dragon, autzen) in the folder BHCL_DATA_DIR names, ""
// when the variable is unset or the file absent (a clone holds no data sets).
inline std::string data_file(const std::string& name) {
  const char* dir = std::getenv("BHCL_DATA_DIR");
  if (!dir || !*dir) return {};
  const std::string path = std::string(dir) + "/" + name;
  return std::ifstream(path).good() ? path : std::string();
}
// Reports the running test as skipped, with why: ctest marks a test whose output holds the tag
// skipped, not passed (SKIP_REGULAR_EXPRESSION in tests/CMakeLists.txt). Return after it.
inline void report_skip(const std::string& why) {
  std::printf("bhcl-skip: %s\n", why.c_str());
  std::fflush(stdout);
}

inline std::string tmp_path(const std::string& name) {
  return std::string(BHCL_TEST_TMP_DIR) + "/" + name;
}

// Writes xyz as a raw float32 point file in the test folder; returns its path.
inline std::string write_points(const std::string& name, const std::vector<float>& xyz) {
  std::string path = tmp_path(name);
  write_points_file(path, xyz);
  return path;
}

// A file's bytes (empty when it cannot be read), and a file written with `data`.
// A bhcl run's inputs: N uniform points and n uniform queries (datasets::uniform with the seeds)
// written to the point files STEM_p.f32 and STEM_q.f32 (P, Q).
struct CliInputs {
  std::vector<float> pts, qs;
  std::string P, Q;
};
inline CliInputs cli_inputs(const std::string& stem, std::size_t N, std::uint64_t seed, std::size_t n,
                            std::uint64_t query_seed) {
  CliInputs in{datasets::uniform(N, seed), datasets::uniform(n, query_seed), "", ""};
  in.P = write_points(stem + "_p.f32", in.pts);
  in.Q = write_points(stem + "_q.f32", in.qs);
  return in;
}

inline std::string slurp(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}
inline void spit(const std::string& path, const std::string& data) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(data.data(), static_cast<std::streamsize>(data.size()));
}

template <typename T>
std::vector<T> read_raw(const std::string& path) {
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  REQUIRE(in.good());
  std::size_t size = static_cast<std::size_t>(in.tellg());
  std::vector<T> v(size / sizeof(T));
  in.seekg(0);
  in.read(reinterpret_cast<char*>(v.data()), static_cast<std::streamsize>(size));
  return v;
}

// Runs fn in a forked child whose address space may grow by at most `extra` bytes; returns the
// child's exit status: 0 fn returned, 1 it threw bhcl::Error, 2 std::bad_alloc, 3 anything else.
template <typename Fn>
int with_memory_limit(std::size_t extra, Fn fn) {
  const pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    std::ifstream statm("/proc/self/statm");
    std::size_t pages = 0;
    statm >> pages;
    const rlim_t limit = rlim_t(pages) * rlim_t(sysconf(_SC_PAGESIZE)) + extra;
    struct rlimit rl {limit, limit};
    setrlimit(RLIMIT_AS, &rl);
    try {
      fn();
    } catch (const Error&) {
      _exit(1);
    } catch (const std::bad_alloc&) {
      _exit(2);
    } catch (...) {
      _exit(3);
    }
    _exit(0);
  }
  int status = 0;
  REQUIRE(waitpid(pid, &status, 0) == pid);
  return WIFEXITED(status) ? WEXITSTATUS(status) : 100 + WTERMSIG(status);
}

}  // namespace bhcl::test
