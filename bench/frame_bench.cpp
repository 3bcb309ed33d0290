// frame_bench: a photon map's frame, per method: build the index over N photon-like points, then
// answer one gather pass of queries at k (default: 1M Cornell-box photons, 262,144 queries =
// 512 x 512, k = 50). Every method of the registry (each choice of a "preset" option), so a new
// method or preset is picked up. Per method: ms for the build, the query call (upload, kernel,
// download, host sort of the queries: the call's wall time less its compile time) and the frame
// (their sum), medians over interleaved rounds (the method order rotates each round), and the
// median of the per-round ratios of its frame to the kd-tree's frame; kernel compile (first
// builds and launches, done in an untimed warm-up round) reported apart; recall@k against the
// exact answer beside each. Progress on stderr, the table on stdout.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <string>
#include <thread>
#include <vector>

#include "blockhash_cl/blockhash_cl.hpp"
#include "bench_cli.hpp"
#include "bench_util.hpp"

using namespace bhcl;

namespace {

using bench::now_s;

struct Entry {
  const MethodInfo* info;
  std::string preset, label;
  bool skipped = false;
  std::string why;
  double compile_s = 0, recall = -1;
  std::vector<double> build_ms, query_ms, frame_ms, ratio;
};

struct Options {
  std::string data = "cornell", data_dir, device, sort = "auto", baseline = "kdtree";
  std::size_t N = 1000000, n_queries = 262144;
  int k = 50, rounds = 3;
  float A = SearchParams{}.A;
  double max_query_s = 20.0;
  std::vector<std::string> only;
};

Options parse(int argc, char** argv) {
  Options o;
  bench::BenchCli cli("frame_bench",
                      "A photon map's frame per method: build over N points + one gather pass of "
                      "queries at k, ms per frame in interleaved rounds, ratio to the kd-tree's frame");
  cli.data_dir(o.data_dir);
  cli.text("data", o.data, "data set: cornell (photon-like, default), uniform, clustered, duplicates, "
           "or bunny, dragon, autzen (files)", "NAME");
  cli.integer("N", o.N, "points (the photon map)", 1, 2147483646.0);
  cli.queries(o.n_queries)->description("queries per frame (262144 = one 512 x 512 gather pass)");
  cli.integer("k", o.k, "neighbours per query", 1, kMaxK);
  cli.integer("rounds", o.rounds, "timed rounds (interleaved; medians reported)", 1, 1000);
  cli.number("A", o.A, "blockhash: examine at most A*k points per query (default: the library's)", 1e-3, 1e6);
  cli.text("sort", o.sort, "dispatch in Hilbert order: auto (the library's default), on, off", "WHEN")
      ->check(CLI::IsMember({"auto", "on", "off"}));
  cli.methods(o.only);
  cli.text("baseline", o.baseline, "the method frames are compared to", "NAME")->check(CLI::IsMember(method_names()));
  cli.number("max-query-s", o.max_query_s,
             "skip a method whose query pass, estimated on a 1/256 sample, would take longer (s)", 0, 1e6);
  cli.device(o.device);
  cli.parse(argc, argv);
  return o;
}

// Every method of the registry (--methods and the baseline), each choice of its "preset" option.
std::vector<Entry> make_entries(const Options& o) {
  std::vector<Entry> entries;
  for (const MethodInfo& m : methods()) {
    if (!o.only.empty() && std::find(o.only.begin(), o.only.end(), m.name) == o.only.end() && m.name != o.baseline)
      continue;
    std::vector<std::string> presets = {""};
    for (const OptionInfo* opt : m.build_options())
      if (opt->name == "preset" && opt->kind == OptionInfo::Kind::Choice) presets = opt->choices;
    for (const auto& preset : presets)
      entries.push_back({&m, preset, preset.empty() ? m.name : m.name + ":" + preset});
  }
  return entries;
}

// What the rounds share: the points, the queries and the search.
struct Frame {
  const std::shared_ptr<Runtime>& rt;
  const std::vector<float>& pts;
  const std::vector<float>& qs;
  SearchParams p;
  std::unique_ptr<Index> build(const Entry& e) const {
    MethodOptions mo;
    if (!e.preset.empty()) mo.set("preset", e.preset);
    return e.info->make(rt, pts.data(), pts.size() / 3, mo);
  }
};

// Warm-up round (untimed): compile time, recall, and the sample-based skip.
void warm_up(const Options& o, const Frame& f, const KnnResult& truth, std::vector<Entry>& entries) {
  const std::size_t n_q = f.qs.size() / 3;
  const std::size_t n_sample = std::max<std::size_t>(1, n_q / 256);
  for (auto& e : entries) {
    std::fprintf(stderr, "frame_bench: warm-up %s\n", e.label.c_str());
    auto index = f.build(e);
    e.compile_s = index->warm_up(f.p);
    KnnResult res;
    QueryStats st = index->query(f.qs.data(), n_sample, f.p, res);
    e.compile_s += st.compile_s;
    const double est = (st.wall_s - st.compile_s) * double(n_q) / double(n_sample);
    if (est > o.max_query_s && e.label != o.baseline) {
      e.skipped = true;
      char why[128];
      std::snprintf(why, sizeof why, "query pass estimated at %.0f s > --max-query-s %.0f", est, o.max_query_s);
      e.why = why;
      std::fprintf(stderr, "frame_bench: %s skipped: %s\n", e.label.c_str(), why);
      continue;
    }
    index->query(f.qs.data(), n_q, f.p, res);
    e.recall = evaluate_accuracy(res, truth).recall;
  }
}

// The timed rounds, the method order rotated each round; each frame's ratio to the baseline's.
void timed_rounds(const Options& o, const Frame& f, std::vector<Entry>& entries) {
  const std::size_t n_q = f.qs.size() / 3;
  std::size_t base = entries.size();
  for (std::size_t i = 0; i < entries.size(); ++i)
    if (entries[i].label == o.baseline) base = i;
  std::vector<std::size_t> active;
  for (std::size_t i = 0; i < entries.size(); ++i)
    if (!entries[i].skipped) active.push_back(i);
  for (int r = 0; r < o.rounds; ++r) {
    std::map<std::size_t, double> frame;
    for (std::size_t j = 0; j < active.size(); ++j) {
      const std::size_t i = active[(j + static_cast<std::size_t>(r)) % active.size()];  // rotated
      Entry& e = entries[i];
      std::fprintf(stderr, "frame_bench: round %d/%d %s\n", r + 1, o.rounds, e.label.c_str());
      const double t0 = now_s();
      auto index = f.build(e);
      const double build_ms = (now_s() - t0) * 1e3;
      KnnResult res;
      QueryStats st = index->query(f.qs.data(), n_q, f.p, res);
      const double query_ms = (st.wall_s - st.compile_s) * 1e3;
      e.compile_s += st.compile_s;  // nonzero only if a variant compiled here
      e.build_ms.push_back(build_ms);
      e.query_ms.push_back(query_ms);
      e.frame_ms.push_back(build_ms + query_ms);
      frame[i] = build_ms + query_ms;
    }
    if (base < entries.size() && frame.count(base))
      for (auto& [i, fr] : frame) entries[i].ratio.push_back(fr / frame[base]);
  }
}

void print_table(const Options& o, const std::vector<Entry>& entries, const std::string& truth_method) {
  std::printf("%-18s %9s %9s %9s %11s %10s %8s\n", "method", "build ms", "query ms", "frame ms",
              ("/" + o.baseline).c_str(), "compile s", "recall");
  for (const auto& e : entries) {
    if (e.skipped) {
      std::printf("%-18s skipped: %s\n", e.label.c_str(), e.why.c_str());
      continue;
    }
    std::printf("%-18s %9.1f %9.1f %9.1f %11.3f %10.2f %8.4f\n", e.label.c_str(),
                bench::median(e.build_ms), bench::median(e.query_ms), bench::median(e.frame_ms),
                bench::median(e.ratio), e.compile_s, e.recall);
  }
  std::printf("# ms: medians over rounds; /%s: median of per-round frame ratios; compile apart;\n"
              "# recall@%d against %s's exact answer\n",
              o.baseline.c_str(), o.k, truth_method.c_str());
}

}  // namespace

