// perf_harness: block hashing against the exact baselines, measured so that 10 % shows on a
// noisy machine (docs/PERFORMANCE.md).
//
// On a shared machine absolute queries/s move up to 3x between runs, but load that lasts seconds
// hits runs made back to back alike. So for each data set every structure is built once (the
// kd-tree kernel index, FLANN, each block-hash build), every (method, variant, k) is warmed up
// (kernel compiles reported apart), and then, for R rounds, every variant runs once per query
// order and k, in an order shuffled per round (baselines included, so no variant always follows
// the same neighbour). A variant's figure is the median over rounds of t_kd / t_variant and
// t_flann / t_variant, with the baselines' times from the same round, order and k: a ratio, not
// an absolute rate. Times are QueryStats::query_s: kernel event time on the device, FLANN's own
// search time on the host; uploads, downloads and compiles are excluded.
//
// Query orders: "random" is the set's own order, "sorted" the same queries sorted once on the
// host in the library's 3D Hilbert order (what SearchParams::sort_queries does). Every method gets
// the same array with sort_queries = false, so no method sorts on its own clock.
// Accuracy comes from the first round's results against the kd-tree kernel's answer (exact, equal
// to FLANN's: checked once, the differing rows are counted and printed).
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <numeric>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "bench_cli.hpp"
#include "bench_util.hpp"
#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"
#include "core/query_order.hpp"  // detail::hilbert_query_order: the order sort_queries uses

using namespace bhcl;

namespace {

// The block-hash search options the harness sweeps: its table's search options but A and recall
// (swept as --A and --recall) and the device options every method shares, save the work-group
// size (a kernel form's field, kernel_forms.hpp: block hashing's alone is swept, the baselines
// keep their device default).
std::vector<const OptionInfo*> sweep_options() {
  std::vector<const OptionInfo*> out;
  const std::vector<OptionInfo> device = device_search_options();
  for (const OptionInfo* o : method_info("blockhash").search_options()) {
    const bool shared = std::any_of(device.begin(), device.end(), [&](const OptionInfo& d) { return d.name == o->name; });
    if (o->name != "A" && o->name != "recall" && (!shared || o->name == "local-size")) out.push_back(o);
  }
  return out;
}

struct BuildSpec { std::string name; BlockHashBuildParams params; };
struct DefineSpec { std::string name, defines; };

struct Options {
  std::vector<std::string> data = {"cornell", "uniform", "autzen"};
  std::size_t N = 1000000, queries = 100000;
  std::vector<int> ks = {10, 50};
  int rounds = 5;
  std::vector<std::string> orders = {"random", "sorted"};
  std::vector<float> As = {1, 1.5f, 2, 3, 4, 6, 8};
  std::vector<double> recalls;  // --recall: variants asking for a recall target instead of an A
  // Block hashing's own search options (its table's, but A and recall, which are swept above, and
  // the device options): each swept over a comma list, default its table default.
  std::vector<const OptionInfo*> sweep;
  std::vector<std::vector<std::string>> sweep_values;
  std::vector<BuildSpec> builds = {{"auto", {}}};
  std::vector<DefineSpec> defines = {{"base", ""}};
  std::string baseline_defines, csv, device, data_dir;
  int threads = 0;
  double recall_target = 0.95;
  unsigned long long seed = 1;
};

// Bad options: one line, exit status 2.
[[noreturn]] void bad(const std::string& why) {
  std::fprintf(stderr, "perf_harness: %s (see perf_harness --help)\n", why.c_str());
  std::exit(2);
}

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  for (std::string item; std::getline(ss, item, sep);)
    if (!item.empty()) out.push_back(item);
  return out;
}

double num(const std::string& s, const std::string& what) {
  char* end = nullptr;
  double v = std::strtod(s.c_str(), &end);
  if (s.empty() || *end || !std::isfinite(v)) bad(what + ": '" + s + "' is not a number");
  return v;
}

