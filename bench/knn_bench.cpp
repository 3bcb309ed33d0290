// knn_bench: run time against error, side by side, in one process.
//
// For each data set: the exact truth once (FLANN when built in, else the brute-force kernel, at
// the largest k: its first k columns are the truth for a smaller k under the tie rule), then for
// each method a build (timed), and for each k and A a warm-up launch (compile time, reported
// apart) and R timed repetitions (kernel time from OpenCL profiling events; host methods by the
// steady clock); the median is reported with recall@k, false negatives and distance dilation.
// Rows go to stdout as a table and to a CSV file.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <random>
#include <sstream>
#include <thread>
#include <string>
#include <vector>

#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/cornell_box.hpp"
#include "bench_cli.hpp"
#include "bench_util.hpp"

using namespace bhcl;

namespace {

struct Options {
  std::vector<std::string> data = {"uniform"};
  std::vector<std::size_t> sizes = {100000};
  std::size_t queries = 20000;
  std::vector<int> ks = {10, 50};
  std::vector<float> As = {1, 2, 4, 8, 16, 32};
  std::vector<std::string> methods;  // empty: every method
  std::vector<std::string> presets = {"auto"};
  int reps = 3;
  std::string sort = "off";  // off, on, both
  std::string csv = "bench_results.csv";
  std::string device;
  std::string truth = "auto";
  std::string data_dir;
  bool append = false;
  // Block-hash build and search knobs (-1: the preset's).
  std::map<std::string, std::string> build, search;  // block hashing's table options given
};

Options parse(int argc, char** argv) {
  Options o;
  bench::BenchCli cli("knn_bench", "Run time against error of every method, side by side in one process");
  cli.data_sets(o.data_dir, o.data, "data sets: uniform, clustered, duplicates, cornell (generated) or bunny, dragon, autzen (files)");
  cli.integers("N", o.sizes, "points per data set (file sets: the first N; 0: all)", 0, 2147483646.0);
  cli.budget_sweep(o.queries, o.ks, o.As, o.presets);
  cli.methods(o.methods);
  cli.reps(o.reps);
  cli.text("sort", o.sort, "dispatch in Hilbert order: off, on or both", "WHEN")->check(CLI::IsMember({"off", "on", "both"}));
  cli.csv(o.csv);
  cli.app().add_flag("--append", o.append, "append to the CSV file instead of replacing it");
  cli.device(o.device);
  cli.text("truth", o.truth, "the exact method giving the true neighbours (auto: " + default_truth_method() + ")", "NAME")
      ->check(CLI::IsMember([] {
        auto v = exact_method_names();
        v.push_back("auto");
        return v;
      }()));
  // Block hashing's own build and search options, from its table (--A and --preset are swept).
  cli.table_options("blockhash", OptionInfo::Build, o.build, {"preset"});
  cli.table_options("blockhash", OptionInfo::Search, o.search, {"A", "recall"});
  cli.parse(argc, argv);
  if (o.methods.empty()) o.methods = method_names();
  if (o.ks.empty() || o.As.empty() || o.data.empty() || o.sizes.empty()) cli.fail("empty list");
  return o;
}

struct Row {
  std::string data, method, preset, device, sort;
  std::size_t N = 0, n = 0;
  int k = 0, threads = 0;
  float A = 0;
  double build_s = 0, compile_s = 0, query_s = 0, qps = 0, mem_per_point = 0;
  Accuracy acc;
};

void print_header() {
  std::printf("%-8s %-10s %-6s %8s %6s %4s %5s %-4s %8s %8s %9s %11s %7s %7s %7s %7s %6s\n", "data",
              "method", "preset", "N", "n", "k", "A", "sort", "build s", "compile", "query s",
              "queries/s", "recall", "FN", "maxdil", "meandil", "B/pt");
}

void print_row(const Row& r) {
  std::printf("%-8s %-10s %-6s %8zu %6zu %4d %5g %-4s %8.3f %8.3f %9.4f %11.0f %7.4f %7.4f %7.3f %7.4f %6.1f\n",
              r.data.c_str(), r.method.c_str(), r.preset.c_str(), r.N, r.n, r.k, r.A, r.sort.c_str(),
              r.build_s, r.compile_s, r.query_s, r.qps, r.acc.recall, r.acc.false_negative_rate,
              r.acc.max_dilation, r.acc.mean_dilation, r.mem_per_point);
  std::fflush(stdout);
}

void write_csv_row(std::ofstream& csv, const Row& r) {
  csv << r.data << ',' << r.method << ',' << r.preset << ',' << r.N << ',' << r.n << ',' << r.k << ','
      << r.A << ',' << r.sort << ',' << '"' << r.device << '"' << ',' << r.threads << ',' << r.build_s
      << ',' << r.compile_s << ',' << r.query_s << ',' << r.qps << ',' << r.acc.recall << ','
      << r.acc.false_negative_rate << ',' << r.acc.max_dilation << ',' << r.acc.mean_dilation << ','
      << r.acc.mean_rel_distance_error << ',' << r.acc.incomplete_queries << ',' << r.mem_per_point
      << '\n';
  csv.flush();
}


}  // namespace

