// update_bench: points added and removed without a fresh build (Index::insert/remove, issue 23).
//  1. Cost, per method: inserting 1 % and 10 % of N and removing 10 %, each against a fresh build
//     of the whole resulting set, in interleaved rounds in one process (fresh build, update, next
//     method...), the median of the per-round ratios (the machine is shared and noisy). With
//     nanoflann's header present, its KDTreeSingleIndexDynamicAdaptor (a logarithmic forest of
//     static trees) against its static KDTreeSingleIndexAdaptor the same way.
//  2. Block hashing's grid after the set grows 10x in 100 inserts, then after half of it is
//     removed in 10 removes: recall@k at the same A and query speed against a fresh build over the
//     same live points (truth: the exact grid mode of the fresh build, ids mapped).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <stdexcept>
#include <fstream>
#include <memory>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "bench_util.hpp"
#include "nanoflann_cloud.hpp"
#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/datasets.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/metrics.hpp"
#include "blockhash_cl/runtime.hpp"

using namespace bhcl;

namespace {

using bench::now_s;

#if BHCL_HAVE_NANOFLANN
using bench::Cloud;
using bench::NfDynamic;
using bench::NfStatic;
#endif

struct Op {
  const char* name;
  double frac;
  bool insert;
};
// insert 25%: past the grid's retune band (as 900k + 100k is), where an update is a full build:
// it must still cost no more than a fresh build of its result (issue 39).
const Op kOps[] = {{"insert 1%", 0.01, true}, {"insert 10%", 0.10, true}, {"remove 10%", 0.10, false}, {"insert 25%", 0.25, true}};
constexpr int kNumOps = int(sizeof kOps / sizeof kOps[0]);

struct Options {
  std::size_t N = 1000000, n_queries = 20000;
  int rounds = 5, k = 10;
  float A = 2;
  std::string data = "uniform", methods_arg = "blockhash,kdtree,bruteforce,flann", csv;
  std::string ops_arg = "insert-1,insert-10,remove-10,insert-25";
  bool skip_cost = false, skip_growth = false, no_nanoflann = false, stats = false;
};

std::vector<int> selected_ops(const std::string& arg);

// Parses the command line (CLI11's own messages and exit codes; `rc` >= 0: exit with it).
Options parse(int argc, char** argv, int& rc) {
  Options o;
  CLI::App app("update_bench: cost of Index::insert/remove against fresh builds, and block hashing's grid after growth and removal");
  app.add_option("--N", o.N, "points")->check(CLI::Range(std::size_t(1000), std::size_t(100000000)));
  app.add_option("--queries", o.n_queries, "queries of the growth study")->check(CLI::Range(std::size_t(100), std::size_t(10000000)));
  app.add_option("--rounds", o.rounds, "interleaved rounds (cost: the median of per-round ratios)")->check(CLI::Range(1, 100));
  app.add_option("--k", o.k, "neighbours")->check(CLI::Range(1, kMaxK));
  app.add_option("--A", o.A, "block hashing's budget factor of the growth study")->check(CLI::Range(0.5f, 1000.0f));
  app.add_option("--data", o.data, "a generated set (uniform, clustered, cornell, ...)");
  app.add_option("--methods", o.methods_arg, "methods of the cost study, comma separated (blockhash-tables: auto's L tables, grid=0)");
  app.add_option("--csv", o.csv, "also write the figures here");
  app.add_option("--ops", o.ops_arg, "operations of the cost study, comma separated (insert-1, insert-10, remove-10, insert-25)");
  app.add_flag("--stats", o.stats, "block hashing: print the build stats of each fresh build and update (stderr)");
  app.add_flag("--no-nanoflann", o.no_nanoflann, "leave nanoflann's dynamic adaptor out of the cost study (profiling one method)");
  app.add_flag("--skip-cost", o.skip_cost, "only the growth study");
  app.add_flag("--skip-growth", o.skip_growth, "only the cost study");
  rc = -1;
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    rc = app.exit(e);
    return o;
  }
  try {
    selected_ops(o.ops_arg);  // named now, before any set is made
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s\n", e.what());
    rc = 2;
  }
  return o;
}