long long integer(const std::string& s, const std::string& what, double lo, double hi) {
  double v = num(s, what);  // through strtod, so that 1e6 is an integer too
  if (v != std::floor(v) || v < lo || v > hi)
    bad(what + ": '" + s + "' is not an integer in [" + std::to_string((long long)lo) + ", " +
        std::to_string((long long)hi) + "]");
  return static_cast<long long>(v);
}

// One key of a --bh-build spec: a build option of block hashing's table, by its name ("L",
// "target-cell-points"), keyword ("target_cell_points") or the field it sets; range-checked there.
void set_key(BlockHashBuildParams& p, const std::string& key, const std::string& v, const std::string& what) {
  for (const OptionInfo* o : method_info("blockhash").build_options()) {
    const std::string field = o->field.substr(o->field.find("::") == std::string::npos ? 0 : o->field.find("::") + 2);
    if (!o->set || (key != o->name && key != o->keyword_name() && key != field)) continue;
    try {
      o->set(&p, o->parse(v, what + " " + key));
    } catch (const Error& e) {
      bad(e.what());
    }
    return;
  }
  bad(what + ": unknown key '" + key + "'");
}

// Names appear in variant names (build/A/sweep/defines) and CSV cells.
std::string check_name(const std::string& name, const std::string& what) {
  if (name.empty() || name.find_first_of("/,\" ") != std::string::npos)
    bad(what + ": name '" + name + "' must be non-empty, without / , \" or spaces");
  return name;
}

// "name:key=value,...;name2" -> builds. A bare name is a preset's defaults.
std::vector<BuildSpec> parse_builds(const std::string& s) {
  std::vector<BuildSpec> out;
  for (const auto& spec : split(s, ';')) {
    const auto colon = spec.find(':');
    BuildSpec b;
    b.name = check_name(spec.substr(0, colon), "--bh-build");
    if (colon == std::string::npos) set_key(b.params, "preset", b.name, "--bh-build " + b.name);
    else
      for (const auto& kv : split(spec.substr(colon + 1), ',')) {
        const auto eq = kv.find('=');
        if (eq == std::string::npos) bad("--bh-build " + b.name + ": '" + kv + "' is not key=value");
        set_key(b.params, kv.substr(0, eq), kv.substr(eq + 1), "--bh-build " + b.name);
      }
    for (const auto& o : out)
      if (o.name == b.name) bad("--bh-build: name '" + b.name + "' given twice");
    out.push_back(b);
  }
  if (out.empty()) bad("--bh-build: no build");
  return out;
}

// Every token must be -DNAME[=VALUE] (the library checks again; this fails before any build).
std::string check_defines(const std::string& d, const std::string& what) {
  std::istringstream is(d);
  for (std::string tok; is >> tok;)
    if (tok.size() < 3 || tok.compare(0, 2, "-D") != 0) bad(what + ": '" + tok + "' is not -DNAME[=VALUE]");
  return d;
}

std::vector<DefineSpec> parse_defines(const std::string& s) {
  std::vector<DefineSpec> out;
  for (const auto& spec : split(s, ';')) {
    const auto colon = spec.find(':');
    if (colon == std::string::npos) bad("--defines: '" + spec + "' is not name:-D...");
    DefineSpec d{check_name(spec.substr(0, colon), "--defines"), ""};
    d.defines = check_defines(spec.substr(colon + 1), "--defines " + d.name);
    for (const auto& o : out)
      if (o.name == d.name) bad("--defines: name '" + d.name + "' given twice");
    out.push_back(d);
  }
  if (out.empty()) bad("--defines: no variant");
  return out;
}