int main(int argc, char** argv) {
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
#endif
  Options o = parse(argc, argv);
  try {
    auto rt = std::make_shared<Runtime>(o.device);
    const char* pt = std::getenv("POCL_MAX_PTHREAD_COUNT");
    int threads = pt ? std::atoi(pt) : static_cast<int>(std::thread::hardware_concurrency());
    std::printf("# device: %s\n# host threads for host methods: %d (POCL_MAX_PTHREAD_COUNT=%s)\n",
                rt->info().summary().c_str(), threads, pt ? pt : "unset");
    std::ofstream csv(o.csv, o.append ? std::ios::app : std::ios::trunc);
    if (!csv) throw Error(o.csv + ": cannot open for writing");
    if (!o.append || csv.tellp() == 0)
      csv << "data,method,preset,N,n,k,A,sort,device,threads,build_s,compile_s,query_s,queries_per_s,"
             "recall,fn_rate,max_dilation,mean_dilation,mean_rel_err,incomplete,bytes_per_point\n";
    const int kmax = *std::max_element(o.ks.begin(), o.ks.end());
    print_header();
    for (const auto& set : o.data) {
      for (std::size_t N : o.sizes) {
        std::vector<float> pts, qs;
        std::string label;
        if (!bench::load_set(o.data_dir, set, N, o.queries, pts, qs)) continue;
        label = set;
        const std::size_t n_pts = pts.size() / 3, n_q = qs.size() / 3;
        // Exact truth, once, at the largest k.
        SearchParams tp;
        tp.k = kmax;
        const std::string truth_method = o.truth == "auto" ? default_truth_method() : o.truth;
        auto t0 = std::chrono::steady_clock::now();
        MethodOptions topt;
        if (truth_method == "flann") topt.set("threads", std::to_string(threads));
        auto truth_index = make_index(truth_method, rt, pts.data(), n_pts, topt);
        KnnResult truth_all = truth_index->query(qs, tp);
        truth_index.reset();
        std::printf("# %s N=%zu: truth by %s in %.1f s\n", label.c_str(), n_pts, truth_method.c_str(),
                    std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
        for (const auto& method : o.methods) {
          bool is_bh = method == "blockhash";
          std::vector<std::string> presets = is_bh ? o.presets : std::vector<std::string>{""};
          for (const auto& preset : presets) {
            MethodOptions mo;
            if (method == "flann") mo.set("threads", std::to_string(threads));
            if (is_bh) {
              if (!preset.empty()) mo.set("preset", preset);
              for (const auto& [name, v] : o.build)
                if (!v.empty()) mo.set(name, v);
            }
            std::unique_ptr<Index> index;
            try {
              index = make_index(method, rt, pts.data(), n_pts, mo);
            } catch (const Error& e) {
              std::printf("# %s on %s: %s: skipped\n", method.c_str(), label.c_str(), e.what());
              continue;
            }
            std::vector<float> As = index->exact() ? std::vector<float>{0.0f} : o.As;
            for (int k : o.ks) {
              KnnResult truth = truth_all.leading_columns(k);
              for (float A : As) {
                std::vector<std::string> sorts;
                if (o.sort == "both") sorts = {"off", "on"};
                else sorts = {o.sort};
                for (const auto& sort : sorts) {
                  SearchParams p;
                  p.k = k;
                  if (A > 0) p.A = A;
                  if (is_bh) bench::BenchCli::apply_search("blockhash", o.search, p);
                  p.sort_queries = sort == "on";
                  Row r;
                  r.data = label;
                  r.method = method;
                  r.preset = preset;
                  r.device = index->exact() && method == "flann" ? "host" : rt->info().device_name;
                  r.N = n_pts;
                  r.n = n_q;
                  r.k = k;
                  r.A = A;
                  r.sort = sort;
                  r.threads = threads;
                  r.build_s = index->build_seconds();
                  r.mem_per_point = double(index->memory_bytes()) / double(n_pts);
                  r.compile_s = index->warm_up(p);
                  std::vector<double> times;
                  KnnResult res;
                  for (int rep = 0; rep < o.reps; ++rep) {
                    QueryStats st = index->query(qs.data(), n_q, p, res);
                    times.push_back(st.query_s);
                    r.compile_s += st.compile_s;
                  }
                  r.query_s = bench::median(times);
                  r.qps = r.query_s > 0 ? double(n_q) / r.query_s : 0.0;
                  r.acc = evaluate_accuracy(res, truth);
                  print_row(r);
                  write_csv_row(csv, r);
                }
              }
            }
          }
        }
      }
    }
    std::printf("# rows written to %s\n", o.csv.c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "knn_bench: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
