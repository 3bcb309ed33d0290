// far_bench: every method on the workloads where the query is not among the points (issue "Fast
// wherever the query is"): queries over the box of uniform, Cornell and Autzen, a distance field
// (k = 1 at every voxel of a grid padded around a scan), ICP (k = 1 from a moved and turned copy of
// a scan), two tight clusters queried between them, 2M points on a line or a plane queried off
// them; and the same sets queried on the data, where the grid already wins.
//
// One process, `--rounds` interleaved rounds (every method once per round on the same batch, host
// arrays, sorting and transfers included); per row the median over rounds of t_kdtree / t_method
// (vs_kd > 1: faster than the kd-tree kernel), and likewise against FLANN and brute force; the
// first call (kernel compile) timed apart. Accuracy of each method against the kd-tree's exact
// rows: recall@k, false negatives, max and mean dilation, and the rows not bit-identical.
// "rings" is block hashing's grid searched by rings alone (-DBHCL_GRID_FINE_RINGS=0xffffffff: the
// search before the occupancy pyramid), for a before/after in the same process.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "bench_cli.hpp"
#include "bench_util.hpp"
#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"

using namespace bhcl;

namespace {

using bench::now_s;

// Every voxel centre of a res^3 grid over the points' box padded by `pad` of its extent per side.
std::vector<float> field_queries(const std::vector<float>& pts, int res, float pad) {
  const bench::Bounds b(pts);
  std::vector<float> q;
  q.reserve(3 * std::size_t(res) * res * res);
  float lo[3], step[3];
  for (int d = 0; d < 3; ++d) {
    const float e = b.hi[d] - b.lo[d];
    lo[d] = b.lo[d] - pad * e;
    step[d] = e * (1 + 2 * pad) / float(res);
  }
  for (int z = 0; z < res; ++z)
    for (int y = 0; y < res; ++y)
      for (int x = 0; x < res; ++x) {
        q.push_back(lo[0] + (x + 0.5f) * step[0]);
        q.push_back(lo[1] + (y + 0.5f) * step[1]);
        q.push_back(lo[2] + (z + 0.5f) * step[2]);
      }
  return q;
}

// The scan turned by `deg` about z through its centroid and moved by `shift` of its diagonal.
std::vector<float> icp_queries(const std::vector<float>& pts, float deg, float shift) {
  const bench::Bounds b(pts);
  double c[3] = {0, 0, 0};
  const std::size_t n = pts.size() / 3;
  for (std::size_t i = 0; i < n; ++i)
    for (int d = 0; d < 3; ++d) c[d] += pts[3 * i + d];
  for (double& v : c) v /= double(n);
  const double a = deg * M_PI / 180, ca = std::cos(a), sa = std::sin(a), t = shift * b.diag() / std::sqrt(3.0);
  std::vector<float> q(pts.size());
  for (std::size_t i = 0; i < n; ++i) {
    const double x = pts[3 * i] - c[0], y = pts[3 * i + 1] - c[1], z = pts[3 * i + 2] - c[2];
    q[3 * i] = float(ca * x - sa * y + c[0] + t);
    q[3 * i + 1] = float(sa * x + ca * y + c[1] + t);
    q[3 * i + 2] = float(z + c[2] + t);
  }
  return q;
}

// Two Gaussian clusters (sigma 0.01) at x = 0 and x = 1; queries between them, x in [0.1, 0.9].
void two_clusters(std::size_t n, std::size_t nq, std::vector<float>& pts, std::vector<float>& q) {
  std::mt19937_64 rng(11);
  std::normal_distribution<float> g(0.0f, 0.01f);
  pts.resize(3 * n);
  for (std::size_t i = 0; i < n; ++i) {
    pts[3 * i] = g(rng) + (i % 2 ? 1.0f : 0.0f);
    pts[3 * i + 1] = g(rng);
    pts[3 * i + 2] = g(rng);
  }
  std::uniform_real_distribution<float> ux(0.1f, 0.9f), uyz(-0.05f, 0.05f);
  q.resize(3 * nq);
  for (std::size_t i = 0; i < nq; ++i) q[3 * i] = ux(rng), q[3 * i + 1] = uyz(rng), q[3 * i + 2] = uyz(rng);
}

// n points on the segment x in [0, 1] (dims 1) or the unit square z = 0 (dims 2); queries at a
// distance of 0.01 to 0.5 off it.
void flat_set(int dims, std::size_t n, std::size_t nq, std::vector<float>& pts, std::vector<float>& q) {
  std::mt19937_64 rng(12);
  std::uniform_real_distribution<float> u(0.0f, 1.0f), off(0.01f, 0.5f);
  pts.assign(3 * n, 0.0f);
  for (std::size_t i = 0; i < n; ++i) {
    pts[3 * i] = u(rng);
    if (dims == 2) pts[3 * i + 1] = u(rng);
  }
  q.resize(3 * nq);
  for (std::size_t i = 0; i < nq; ++i) {
    q[3 * i] = u(rng);
    q[3 * i + 1] = dims == 2 ? u(rng) : off(rng);
    q[3 * i + 2] = off(rng);
  }
}

struct Workload {
  std::string name;
  std::vector<float> pts, q;
};

struct Method {
  std::string name;   // as printed
  std::string index;  // make_index's name
  std::string defines;
};

// Rows of a and b identical (ids and squared distances bit for bit).
std::size_t rows_differing(const KnnResult& a, const KnnResult& b, int k) {
  std::size_t bad = 0;
  for (std::size_t r = 0; r < a.counts.size(); ++r)
    for (int j = 0; j < k; ++j) {
      const std::size_t o = r * std::size_t(k) + std::size_t(j);
      if (a.ids[o] != b.ids[o] || !(a.dist2[o] == b.dist2[o] || (std::isinf(a.dist2[o]) && std::isinf(b.dist2[o])))) {
        ++bad;
        break;
      }
    }
  return bad;
}

struct Options {
  std::vector<std::string> sets = {"uniform-on", "uniform-box", "cornell-on", "cornell-box", "autzen-on", "autzen-box",
                                   "field-bunny", "field-dragon", "icp-bunny", "icp-dragon", "clusters", "line", "plane"};
  std::vector<std::string> methods = {"blockhash", "rings", "kdtree", "flann", "bruteforce"};
  std::string data_dir, device, csv;
  std::size_t N = 1000000, n_queries = 20000, n_far = 2000, flat_n = 2000000;
  std::size_t brute_limit = 4000000000ull;
  int res = 64, rounds = 5;
  std::vector<int> ks = {1, 10, 50};
};

void declare(bench::BenchCli& cli, Options& o) {
  cli.names("sets", o.sets,
            "workloads: {uniform,cornell,autzen}-{on,box}, field-{bunny,dragon}, icp-{bunny,dragon}, clusters, line, "
            "plane");
  cli.names("methods", o.methods, "blockhash, rings (the grid by rings alone: the search before), kdtree, flann, bruteforce, "
            "bh:DEFINES (blockhash with these kernel defines)");
  cli.integer("N", o.N, "points of uniform, cornell and autzen", 1000, 2147483646.0);
  cli.queries(o.n_queries);
  cli.integer("far-queries", o.n_far, "queries of clusters, line and plane", 1, 1e9);
  cli.integer("flat-N", o.flat_n, "points of line and plane (clusters: 60000)", 1000, 2147483646.0);
  cli.integer("res", o.res, "distance fields: voxels per axis", 4, 1024);
  cli.integer("brute-limit", o.brute_limit, "brute force only where points x queries is at most this", 0, 9e18);
  cli.ks(o.ks);
  cli.integer("rounds", o.rounds, "interleaved rounds (medians of per-round ratios)", 1, 1000);
  cli.csv(o.csv);
  cli.data_dir(o.data_dir);
  cli.device(o.device);
}

std::vector<Method> parse_methods(const bench::BenchCli& cli, const std::vector<std::string>& methods) {
  std::vector<Method> ms;
  for (const std::string& m : methods) {
    if (m == "rings") ms.push_back({m, "blockhash", "-DBHCL_GRID_FINE_RINGS=0xffffffff"});
    else if (m.rfind("bh:", 0) == 0) ms.push_back({m, "blockhash", m.substr(3)});  // blockhash with these defines
    else if (m == "blockhash" || m == "kdtree" || m == "flann" || m == "bruteforce") ms.push_back({m, m, ""});
    else cli.fail("--methods: unknown method '" + m + "'");
  }
  return ms;
}

// The points and queries of workload `set`, and its k (distance fields and ICP: k = 1 only).
// False when its data file is absent.
bool load_workload(const bench::BenchCli& cli, const Options& o, const std::string& set, Workload& w,
                   std::vector<int>& set_ks) {
  w = Workload{set, {}, {}};
  set_ks = o.ks;
  const auto dash = set.find('-');
  const std::string base = dash == std::string::npos ? set : set.substr(0, dash);
  const std::string kind = dash == std::string::npos ? "" : set.substr(dash + 1);
  if (base == "field" || base == "icp") {
    std::vector<float> on;
    if (!bench::load_set(o.data_dir, kind, 0, 1, w.pts, on)) return false;
    w.q = base == "field" ? field_queries(w.pts, o.res, 0.1f) : icp_queries(w.pts, 5.0f, 0.02f);
    set_ks = {1};
  } else if (set == "clusters") {
    two_clusters(60000, o.n_far, w.pts, w.q);
  } else if (set == "line" || set == "plane") {
    flat_set(set == "line" ? 1 : 2, o.flat_n, o.n_far, w.pts, w.q);
  } else if (kind == "on" || kind == "box") {
    std::vector<float> on;
    if (!bench::load_set(o.data_dir, base, o.N, o.n_queries, w.pts, on)) return false;
    w.q = kind == "on" ? on : bench::box_queries(w.pts, o.n_queries, 7);
  } else {
    cli.fail("--sets: unknown workload '" + set + "'");
  }
  return true;
}

// The indexes of one workload, built once; consecutive blockhash methods share one.
struct Indexes {
  std::vector<std::unique_ptr<Index>> idx;
  std::vector<bool> run;  // false: brute force past --brute-limit
  Index& of(std::size_t m) const {
    while (!idx[m]) --m;
    return *idx[m];
  }
};

Indexes build_indexes(const Options& o, const std::vector<Method>& ms, const std::shared_ptr<Runtime>& rt,
                      const Workload& w) {
  const std::size_t np = w.pts.size() / 3, nq = w.q.size() / 3;
  Indexes ix{std::vector<std::unique_ptr<Index>>(ms.size()), std::vector<bool>(ms.size(), true)};
  for (std::size_t m = 0; m < ms.size(); ++m) {
    if (ms[m].index == "bruteforce" && double(np) * double(nq) > double(o.brute_limit)) {
      ix.run[m] = false;
      continue;
    }
    if (m > 0 && ms[m].index == "blockhash" && ms[m - 1].index == "blockhash") continue;  // shares the index
    ix.idx[m] = make_index(ms[m].index, rt, w.pts.data(), np);
  }
  return ix;
}

// One k on a workload: each method's first call (kept: its rows), then `rounds` interleaved timed
// calls, the order rotated by one method each round.
struct Timings {
  std::vector<SearchParams> p;
  std::vector<KnnResult> res;
  std::vector<double> first;
  std::vector<std::vector<double>> t;
};

Timings time_methods(const Options& o, const std::vector<Method>& ms, const Indexes& ix, const Workload& w, int k) {
  const std::size_t nq = w.q.size() / 3;
  Timings tm{std::vector<SearchParams>(ms.size()), std::vector<KnnResult>(ms.size()),
             std::vector<double>(ms.size(), 0), std::vector<std::vector<double>>(ms.size())};
  for (std::size_t m = 0; m < ms.size(); ++m) {
    tm.p[m].k = k;
    tm.p[m].kernel_defines = ms[m].defines;
    if (!ix.run[m]) continue;
    const double t0 = now_s();
    ix.of(m).query(w.q.data(), nq, tm.p[m], tm.res[m]);
    tm.first[m] = now_s() - t0;
  }
  // Each round starts one method later: in a fixed order the first method always ran right after
  // the last one's host threads (FLANN), so any cost of that position (the device threads'
  // wake-up on the short on-data calls, 10-30 ms) fell on it alone.
  for (int r = 0; r < o.rounds; ++r)
    for (std::size_t i = 0; i < ms.size(); ++i) {
      const std::size_t m = (i + std::size_t(r)) % ms.size();
      if (!ix.run[m]) continue;
      KnnResult tmp;
      const double t0 = now_s();
      ix.of(m).query(w.q.data(), nq, tm.p[m], tmp);
      tm.t[m].push_back(now_s() - t0);
    }
  return tm;
}

// Block hashing: the mean points examined per query (NaN for the other methods).
double mean_examined(const Method& method, const Index& index, const Workload& w, const SearchParams& p) {
  if (method.index != "blockhash") return NAN;
  const std::size_t nq = w.q.size() / 3;
  SearchParams pe = p;
  pe.count_examined = true;
  KnnResult re;
  index.query(w.q.data(), nq, pe, re);
  double s = 0;
  for (std::int32_t e : re.examined) s += e;
  return s / double(std::max<std::size_t>(1, nq));
}

// The rows of one k: each method's times, ratios to the others and accuracy against the kd-tree.
void report_k(const Options& o, const std::vector<Method>& ms, const Indexes& ix, const Workload& w, int k,
              const Timings& tm, std::FILE* out) {
  const std::size_t np = w.pts.size() / 3, nq = w.q.size() / 3;
  auto ratio = [&](const std::string& other, std::size_t m) {
    for (std::size_t b = 0; b < ms.size(); ++b)
      if (ms[b].name == other && ix.run[b]) {
        std::vector<double> rs;
        for (int r = 0; r < o.rounds; ++r) rs.push_back(tm.t[b][r] / tm.t[m][r]);
        return bench::median(rs);
      }
    return double(NAN);
  };
  std::size_t truth = ms.size();
  for (std::size_t m = 0; m < ms.size(); ++m)
    if (ms[m].name == "kdtree") truth = m;
  for (std::size_t m = 0; m < ms.size(); ++m) {
    if (!ix.run[m]) continue;
    Accuracy acc;
    std::size_t diff = 0;
    if (truth < ms.size()) {
      acc = evaluate_accuracy(tm.res[m], tm.res[truth]);
      diff = rows_differing(tm.res[m], tm.res[truth], k);
    }
    const double mean_ex = mean_examined(ms[m], ix.of(m), w, tm.p[m]);
    const double t = bench::median(tm.t[m]), vkd = ratio("kdtree", m), vfl = ratio("flann", m),
                 vbf = ratio("bruteforce", m);
    const char* set = w.name.c_str();
    std::printf("%-13s %3d %-10s %8.3f %8.3f %9.5f %7.2f %8.2f %7.2f %7.4f %7.4f %8.4f %7.4f %8zu %9.1f\n",
                set, k, ms[m].name.c_str(), ix.of(m).build_seconds(), tm.first[m], t, vkd, vfl, vbf,
                acc.recall, acc.false_negative_rate, acc.max_dilation, acc.mean_dilation, diff, mean_ex);
    std::fflush(stdout);
    if (out)
      std::fprintf(out, "%s,%zu,%zu,%d,%s,%.5f,%.5f,%.6f,%.4f,%.4f,%.4f,%.5f,%.5f,%.5f,%.5f,%zu,%.2f\n", set,
                   np, nq, k, ms[m].name.c_str(), ix.of(m).build_seconds(), tm.first[m], t, vkd, vfl, vbf,
                   acc.recall, acc.false_negative_rate, acc.max_dilation, acc.mean_dilation, diff, mean_ex);
  }
}

}  // namespace