Options parse(int argc, char** argv) {
  Options o;
  bench::BenchCli cli("perf_harness", "Block hashing against the kd-tree kernel and FLANN: interleaved "
                                      "rounds, per-round ratios, accuracy beside speed");
  std::string builds, defines;
  cli.names("data", o.data, "data sets: cornell, uniform, clustered, duplicates (generated) or bunny, dragon, autzen (files)");
  cli.integer("N", o.N, "points per data set (file sets: the first N)", 1, 2147483646.0);
  cli.queries(o.queries);
  cli.ks(o.ks);
  cli.integer("rounds", o.rounds, "interleaved rounds (the median of per-round ratios is reported)", 1, 1000);
  cli.names("order", o.orders, "query orders: random, sorted (Hilbert)")->check(CLI::IsMember({"random", "sorted"}));
  cli.As(o.As);
  cli.numbers("recall", o.recalls, "blockhash variants asking for these recall targets instead of an A", 1e-6, 1.0);
  o.sweep = sweep_options();
  o.sweep_values.resize(o.sweep.size());
  for (std::size_t i = 0; i < o.sweep.size(); ++i) {
    const OptionInfo* s = o.sweep[i];
    o.sweep_values[i] = {s->def};
    cli.app()
        .add_option("--" + s->name, o.sweep_values[i], "blockhash: " + s->help + " (" + s->range_text() + "), comma separated")
        ->delimiter(',')
        ->check(bench::BenchCli::table_check(s))
        ->type_name("LIST");
  }
  std::string keys;  // block hashing's build options, from its table
  for (const OptionInfo* k : method_info("blockhash").build_options())
    if (k->set) keys += " " + k->keyword_name();
  cli.text("bh-build", builds, "blockhash builds: \"name[:key=value,...];...\"; keys:" + keys +
           "; a bare name is a preset (auto, paper) [default: auto]", "SPECS");
  cli.text("defines", defines, "kernel variants: \"name:-DFOO=1 -DBAR;...\" [default: base, none]", "SPECS");
  cli.text("baseline-defines", o.baseline_defines, "-D switches for the kd-tree baseline's kernel", "DEFINES");
  cli.csv(o.csv);
  cli.device(o.device);
  cli.integer("threads", o.threads, "flann: host threads (0: all hardware threads)", 0, 4096);
  cli.number("recall-target", o.recall_target, "the recall the smallest-A summary asks for", 1e-6, 1.0);
  cli.seed(o.seed);
  cli.data_dir(o.data_dir);
  cli.parse(argc, argv);
  if (!builds.empty()) o.builds = parse_builds(builds);
  if (!defines.empty()) o.defines = parse_defines(defines);
  if (!o.baseline_defines.empty()) check_defines(o.baseline_defines, "--baseline-defines");
  if (o.ks.empty() || o.As.empty()) bad("--k and --A need at least one value");
  if (o.data.empty()) bad("--data: no data set");
  for (const auto& d : o.data)  // file sets are bench::load_set's; the rest must be generated ones
    if (d != "bunny" && d != "dragon" && d != "autzen") try {
        datasets::by_name(d, 1, 1);
      } catch (const std::exception& e) {
        bad("--data: " + std::string(e.what()) + "; file sets: bunny, dragon, autzen");
      }
  if (o.orders.empty()) bad("--order: no order");
  return o;
}

// One timed configuration. Baselines have A = 0 and an empty build.
struct Variant {
  std::string name, method, build, defines_name;
  std::vector<std::string> sweep;  // block-hash variants: the values of Options::sweep
  const Index* index = nullptr;
  SearchParams params;  // k set per run
  double compile_s = 0;
};

// Per (order, k, variant): the round times and the first round's accuracy.
struct Cell {
  std::vector<double> t;
  Accuracy acc;
};

std::string fmt_A(float A) {
  char b[32];
  std::snprintf(b, sizeof b, "%g", A);
  return b;
}

// A swept value in variant names: the option's initial and the value ("def": the default), e.g. "pdef".
std::string sweep_tag(const OptionInfo& o, const std::string& v) {
  return o.name.substr(0, 1) + (v == o.def ? "def" : v);
}
std::string sweep_tags(const Options& o, const std::vector<std::string>& values) {
  std::string t;
  // "+" between them: the names are CSV cells.
  for (std::size_t i = 0; i < values.size(); ++i) t += (i ? "+" : "") + sweep_tag(*o.sweep[i], values[i]);
  return t;
}