// N points plus the 25 % the largest insert adds, in a random order, so that a prefix is a uniform sample
// of the set (some sets are generated in spatial order).
std::vector<float> shuffled_set(const std::string& data, std::size_t N) {
  std::vector<float> all = datasets::by_name(data, N + N / 4, 1);
  std::vector<std::size_t> perm(all.size() / 3);
  std::iota(perm.begin(), perm.end(), 0);
  std::shuffle(perm.begin(), perm.end(), std::mt19937_64(3));
  std::vector<float> sh(all.size());
  for (std::size_t i = 0; i < perm.size(); ++i)
    for (int d = 0; d < 3; ++d) sh[3 * i + d] = all[3 * perm[i] + d];
  return sh;
}

std::vector<std::string> split_list(const std::string& arg) {
  std::vector<std::string> items;
  for (std::size_t a = 0; a <= arg.size();) {
    std::size_t b = arg.find(',', a);
    if (b == std::string::npos) b = arg.size();
    if (b > a) items.push_back(arg.substr(a, b - a));
    a = b + 1;
  }
  return items;
}

std::vector<std::string> split_methods(const std::string& methods_arg, bool no_nanoflann) {
  std::vector<std::string> methods = split_list(methods_arg);
#if BHCL_HAVE_NANOFLANN
  if (!no_nanoflann) methods.push_back("nanoflann-dynamic");
#else
  std::printf("# nanoflann.hpp not found: its dynamic adaptor skipped (Debian: libnanoflann-dev)\n");
#endif
  return methods;
}

// The operations --ops names ("insert 10%" as insert-10), in kOps' order; an unknown name is an error.
std::vector<int> selected_ops(const std::string& arg) {
  std::vector<int> ops;
  for (const std::string& name : split_list(arg)) {
    int found = -1;
    for (int op = 0; op < kNumOps; ++op) {
      std::string key = kOps[op].name;
      std::replace(key.begin(), key.end(), ' ', '-');
      key.erase(std::remove(key.begin(), key.end(), '%'), key.end());
      if (key == name) found = op;
    }
    if (found < 0) throw std::runtime_error("update_bench: --ops: unknown operation '" + name + "'");
    ops.push_back(found);
  }
  std::sort(ops.begin(), ops.end());
  return ops;
}

// The cost study's sets: all (the first N, then the inserted ones), the ids a remove drops and the
// points kept after it (in id order).
struct CostSets {
  const std::vector<float>& all;
  std::size_t N;
  std::vector<std::int32_t> drop;
  std::vector<float> kept;
};

CostSets cost_sets(const std::vector<float>& all, std::size_t N) {
  CostSets c{all, N, std::vector<std::int32_t>(N / 10), {}};
  {
    std::vector<std::int32_t> ids(N);
    std::iota(ids.begin(), ids.end(), 0);
    std::shuffle(ids.begin(), ids.end(), std::mt19937_64(5));
    std::copy(ids.begin(), ids.begin() + c.drop.size(), c.drop.begin());
  }
  std::vector<char> gone(N, 0);
  for (auto id : c.drop) gone[std::size_t(id)] = 1;
  for (std::size_t i = 0; i < N; ++i)
    if (!gone[i]) c.kept.insert(c.kept.end(), all.begin() + 3 * i, all.begin() + 3 * i + 3);
  return c;
}

