// bhcl eval: runs a method and an exact one on the same points and queries, prints the accuracy
// metrics and both timings as one table (and JSON with --stats).
#include <cstdio>
#include <memory>
#include <string>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/metrics.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "commands.hpp"

namespace bhcl::cli {
namespace {

struct Side {
  std::unique_ptr<Index> index;
  KnnResult result;
  QueryStats stats;
  Accuracy accuracy;
};

Side run_side(const std::string& method, const std::shared_ptr<Runtime>& rt,
              const std::vector<float>& points, const std::vector<float>& queries,
              const SearchParams& params, const MethodOptions& mopt, bool quiet) {
  Side s;
  // The paper presets: B sized for the A and k asked (the talk's rule).
  s.index = build_with_progress(method, rt, points, method == "blockhash" ? paper_options_for_search(mopt, params) : mopt,
                                quiet);
  s.stats = query_with_progress(*s.index, queries, params, s.result, quiet);
  return s;
}

std::string fmt(const char* f, double v) {
  char b[64];
  std::snprintf(b, sizeof b, f, v);
  return b;
}

void declare_eval(Args& a) {
  declare_data_options(a, "the method evaluated: " + method_list(method_names()));
  a.add_text("truth", "the exact method giving the true neighbours: " + method_list(exact_method_names()),
             default_truth_method(), "NAME");
  declare_run_options(a, "write the metrics, timings and parameters here as JSON");
  a.group("Radius search");
  a.add_number("radius", "evaluate the radius search instead of kNN: every point within this Euclidean "
                         "distance of each query, against the truth's", "");
  a.group("");
}

// What both of eval's modes read (read_command_inputs), and the truth's method options: those
// of the method under test without saving or loading an index (they belong to the method under
// test; the truth shares the rest, e.g. --threads for flann).
struct EvalInputs {
  CommandInputs in;
  MethodOptions topt;
};
EvalInputs read_eval_inputs(const Args& args) {
  EvalInputs e{read_command_inputs(args, {}), {}};
  e.topt = e.in.mopt;
  e.topt.values.erase("load-index");
  e.topt.values.erase("save-index");
  return e;
}

// One side of a radius evaluation: its index, its answer and the call's statistics.
struct RadiusSide {
  std::unique_ptr<Index> index;
  RadiusResult result;
  QueryStats stats;
};

RadiusSide run_radius_side(const std::string& method, const std::shared_ptr<Runtime>& rt,
                           const std::vector<float>& points, const std::vector<float>& queries, float radius,
                           const RadiusParams& params, const MethodOptions& mopt, bool quiet) {
  RadiusSide s;
  s.index = build_with_progress(method, rt, points, mopt, quiet);
  s.stats = radius_with_progress(*s.index, queries, radius, params, s.result, quiet);
  return s;
}

// The radius table: the method beside the truth (whose accuracy is its own against itself).
void print_radius_table(const Runtime& rt, std::size_t N, std::size_t n, float radius, const RadiusParams& rp,
                        const RadiusSide& m, const RadiusSide& truth, const RadiusAccuracy& acc) {
  const RadiusAccuracy self = evaluate_radius_accuracy(truth.result, truth.result);
  const QueryStats &m_st = m.stats, &truth_st = truth.stats;
  std::printf("bhcl eval --radius on %s: N=%zu n=%zu r=%g budget=%u\n", rt.info().summary().c_str(), N, n,
              static_cast<double>(radius), rp.budget);
  const std::string truth_head = truth.index->method() + " (truth)";
  std::printf("%-22s %16s %16s\n", "", m.index->method().c_str(), truth_head.c_str());
  auto both = [&](const char* name, const char* f, double a, double b) {
    std::printf("%-22s %16s %16s\n", name, fmt(f, a).c_str(), fmt(f, b).c_str());
  };
  std::printf("%-22s %16s %16s\n", "exact", m.index->exact() ? "yes" : "no", "yes");
  both("build s", "%.4f", m.index->build_seconds(), truth.index->build_seconds());
  both("compile s", "%.4f", m_st.compile_s, truth_st.compile_s);
  both("query s", "%.4f", m_st.query_s, truth_st.query_s);
  both("wall s", "%.4f", m_st.wall_s, truth_st.wall_s);
  both("queries/s", "%.0f", m_st.queries_per_s(), truth_st.queries_per_s());
  both("points per query", "%.3f", acc.mean_found, self.mean_true);
  both("recall", "%.4f", acc.recall, self.recall);
  both("found of true points", "%.4f", acc.found_fraction, self.found_fraction);
  both("missing points", "%.0f", double(acc.missing), double(self.missing));
  both("false positives", "%.0f", double(acc.false_positives), double(self.false_positives));
  both("incomplete queries", "%.0f", double(acc.incomplete_queries), double(self.incomplete_queries));
  both("identical slices", "%.0f", double(acc.identical_slices), double(self.identical_slices));
  std::printf("query s: both passes' kernel time for device methods (compile, transfers and the host's sort "
              "of the slices apart), search wall time for host methods (flann); wall s: whole calls\n");
}

// bhcl eval --radius's stats file.
Json radius_eval_stats(const Args& args, const Runtime& rt, std::size_t N, std::size_t n, float radius,
                       const RadiusParams& rp, const RadiusSide& m, const MethodOptions& mopt, const RadiusSide& truth,
                       const RadiusAccuracy& acc) {
  const Index* index = m.index.get();
  const QueryStats &m_st = m.stats, &truth_st = truth.stats;
  Json j = stats_header("eval", rt);
  j["points"] = args.str("points");
  j["queries"] = args.str("queries");
  j["N"] = N;
  j["n"] = n;
  j["radius"] = radius;
  j["budget"] = rp.budget;
  j["method"] = index->method();
  j["exact"] = index->exact();
  j["build"] = build_json(*index, mopt);
  j["truth_method"] = truth.index->method();
  j["build_s"] = index->build_seconds();
  j["compile_s"] = m_st.compile_s;
  j["query_s"] = m_st.query_s;
  j["wall_s"] = m_st.wall_s;
  j["truth_query_s"] = truth_st.query_s;
  j["truth_wall_s"] = truth_st.wall_s;
  j["recall"] = acc.recall;
  j["found_fraction"] = acc.found_fraction;
  j["missing"] = acc.missing;
  j["false_positives"] = acc.false_positives;
  j["incomplete_queries"] = acc.incomplete_queries;
  j["identical_slices"] = acc.identical_slices;
  j["mean_found"] = acc.mean_found;
  j["mean_true"] = acc.mean_true;
  j["compared_queries"] = acc.queries;
  return j;
}

// bhcl eval --radius: both sides' radius searches, the points of each ball found.
int run_eval_radius(const Args& args, const std::string& method, const std::string& truth_method) {
  float radius = 0;
  const RadiusParams rp = radius_search_options(args, {method, truth_method}, radius);
  RadiusParams tp = rp;
  tp.budget = 0;  // the truth finds every point
  const EvalInputs e = read_eval_inputs(args);
  const auto& [mopt, points, queries, N, n, rt, beside] = e.in;
  const bool quiet = args.flag("quiet");
  const RadiusSide truth = run_radius_side(truth_method, rt, points, queries, radius, tp, e.topt, quiet);
  const RadiusSide m = run_radius_side(method, rt, points, queries, radius, rp, mopt, quiet);
  const RadiusAccuracy acc = evaluate_radius_accuracy(m.result, truth.result);
  print_radius_table(*rt, N, n, radius, rp, m, truth, acc);
  if (args.has("stats")) write_json(args.str("stats"), radius_eval_stats(args, *rt, N, n, radius, rp, m, mopt, truth, acc));
  return 0;
}

// The kNN table: each figure of the method beside the truth's.
void print_knn_table(const Runtime& rt, std::size_t N, std::size_t n, const SearchParams& params, const Side& m,
                     const Side& truth) {
  std::printf("bhcl eval on %s: N=%zu n=%zu k=%d max_radius=%g\n", rt.info().summary().c_str(), N,
              n, params.k, static_cast<double>(params.max_radius));
  const std::string truth_head = truth.index->method() + " (truth)";
  std::printf("%-22s %16s %16s\n", "", m.index->method().c_str(), truth_head.c_str());
  auto row = [&](const char* name, const std::string& a, const std::string& b) {
    std::printf("%-22s %16s %16s\n", name, a.c_str(), b.c_str());
  };
  auto both = [&](const char* name, const char* f, double a, double b) { row(name, fmt(f, a), fmt(f, b)); };
  auto acc = [&](const char* name, const char* f, double Accuracy::*field) {
    both(name, f, m.accuracy.*field, truth.accuracy.*field);
  };
  row("exact", m.index->exact() ? "yes" : "no", "yes");
  both("build s", "%.4f", m.index->build_seconds(), truth.index->build_seconds());
  both("compile s", "%.4f", m.stats.compile_s, truth.stats.compile_s);
  both("query s", "%.4f", m.stats.query_s, truth.stats.query_s);
  both("queries/s", "%.0f", m.stats.queries_per_s(), truth.stats.queries_per_s());
  both("memory MiB", "%.2f", m.index->memory_bytes() / 1048576.0, truth.index->memory_bytes() / 1048576.0);
  acc("recall", "%.4f", &Accuracy::recall);
  acc("false negatives", "%.4f", &Accuracy::false_negative_rate);
  acc("dilation max", "%.4f", &Accuracy::max_dilation);
  acc("dilation mean", "%.5f", &Accuracy::mean_dilation);
  acc("mean rel. dist. error", "%.2e", &Accuracy::mean_rel_distance_error);
  both("incomplete queries", "%.0f", double(m.accuracy.incomplete_queries), double(truth.accuracy.incomplete_queries));
  both("identical rows", "%.0f", double(m.accuracy.identical_rows), double(truth.accuracy.identical_rows));
  both("compared queries", "%.0f", double(m.accuracy.queries), double(truth.accuracy.queries));
  std::printf("query s: kernel time for device methods (compile and transfers apart), search wall "
              "time for host methods (flann)\n");
}

// One side's method, parameters and timings, each key prefixed ("" or "truth_").
void add_side_json(Json& j, const std::string& p, const Side& s, const MethodOptions& o, const SearchParams& params) {
  j[p + "method"] = s.index->method();
  j[p + "exact"] = s.index->exact();
  j[p + "build"] = build_json(*s.index, o);
  j[p + "search"] = search_json(*s.index, params);
  j[p + "build_s"] = s.index->build_seconds();
  j[p + "compile_s"] = s.stats.compile_s;
  j[p + "query_s"] = s.stats.query_s;
  j[p + "wall_s"] = s.stats.wall_s;
  j[p + "queries_per_s"] = s.stats.queries_per_s();
  j[p + "memory_bytes"] = s.index->memory_bytes();
}

// bhcl eval's stats file (kNN).
Json knn_eval_stats(const Args& args, const Runtime& rt, std::size_t N, std::size_t n, const SearchParams& params,
                    const Side& m, const MethodOptions& mopt, const Side& truth, const MethodOptions& topt) {
  Json j = stats_header("eval", rt);
  j.update(inputs_json(args, N, n, params));
  add_side_json(j, "", m, mopt, params);
  add_side_json(j, "truth_", truth, topt, params);
  j["recall"] = m.accuracy.recall;
  j["false_negative_rate"] = m.accuracy.false_negative_rate;
  j["max_dilation"] = m.accuracy.max_dilation;
  j["mean_dilation"] = m.accuracy.mean_dilation;
  j["mean_rel_distance_error"] = m.accuracy.mean_rel_distance_error;
  j["incomplete_queries"] = m.accuracy.incomplete_queries;
  j["identical_rows"] = m.accuracy.identical_rows;
  j["compared_queries"] = m.accuracy.queries;
  return j;
}

int run_eval(const Args& args) {
  const std::string method = args.str("method");
  const std::string truth_method = args.str("truth", default_truth_method());
  check_method_options(args, {method, truth_method});
  // Before any work: the truth must be an exact method (the registry says which are).
  if (!method_info(truth_method).exact)
    throw UsageError("--truth " + truth_method + " is not an exact method (" +
                     method_list(exact_method_names()) + ")");
  if (args.has("radius")) return run_eval_radius(args, method, truth_method);
  if (args.has("budget")) throw UsageError("--budget applies only with --radius");
  SearchParams params = search_params(args);
  const EvalInputs e = read_eval_inputs(args);
  const auto& [mopt, points, queries, N, n, rt, beside] = e.in;
  const MethodOptions& topt = e.topt;
  // The truth first: a bad --truth fails before the (possibly long) method run.
  Side truth = run_side(truth_method, rt, points, queries, params, topt, args.flag("quiet"));
  Side m = run_side(method, rt, points, queries, params, mopt, args.flag("quiet"));
  m.accuracy = evaluate_accuracy(m.result, truth.result);
  truth.accuracy = evaluate_accuracy(truth.result, truth.result);

  print_knn_table(*rt, N, n, params, m, truth);
  if (args.has("stats"))
    write_json(args.str("stats"), knn_eval_stats(args, *rt, N, n, params, m, mopt, truth, topt));
  return 0;
}

RegisterCommand reg_eval("eval", "a method against an exact one: accuracy metrics and timings",
                         declare_eval, run_eval);

}  // namespace
}  // namespace bhcl::cli