// Every combination of the swept values, the first option outermost.
std::vector<std::vector<std::string>> sweep_product(const Options& o) {
  std::vector<std::vector<std::string>> out = {{}};
  for (const auto& values : o.sweep_values) {
    std::vector<std::vector<std::string>> next;
    for (const auto& prefix : out)
      for (const auto& v : values) {
        next.push_back(prefix);
        next.back().push_back(v);
      }
    out = std::move(next);
  }
  return out;
}

// Rows that differ (ids, distances bit for bit, or counts) between two results of one shape.
std::size_t differing_rows(const KnnResult& a, const KnnResult& b) {
  std::size_t rows = 0;
  for (std::size_t q = 0; q < a.n; ++q) {
    bool same = a.counts[q] == b.counts[q];
    for (int j = 0; same && j < a.k; ++j)
      same = a.id(q, j) == b.id(q, j) && std::memcmp(&a.dist2[q * a.k + j], &b.dist2[q * b.k + j], 4) == 0;
    rows += !same;
  }
  return rows;
}

// The query arrays, one per order, and the permutation that made each (the identity for "random").
struct QueryOrders {
  std::vector<std::vector<float>> q;
  std::vector<std::vector<std::size_t>> perm;
};

QueryOrders query_orders(const Options& o, const std::vector<float>& qs) {
  const std::size_t n = qs.size() / 3;
  QueryOrders out;
  for (const auto& ord : o.orders) {
    std::vector<std::size_t> perm(n);
    std::iota(perm.begin(), perm.end(), 0);
    if (ord == "sorted") perm = detail::hilbert_query_order(qs.data(), n);
    std::vector<float> q(3 * n);
    for (std::size_t i = 0; i < n; ++i) std::copy_n(&qs[3 * perm[i]], 3, &q[3 * i]);
    out.q.push_back(std::move(q));
    out.perm.push_back(std::move(perm));
  }
  return out;
}

// Variants: the two baselines first (their times are the ratios' numerators), then block hashing
// grouped by (build, defines, swept search options) with A innermost, as the tables list them.
std::vector<Variant> make_variants(const Options& o, const Index& kd, const Index& fl,
                                   const std::vector<std::unique_ptr<BlockHashIndex>>& bh) {
  std::vector<Variant> vars;
  auto base = [&](const std::string& name, const Index* idx, const std::string& defines) {
    Variant v;
    v.name = v.method = name;
    v.index = idx;
    v.params.kernel_defines = defines;
    v.defines_name = defines.empty() ? "" : "baseline";
    vars.push_back(v);
  };
  base("kdtree", &kd, o.baseline_defines);
  base("flann", &fl, "");
  // Block-hash variants: build x defines x swept search options x (each A, then each recall target; a
  // recall-target variant's A is tuned by the index at warm-up, BlockHashIndex::tune_for_recall).
  for (std::size_t bi = 0; bi < o.builds.size(); ++bi)
    for (const auto& d : o.defines)
      for (const std::vector<std::string>& sw : sweep_product(o)) {
        auto add = [&](const std::string& knob, float A, double recall) {
          Variant v;
          v.method = "blockhash";
          v.build = o.builds[bi].name;
          v.defines_name = d.name;
          v.index = bh[bi].get();
          v.params.A = A;
          v.params.recall_target = recall;
          v.sweep = sw;
          for (std::size_t i = 0; i < sw.size(); ++i) o.sweep[i]->set_search(&v.params, o.sweep[i]->parse(sw[i]));
          v.params.kernel_defines = d.defines;
          v.name = v.build + "/" + knob + "/" + sweep_tags(o, sw) + "/" + d.name;
          vars.push_back(v);
        };
        for (float A : o.As) add("A" + fmt_A(A), A, 0.0);
        for (double r : o.recalls) {
          char rb[32];
          std::snprintf(rb, sizeof rb, "R%.3g", r);
          add(rb, SearchParams{}.A, r);
        }
      }
  for (auto& v : vars) v.params.sort_queries = 0;  // each order's array is dispatched as it is
  return vars;
}