// One method's fresh build of the set after `op` and the update that makes it: (fresh_s, update_s).
std::pair<double, double> time_op(const std::string& method, const Op& op, const CostSets& c,
                                  const std::shared_ptr<Runtime>& rt, bool stats) {
  const std::size_t N = c.N, m = static_cast<std::size_t>(op.frac * double(N));
  const std::size_t n_after = op.insert ? N + m : N - m;
  const float* after = op.insert ? c.all.data() : c.kept.data();
  double tf = 0, tu = 0;
#if BHCL_HAVE_NANOFLANN
  if (method == "nanoflann-dynamic") {
    Cloud cf{&(op.insert ? c.all : c.kept), n_after};
    double t0 = now_s();
    NfStatic fresh(3, cf, nanoflann::KDTreeSingleIndexAdaptorParams(10));
    fresh.buildIndex();
    tf = now_s() - t0;
    Cloud cd{&c.all, N};
    NfDynamic dyn(3, cd, nanoflann::KDTreeSingleIndexAdaptorParams(10));
    t0 = now_s();
    if (op.insert) {
      cd.n = N + m;  // the adaptor keeps a reference to the dataset: it now sees the new points
      dyn.addPoints(N, N + m - 1);
    } else {
      for (auto id : c.drop) dyn.removePoint(std::size_t(id));
    }
    tu = now_s() - t0;
    return {tf, tu};
  }
#endif
  MethodOptions mo;
  std::string name = method;
  if (method == "blockhash-tables") {
    name = "blockhash";
    mo.set("grid", "0");  // auto's L tables
  }
  double t0 = now_s();
  auto fresh = make_index(name, rt, after, n_after, mo);
  tf = now_s() - t0;
  auto say = [&](const char* what, const Index& ix) {
    if (!stats) return;
    if (const auto* bh = dynamic_cast<const BlockHashIndex*>(&ix))
      std::fprintf(stderr, "# %s %s: %s  merges %zu rebuilds %zu retunes %zu holes %zu update %.4f s\n", op.name, what,
                   bh->info().summary().c_str(), bh->info().merges, bh->info().update_rebuilds, bh->info().retunes,
                   bh->info().holes, bh->info().t_update);
  };
  say("fresh", *fresh);
  fresh.reset();
  auto ix = make_index(name, rt, c.all.data(), N, mo);
  t0 = now_s();
  if (op.insert) ix->insert(c.all.data() + 3 * N, m);
  else ix->remove(c.drop.data(), c.drop.size());
  tu = now_s() - t0;
  say("updated", *ix);
  return {tf, tu};
}

// 1. Each method's inserts and remove against fresh builds, in interleaved rounds.
void cost_study(const Options& o, const std::shared_ptr<Runtime>& rt, const std::vector<float>& all, std::FILE* out) {
  const std::size_t N = o.N;
  const std::vector<std::string> methods = split_methods(o.methods_arg, o.no_nanoflann);
  const std::vector<int> ops = selected_ops(o.ops_arg);
  // ratios[method][op] over rounds, and the times
  std::vector<std::vector<std::vector<double>>> ratio(methods.size(), std::vector<std::vector<double>>(kNumOps)),
      fresh_t = ratio, upd_t = ratio;
  const CostSets c = cost_sets(all, N);
  for (int r = 0; r < o.rounds; ++r) {
    for (std::size_t mi = 0; mi < methods.size(); ++mi)
      for (int op : ops) {
        const auto [tf, tu] = time_op(methods[mi], kOps[op], c, rt, o.stats);
        ratio[mi][op].push_back(tu / tf);
        fresh_t[mi][op].push_back(tf);
        upd_t[mi][op].push_back(tu);
      }
    std::fprintf(stderr, "# round %d done\n", r + 1);
  }
  std::printf("\n## Cost of an update against a fresh build of the resulting set (N = %zu, median of %d interleaved rounds)\n", N, o.rounds);
  std::printf("%-20s %-11s %10s %10s %8s\n", "method", "op", "fresh_s", "update_s", "ratio");
  for (std::size_t mi = 0; mi < methods.size(); ++mi)
    for (int op : ops) {
      const double f = bench::median(fresh_t[mi][op]), u = bench::median(upd_t[mi][op]), q = bench::median(ratio[mi][op]);
      std::printf("%-20s %-11s %10.4f %10.4f %8.3f\n", methods[mi].c_str(), kOps[op].name, f, u, q);
      if (out) std::fprintf(out, "cost,%s,%s,%.6f,%.6f,%.4f\n", methods[mi].c_str(), kOps[op].name, f, u, q);
    }
}