int main(int argc, char** argv) {
  const Options o = parse(argc, argv);
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
#endif
  try {
    auto rt = std::make_shared<Runtime>(o.device);
    std::vector<float> pts, qs;
    if (!bench::load_set(o.data_dir, o.data, o.N, o.n_queries, pts, qs)) return 1;
    const std::size_t n_pts = pts.size() / 3, n_q = qs.size() / 3;
    const char* pt = std::getenv("POCL_MAX_PTHREAD_COUNT");
    std::string command = "#";
    for (int i = 0; i < argc; ++i) command += std::string(" ") + argv[i];
    std::printf("%s\n# frame_bench: %s, N = %zu points, %zu queries, k = %d, %d rounds, sort %s, A %g\n",
                command.c_str(), o.data.c_str(), n_pts, n_q, o.k, o.rounds, o.sort.c_str(), o.A);
    std::printf("# device: %s; host threads %u (POCL_MAX_PTHREAD_COUNT=%s)\n",
                rt->info().summary().c_str(), std::thread::hardware_concurrency(), pt ? pt : "unset");
    Frame f{rt, pts, qs, {}};
    f.p.k = o.k;
    f.p.A = o.A;
    f.p.sort_queries = o.sort == "auto" ? -1 : o.sort == "on" ? 1 : 0;
    std::vector<Entry> entries = make_entries(o);

    // The exact answer, by the default truth method.
    const std::string truth_method = default_truth_method();
    std::fprintf(stderr, "frame_bench: exact answer by %s\n", truth_method.c_str());
    KnnResult truth;
    {
      SearchParams tp = f.p;
      auto index = make_index(truth_method, rt, pts.data(), n_pts);
      index->query(qs.data(), n_q, tp, truth);
    }
    warm_up(o, f, truth, entries);
    timed_rounds(o, f, entries);
    print_table(o, entries, truth_method);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "frame_bench: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