// Truth: the kd-tree kernel without the baseline defines (they are what is being explored), at
// the largest k; FLANN checked against it once. truth[order][k]: the leading columns (exact for a
// smaller k under the tie rule), rows permuted as the order's queries.
std::vector<std::vector<KnnResult>> truth_by_order(const Options& o, const Index& kd, const Index& fl,
                                                   const std::vector<float>& qs,
                                                   const std::vector<std::vector<std::size_t>>& order_perm) {
  const std::size_t n = qs.size() / 3;
  const int kmax = *std::max_element(o.ks.begin(), o.ks.end());
  SearchParams tp;
  tp.k = kmax;
  tp.sort_queries = false;
  KnnResult truth_all, flann_all;
  if (double c = kd.warm_up(tp); c > 0) std::printf("# compile (truth: kdtree without defines) s: %.2f\n", c);
  kd.query(qs.data(), n, tp, truth_all);
  fl.query(qs.data(), n, tp, flann_all);
  std::printf("# flann vs kdtree kernel (k = %d): %zu of %zu rows differ\n", kmax,
              differing_rows(truth_all, flann_all), n);
  flann_all = KnnResult();
  std::vector<std::vector<KnnResult>> truth(o.orders.size());
  for (std::size_t oi = 0; oi < o.orders.size(); ++oi)
    for (int k : o.ks) {
      KnnResult lead = truth_all.leading_columns(k), t;
      t.resize(n, k);
      for (std::size_t i = 0; i < n; ++i) {
        const std::size_t src = order_perm[oi][i];
        std::copy_n(&lead.ids[src * k], k, &t.ids[i * k]);
        std::copy_n(&lead.dist2[src * k], k, &t.dist2[i * k]);
        t.counts[i] = lead.counts[src];
      }
      truth[oi].push_back(std::move(t));
    }
  return truth;
}

// cells[order][k][variant]: the round times and the first round's accuracy.
using Cells = std::vector<std::vector<std::vector<Cell>>>;

// The rounds: every variant once per order and k, in an order shuffled per round.
Cells run_rounds(const Options& o, const std::string& set, const std::vector<Variant>& vars,
                 const std::vector<std::vector<float>>& order_q, const std::vector<std::vector<KnnResult>>& truth) {
  const std::size_t n = order_q.empty() ? 0 : order_q[0].size() / 3;
  Cells cells(o.orders.size(), std::vector<std::vector<Cell>>(o.ks.size(), std::vector<Cell>(vars.size())));
  std::mt19937_64 rng(o.seed);
  const bool tty = isatty(STDERR_FILENO);
  KnnResult res;
  double stray_compile = 0;
  for (int r = 0; r < o.rounds; ++r) {
    if (tty) std::fprintf(stderr, "\rperf_harness: %s round %d/%d ", set.c_str(), r + 1, o.rounds);
    for (std::size_t oi = 0; oi < o.orders.size(); ++oi)
      for (std::size_t ki = 0; ki < o.ks.size(); ++ki) {
        std::vector<std::size_t> run(vars.size());
        std::iota(run.begin(), run.end(), 0);
        std::shuffle(run.begin(), run.end(), rng);
        for (std::size_t vi : run) {
          SearchParams p = vars[vi].params;
          p.k = o.ks[ki];
          QueryStats st = vars[vi].index->query(order_q[oi].data(), n, p, res);
          stray_compile += st.compile_s;
          cells[oi][ki][vi].t.push_back(st.query_s);
          if (r == 0) cells[oi][ki][vi].acc = evaluate_accuracy(res, truth[oi][ki]);
        }
      }
  }
  if (tty) std::fprintf(stderr, "\n");
  if (stray_compile > 0)
    std::printf("# warning: %.2f s of compiles happened in timed runs (not in query_s)\n", stray_compile);
  return cells;
}