// 2. Block hashing's grid, updated, against a fresh build over the same live points.
struct GrowthStudy {
  const Options& o;
  const std::shared_ptr<Runtime>& rt;
  std::FILE* out;
  BlockHashIndex& ix;  // the updated index
  std::vector<float> qs;

  // Recall at the same A against the exact answer over the live points (ids: the live points'
  // ids in ix) and query speed, updated against fresh; one line per stage.
  void compare(const char* stage, const std::vector<float>& live, const std::vector<std::int32_t>& ids) const {
    const int k = o.k;
    const float A = o.A;
    const auto fresh_owned = BlockHashIndex::build(rt, live.data(), ids.size());
    BlockHashIndex& fresh = *fresh_owned;
    SearchParams exact;
    exact.k = k;
    exact.A = INFINITY;
    KnnResult truth = fresh.query(qs, exact);
    for (auto& id : truth.ids)
      if (id >= 0) id = ids[std::size_t(id)];
    SearchParams sp;
    sp.k = k;
    sp.A = A;
    fresh.warm_up(sp);
    ix.warm_up(sp);
    std::vector<double> qf, qu;
    KnnResult rf, ru;
    for (int r = 0; r < std::max(3, o.rounds); ++r) {  // interleaved
      QueryStats a = fresh.query(qs.data(), qs.size() / 3, sp, rf);
      QueryStats b = ix.query(qs.data(), qs.size() / 3, sp, ru);
      qf.push_back(a.query_s);
      qu.push_back(b.query_s);
    }
    for (auto& id : rf.ids)
      if (id >= 0) id = ids[std::size_t(id)];
    const double recall_f = evaluate_accuracy(rf, truth).recall, recall_u = evaluate_accuracy(ru, truth).recall;
    std::vector<double> speed;  // per round: updated queries/s over fresh queries/s
    for (std::size_t r = 0; r < qf.size(); ++r) speed.push_back(qf[r] / qu[r]);
    const double sp_ratio = bench::median(speed);
    std::printf("%-28s N %9zu  A %.3g k %d  recall fresh %.4f updated %.4f (diff %+.4f)  query_s fresh %.4f updated %.4f  speed ratio %.3f\n",
                stage, ids.size(), double(A), k, recall_f, recall_u, recall_u - recall_f, bench::median(qf),
                bench::median(qu), sp_ratio);
    std::printf("    updated: %s\n    holes %zu merges %zu compactions %zu rebuilds %zu retunes %zu\n", ix.info().summary().c_str(),
                ix.info().holes, ix.info().merges, ix.info().compactions, ix.info().update_rebuilds, ix.info().retunes);
    std::printf("    fresh:   %s\n", fresh.info().summary().c_str());
    if (out)
      std::fprintf(out, "growth,blockhash,%s recall_fresh %.4f recall_updated %.4f,%.6f,%.6f,%.4f\n", stage, recall_f,
                   recall_u, bench::median(qf), bench::median(qu), sp_ratio);
  }
};