int main(int argc, char** argv) {
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
#endif
  Options o;
  bench::BenchCli cli("far_bench",
                      "every method where the query is not among the points (over the box, distance fields, ICP, "
                      "two clusters, a line, a plane) and on the data: median per-round speed ratios and accuracy");
  declare(cli, o);
  cli.parse(argc, argv);
  const std::vector<Method> ms = parse_methods(cli, o.methods);
  try {
    auto rt = std::make_shared<Runtime>(o.device);
    bench::print_run_header(argc, argv, *rt);
    std::printf("# vs_kd, vs_flann, vs_bf: median over %d rounds of t_other / t_method (> 1: this method faster); "
                "t_s: median wall of a call; first_s: the first call (compiles); accuracy against the kd-tree's "
                "exact rows; rows_diff: rows not bit-identical\n",
                o.rounds);
    std::FILE* out = cli.csv_file(
        o.csv, "set,N,queries,k,method,build_s,first_s,t_s,vs_kd,vs_flann,vs_bf,recall,fn,maxdil,meandil,rows_diff,examined\n");
    for (const std::string& set : o.sets) {
      Workload w;
      std::vector<int> set_ks;
      if (!load_workload(cli, o, set, w, set_ks)) continue;
      std::printf("\n# %s: %zu points, %zu queries\n", set.c_str(), w.pts.size() / 3, w.q.size() / 3);
      std::printf("%-13s %3s %-10s %8s %8s %9s %7s %8s %7s %7s %7s %8s %7s %8s %9s\n", "set", "k", "method", "build_s",
                  "first_s", "t_s", "vs_kd", "vs_flann", "vs_bf", "recall", "FN", "maxdil", "mdil", "rows_diff", "examined");
      const Indexes ix = build_indexes(o, ms, rt, w);
      for (int k : set_ks) report_k(o, ms, ix, w, k, time_methods(o, ms, ix, w, k), out);
    }
    if (out) std::fclose(out);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "far_bench: %s\n", e.what());
    return 1;
  }
  return 0;
}