// A variant's per-round ratios against the same round's baselines (row[0] = kdtree, row[1] =
// flann) and its queries/s, with their medians and ranges.
struct Ratios {
  double qps = 0, kd = 0, fl = 0;
  std::pair<double, double> kd_range, fl_range;  // min, max
};

Ratios round_ratios(const std::vector<Cell>& row, std::size_t vi, int rounds, std::size_t n) {
  const Cell& c = row[vi];
  std::vector<double> rk, rf, qps;
  for (int r = 0; r < rounds; ++r) {
    rk.push_back(row[0].t[r] / c.t[r]);
    rf.push_back(row[1].t[r] / c.t[r]);
    qps.push_back(double(n) / c.t[r]);
  }
  const auto mk = std::minmax_element(rk.begin(), rk.end());
  const auto mf = std::minmax_element(rf.begin(), rf.end());
  return {bench::median(qps), bench::median(rk), bench::median(rf), {*mk.first, *mk.second}, {*mf.first, *mf.second}};
}

// The data set a table is about.
struct SetInfo {
  std::string name;
  std::size_t N, n;
  int threads;
};

void write_csv_row(std::ofstream& csv, const Options& o, const Runtime& rt, const SetInfo& s, int k,
                   const std::string& order, const Variant& v, const Ratios& q, const Accuracy& acc) {
  const bool bhv = v.method == "blockhash";
  csv << s.name << ',' << s.N << ',' << s.n << ',' << k << ',' << order << ',' << v.name << ','
      << v.method << ',' << v.build << ',' << (bhv ? fmt_A(v.params.A) : "") << ',';
  for (std::size_t i = 0; i < o.sweep.size(); ++i) csv << (bhv ? v.sweep[i] : "") << ',';
  csv
       << v.defines_name << ",\"" << v.params.kernel_defines << "\",\""
       << (v.method == "flann" ? "host" : rt.info().device_name) << "\"," << s.threads << ','
       << o.rounds << ',' << v.index->build_seconds() << ','
       << v.compile_s << ',' << q.qps << ',' << q.kd << ',' << q.fl << ','
       << q.kd_range.first << ',' << q.kd_range.second << ',' << q.fl_range.first << ',' << q.fl_range.second << ','
       << acc.recall << ',' << acc.false_negative_rate << ',' << acc.max_dilation << ','
       << acc.mean_dilation << '\n';
}

// Per (build, defines, swept options) group (contiguous in vars): the smallest A reaching the target.
void print_smallest_A(const Options& o, const std::vector<Variant>& vars, const std::vector<Cell>& row,
                      const std::vector<Ratios>& ratios) {
  for (std::size_t g = 2; g < vars.size();) {
    std::size_t end = g, best = 0;
    double top = -1;
    float top_A = 0;
    for (; end < vars.size() && vars[end].build == vars[g].build && vars[end].defines_name == vars[g].defines_name &&
           vars[end].sweep == vars[g].sweep;
         ++end) {
      const double rec = row[end].acc.recall;
      if (vars[end].params.recall_target > 0) continue;  // its A is the index's choice: own row
      if (rec >= o.recall_target && (!best || vars[end].params.A < vars[best].params.A)) best = end;
      if (rec > top) top = rec, top_A = vars[end].params.A;
    }
    const Variant& v = vars[g];
    if (best)
      std::printf("smallest A with recall >= %g: %s ratio_kd %.2f ratio_flann %.2f\n", o.recall_target,
                  vars[best].name.c_str(), ratios[best].kd, ratios[best].fl);
    else
      std::printf("smallest A with recall >= %g: %s/A*/%s/%s none reaches the target (best recall %.4f at A%s)\n",
                  o.recall_target, v.build.c_str(), sweep_tags(o, v.sweep).c_str(),
                  v.defines_name.c_str(), top, fmt_A(top_A).c_str());
    g = end;
  }
}