// Grows from N/10 to N in 100 inserts, compared at a quarter, half and three quarters of the
// growth (a state just after a retune equals a fresh build; the others show the band the cells
// drift in) and at the end.
void grow(const GrowthStudy& g, const std::vector<float>& all, std::size_t n0, double t_first) {
  const std::size_t N = g.o.N;
  double t_ins = 0;
  std::size_t at = n0;
  std::vector<std::int32_t> ids(N);
  std::iota(ids.begin(), ids.end(), 0);
  std::printf("\n## Block hashing's grid grown 10x in 100 inserts (%zu -> %zu points)\n", n0, N);
  for (int s = 0; s < 100; ++s) {
    const std::size_t to = n0 + (N - n0) * std::size_t(s + 1) / 100;
    const double t0 = now_s();
    g.ix.insert(all.data() + 3 * at, to - at);
    t_ins += now_s() - t0;
    at = to;
    if ((s + 1) % 25 == 0 && s + 1 < 100) {
      const std::string stage = "growth step " + std::to_string(s + 1);
      g.compare(stage.c_str(), std::vector<float>(all.begin(), all.begin() + 3 * to),
                std::vector<std::int32_t>(ids.begin(), ids.begin() + to));
    }
  }
  std::printf("# build of the first %zu: %.3f s; the 100 inserts: %.3f s in all\n", n0, t_first, t_ins);
  g.compare("after growth 10x", std::vector<float>(all.begin(), all.begin() + 3 * N), ids);
}

// Then removes half, in 10 removes of random ids, compared after 5 and after all 10.
void shrink(const GrowthStudy& g, const std::vector<float>& all) {
  const std::size_t N = g.o.N;
  std::vector<std::int32_t> order(N);
  std::iota(order.begin(), order.end(), 0);
  std::shuffle(order.begin(), order.end(), std::mt19937_64(17));
  double t_rem = 0;
  std::printf("\n## Then half removed in 10 removes\n");
  for (int s = 0; s < 10; ++s) {
    const std::size_t a = N / 2 * std::size_t(s) / 10, b = N / 2 * std::size_t(s + 1) / 10;
    const double t0 = now_s();
    g.ix.remove(order.data() + a, b - a);
    t_rem += now_s() - t0;
    if (s == 4 || s == 9) {
      std::vector<char> gone(N, 0);
      for (std::size_t i = 0; i < b; ++i) gone[std::size_t(order[i])] = 1;
      std::vector<float> live;
      std::vector<std::int32_t> live_ids;
      for (std::size_t i = 0; i < N; ++i)
        if (!gone[i]) {
          live.insert(live.end(), all.begin() + 3 * i, all.begin() + 3 * i + 3);
          live_ids.push_back(std::int32_t(i));
        }
      g.compare(s == 4 ? "a quarter removed" : "after half removed", live, live_ids);
    }
  }
  std::printf("# the 10 removes: %.3f s in all\n", t_rem);
}

void growth_study(const Options& o, const std::shared_ptr<Runtime>& rt, const std::vector<float>& all, std::FILE* out) {
  const std::size_t n0 = o.N / 10;
  const double t0 = now_s();
  const auto ix_owned = BlockHashIndex::build(rt, all.data(), n0);
  BlockHashIndex& ix = *ix_owned;
  const double t_first = now_s() - t0;
  const GrowthStudy g{o, rt, out, ix, datasets::queries_by_name(o.data, o.n_queries, 2)};
  grow(g, all, n0, t_first);
  shrink(g, all);
}

}  // namespace

int main(int argc, char** argv) {
  int rc = -1;
  const Options o = parse(argc, argv, rc);
  if (rc >= 0) return rc;
  auto rt = default_runtime();
  std::printf("# update_bench  N %zu  data %s  rounds %d  device %s\n", o.N, o.data.c_str(), o.rounds,
              rt->info().summary().c_str());
  const std::vector<float> all = shuffled_set(o.data, o.N);
  std::FILE* out = o.csv.empty() ? nullptr : std::fopen(o.csv.c_str(), "w");
  if (out) std::fprintf(out, "study,method,op,fresh_s,update_s,ratio\n");
  if (!o.skip_cost) cost_study(o, rt, all, out);
  if (!o.skip_growth) growth_study(o, rt, all, out);
  if (out) std::fclose(out);
  return 0;
}