// The table of one (k, order): each variant's medians and accuracy (and its CSV row), the
// baselines' ratio, and each group's smallest A reaching the recall target.
void report(const Options& o, const Runtime& rt, const SetInfo& s, const std::vector<Variant>& vars,
            const std::vector<Cell>& row, std::size_t ki, std::size_t oi, std::ofstream* csv) {
  std::size_t w = 8;
  for (const auto& v : vars) w = std::max(w, v.name.size());
  const int k = o.ks[ki];
  std::printf("\n## %s N=%zu n=%zu k=%d order=%s threads=%d rounds=%d (ratios: median over rounds "
              "of t_base / t_variant)\n",
              s.name.c_str(), s.N, s.n, k, o.orders[oi].c_str(), s.threads, o.rounds);
  std::printf("%-*s %10s %7s %8s %13s %7s %7s %7s %8s\n", int(w), "variant", "q/s", "vs kd",
              "vs flann", "vs kd min-max", "recall", "FN", "maxdil", "meandil");
  std::vector<Ratios> ratios(vars.size());
  for (std::size_t vi = 0; vi < vars.size(); ++vi) {
    const Cell& c = row[vi];
    const Ratios& q = ratios[vi] = round_ratios(row, vi, o.rounds, s.n);
    char range[40];
    std::snprintf(range, sizeof range, "%.2f-%.2f", q.kd_range.first, q.kd_range.second);
    std::printf("%-*s %10.0f %7.2f %8.2f %13s %7.4f %7.4f %7.3f %8.4f\n", int(w), vars[vi].name.c_str(),
                q.qps, q.kd, q.fl, range, c.acc.recall,
                c.acc.false_negative_rate, c.acc.max_dilation, c.acc.mean_dilation);
    if (csv) write_csv_row(*csv, o, rt, s, k, o.orders[oi], vars[vi], q, c.acc);
  }
  std::printf("kd-tree kernel vs FLANN: %.2f (median of per-round t_flann / t_kd)\n", ratios[0].fl);
  print_smallest_A(o, vars, row, ratios);
}

void run_set(const Options& o, const std::shared_ptr<Runtime>& rt, const std::string& set, int threads,
             std::ofstream* csv) {
  std::vector<float> pts, qs;
  if (!bench::load_set(o.data_dir, set, o.N, o.queries, pts, qs)) return;
  const std::size_t N = pts.size() / 3, n = qs.size() / 3;
  std::printf("\n# %s: N = %zu points, n = %zu queries\n", set.c_str(), N, n);
  if (N < o.N) std::printf("# %s: the file holds fewer than --N %zu points: all of them used\n", set.c_str(), o.N);

  // Every structure once.
  KdTreeIndex kd(rt, pts.data(), N);
  std::printf("# build kdtree  %7.3f s\n", kd.build_seconds());
  FlannParams fp;
  fp.threads = threads;
  FlannIndex fl(rt, pts.data(), N, fp);
  std::printf("# build flann   %7.3f s (%d threads)\n", fl.build_seconds(), fl.threads());
  std::vector<std::unique_ptr<BlockHashIndex>> bh;
  for (const auto& b : o.builds) {
    bh.push_back(BlockHashIndex::build(rt, pts.data(), N, b.params));
    std::printf("# build %-7s %7.3f s  %s\n", b.name.c_str(), bh.back()->build_seconds(),
                bh.back()->info().summary().c_str());
  }
  std::fflush(stdout);

  const QueryOrders orders = query_orders(o, qs);
  std::vector<Variant> vars = make_variants(o, kd, fl, bh);

  // Warm-up: kernel compiles (PoCL compiles at the first launch) never land in a timed run.
  // Reported per structure and defines variant (A and the swept search options share a kernel).
  std::vector<std::pair<std::string, double>> compiles;
  for (auto& v : vars)
    for (int k : o.ks) {
      SearchParams p = v.params;
      p.k = k;
      v.compile_s += v.index->warm_up(p);  // a recall-target variant tunes its A here, untimed
      if (const auto t = v.index->recall_tuning(p))  // the tuning warm_up cached
        std::printf("# %s k=%d: recall target %.3g -> A %g (sample recall %.4f on %zu queries%s, %.2f s)\n",
                    v.name.c_str(), k, p.recall_target, double(t->A), t->recall, t->sample,
                    t->reached ? "" : ", not reached", t->seconds);
    }
  for (const auto& v : vars) {
    const std::string label = v.method == "blockhash" ? v.build + "/" + v.defines_name : v.name;
    if (compiles.empty() || compiles.back().first != label) compiles.emplace_back(label, 0.0);
    compiles.back().second += v.compile_s;
  }
  std::printf("# compile (warm-up) s:");
  for (const auto& c : compiles) std::printf(" %s %.2f", c.first.c_str(), c.second);
  std::printf("\n");
  std::fflush(stdout);

  const std::vector<std::vector<KnnResult>> truth = truth_by_order(o, kd, fl, qs, orders.perm);
  const Cells cells = run_rounds(o, set, vars, orders.q, truth);
  for (std::size_t ki = 0; ki < o.ks.size(); ++ki)
    for (std::size_t oi = 0; oi < o.orders.size(); ++oi)
      report(o, *rt, {set, N, n, threads}, vars, cells[oi][ki], ki, oi, csv);
  if (csv) csv->flush();
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  Options o = parse(argc, argv);
  // FLANN and PoCL on the same thread count. PoCL reads POCL_MAX_PTHREAD_COUNT once, when the
  // device opens: set it from --threads when it is unset, warn when the two differ.
  const char* env = std::getenv("POCL_MAX_PTHREAD_COUNT");
  if (!o.threads) o.threads = env && std::atoi(env) > 0 ? std::atoi(env) : int(std::thread::hardware_concurrency());
  if (!env) setenv("POCL_MAX_PTHREAD_COUNT", std::to_string(o.threads).c_str(), 1);
  else if (std::atoi(env) != o.threads)
    std::fprintf(stderr, "perf_harness: warning: POCL_MAX_PTHREAD_COUNT=%s but --threads %d\n", env, o.threads);
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
#endif
  try {
    auto rt = std::make_shared<Runtime>(o.device);
    std::printf("# perf_harness: device %s; FLANN threads %d, POCL_MAX_PTHREAD_COUNT=%s; seed %llu\n",
                rt->info().summary().c_str(), o.threads, std::getenv("POCL_MAX_PTHREAD_COUNT"), o.seed);
    if (!o.baseline_defines.empty()) std::printf("# kdtree kernel defines: %s\n", o.baseline_defines.c_str());
    for (const auto& d : o.defines)
      if (!d.defines.empty()) std::printf("# defines %s: %s\n", d.name.c_str(), d.defines.c_str());
    std::unique_ptr<std::ofstream> csv;
    if (!o.csv.empty()) {
      csv = std::make_unique<std::ofstream>(o.csv, std::ios::trunc);
      if (!*csv) throw Error(o.csv + ": cannot open for writing");
      *csv << "data,N,n,k,order,variant,method,build,A,";
      for (const OptionInfo* s : o.sweep) *csv << s->name << ',';
      *csv << "defines_name,defines,device,threads,rounds,"
              "build_s,compile_s,qps_median,ratio_kd_median,ratio_flann_median,ratio_kd_min,ratio_kd_max,"
              "ratio_flann_min,ratio_flann_max,recall,fn_rate,max_dilation,mean_dilation\n";
    }
    for (const auto& set : o.data) run_set(o, rt, set, o.threads, csv.get());
    if (csv) std::printf("# rows written to %s\n", o.csv.c_str());
  } catch (const std::exception& e) {  // bhcl::Error and the rest (bad_alloc, ...)
    std::fprintf(stderr, "perf_harness: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
