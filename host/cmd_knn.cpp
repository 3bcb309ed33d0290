// bhcl knn: k nearest neighbours (or, with --radius, every point within a radius) of every query
// of a point file, written as raw arrays.
#include <chrono>
#include <cmath>
#include <cstdio>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/multi_device.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "commands.hpp"
#include "progress.hpp"
#include "result_files.hpp"

namespace bhcl::cli {
void declare_knn_distributed(Args& a);      // cmd_knn_distributed.cpp: --distributed and its options
int run_knn_distributed(const Args& args);  // -1 unless --distributed, else the MPI run's status
RadiusParams radius_options(const Args& args, float& radius);  // --radius's options, checked
namespace {

void declare_knn(Args& a) {
  declare_data_options(a, method_list(method_names()));
  a.add_required("out-ids", "write the neighbour ids here (int32, n x k, row-major; with --radius "
                            "all slices one after the other; NPY when named .npy)");
  a.add_required("out-dist2", "write the squared distances here (float32, laid out as --out-ids; NPY "
                              "when named .npy)");
  a.add_text("out-counts", "write the neighbours found per query here (int32, n; NPY when named .npy)", "", "FILE");
  declare_run_options(a, "write timings and parameters here as JSON");
  a.group("Radius search");
  a.add_number("radius", "every point within this Euclidean distance of each query instead of the k "
                         "nearest (FAISS range_search layout: --out-offsets, --out-ids, --out-dist2, "
                         "each query's slice sorted by distance, then index)", "");
  a.add_text("out-offsets", "with --radius: query i's results are entries offsets[i] .. offsets[i+1] "
                            "of --out-ids and --out-dist2 (int64, n + 1; NPY when named .npy)", "", "FILE");
  a.add_integer("max-results", "with --radius: at most this many results per query, the nearest "
                               "(0: no cap; truncated queries are counted)", 0, Args::kNoLimit, "0");
  a.group("");
  declare_knn_distributed(a);
}

}  // namespace

// The radius-search options of bhcl knn, checked (also for --distributed: cmd_knn_distributed.cpp).
RadiusParams radius_options(const Args& args, float& radius) {
  if (!args.has("out-offsets")) throw UsageError("--radius needs --out-offsets (where each query's results start)");
  RadiusParams rp = radius_search_options(args, {args.str("method")}, radius);
  rp.max_results = static_cast<std::size_t>(args.integer("max-results", 0));
  return rp;
}

namespace {

// What bhcl knn's runner did.
struct Answered {
  QueryStats st;
  SearchParams params;  // kNN: the parameters the batch ran with (SearchIndex::params_for_batch)
  BatchTuning bt;       // kNN: what params_for_batch did
  double write_s = 0;         // kNN: the output files' appends, inside the query call's wall time
  double commit_s = 0;        // kNN: their flush to the disk and renames, after it
  std::size_t found = 0;      // neighbours found, or radius results
  std::size_t truncated = 0;  // radius: queries cut at --max-results
};

// bhcl knn's one runner, over any SearchIndex (an Index, or the copies of a MultiDeviceIndex):
// kNN with the batch's parameters (block hashing: a recall target, or the block layouts' default
// one, tuned on a sample of these queries, not on the index's own points) or, with
// `radius_params`, radius search; in slices (a progress bar on a terminal), each slice's rows
// written as it finishes (no second copy of the result), renamed in place at the end: a failure
// leaves the old files and no temporary. Results do not depend on the slicing.
Answered answer(const Args& args, const SearchIndex& index, const std::vector<float>& queries,
                const SearchParams& params, const RadiusParams* radius_params, float radius) {
  const std::size_t n = queries.size() / 3;
  const bool quiet = args.flag("quiet");
  Answered a;
  if (radius_params) {
    RadiusOutputs files(args, n);
    a.st = radius_in_slices(index, queries, radius, *radius_params, quiet,
                            [&](std::size_t, const RadiusResult& part) { files.append(part); });
    files.commit();
    a.found = files.total();
    a.truncated = files.truncated_queries();
  } else {
    a.params = index.params_for_batch(queries.data(), n, params, &a.bt);
    KnnOutputs files(args, n, a.params.k);
    a.st = query_in_slices(index, queries, a.params, quiet, [&](std::size_t, const KnnResult& part) {
      const auto t0 = std::chrono::steady_clock::now();
      files.append(part);
      a.write_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    });
    const auto t0 = std::chrono::steady_clock::now();
    files.commit();  // after the wall time: the files' flush to the disk and their renames
    a.commit_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    a.found = files.found();
  }
  return a;
}

// A MultiDeviceIndex as the runner queries it: each device's share summed over the slices.
class SharesSummed final : public SearchIndex {
 public:
  explicit SharesSummed(const MultiDeviceIndex& index) : index_(index) {}
  std::string method() const override { return index_.method(); }
  bool exact() const override { return index_.exact(); }
  std::size_t size() const override { return index_.size(); }
  SearchParams params_for_batch(const float* queries, std::size_t n, const SearchParams& params,
                                BatchTuning* info = nullptr) const override {
    return index_.params_for_batch(queries, n, params, info);
  }
  QueryStats query(const float* queries, std::size_t n, const SearchParams& params,
                   KnnResult& out) const override {
    std::vector<DeviceShare> s;
    const QueryStats st = index_.query(queries, n, params, out, &s);
    add(s);
    return st;
  }
  QueryStats radius_search(const float* queries, std::size_t n, float r, const RadiusParams& params,
                           RadiusResult& out) const override {
    std::vector<DeviceShare> s;
    const QueryStats st = index_.radius_search(queries, n, r, params, out, &s);
    add(s);
    return st;
  }
  const std::vector<DeviceShare>& shares() const { return shares_; }

 private:
  void add(const std::vector<DeviceShare>& s) const {
    if (shares_.empty()) {
      shares_ = s;
      return;
    }
    for (std::size_t d = 0; d < s.size() && d < shares_.size(); ++d) {
      shares_[d].queries += s[d].queries;
      shares_[d].weight = s[d].weight;  // the latest split
      shares_[d].stats.add_slice(s[d].stats);
      shares_[d].stats.wall_s += s[d].stats.wall_s;
    }
  }
  const MultiDeviceIndex& index_;
  mutable std::vector<DeviceShare> shares_;
};

// bhcl knn --radius: Index::radius_search in slices (a progress bar on a terminal), the slices
// concatenated (results do not depend on the slicing).
int run_radius(const Args& args) {
  const std::string method = args.str("method");
  float radius = 0;
  const RadiusParams rp = radius_options(args, radius);
  const std::string out_offsets = args.str("out-offsets"), out_ids = args.str("out-ids"),
                    out_dist2 = args.str("out-dist2");
  const CommandInputs in = read_command_inputs(
      args, {{"--out-offsets", out_offsets}, {"--out-ids", out_ids}, {"--out-dist2", out_dist2},
             {"--out-counts", args.str("out-counts", "")}});
  const auto& [mopt, points, queries, N, n, rt] = in;
  const bool quiet = args.flag("quiet");
  auto index = build_with_progress(method, rt, points, mopt, quiet);
  const Answered a = answer(args, *index, queries, {}, &rp, radius);
  const QueryStats& st = a.st;
  const std::size_t total = a.found, truncated = a.truncated;
  std::fprintf(stderr,
               "bhcl knn --radius: %s on %s: N=%zu n=%zu r=%g  build %.3f s  compile %.3f s  query %.4f s "
               "(%.0f q/s)  results %zu (%.2f per query)  truncated queries %zu\n",
               index->method().c_str(), rt->info().device_name.c_str(), N, n, radius,
               index->build_seconds(), st.compile_s, st.query_s, st.queries_per_s(), total,
               n ? double(total) / double(n) : 0.0, truncated);
  if (args.has("stats")) {
    Json j = stats_header("knn", *rt);
    j["method"] = index->method();
    j["exact"] = index->exact();
    j["points"] = args.str("points");
    j["queries"] = args.str("queries");
    j["N"] = N;
    j["n"] = n;
    j["build"] = build_json(*index, mopt);
    j["radius"] = {{"radius", radius}, {"max_results", rp.max_results}};
    j["radius"].update(table_values(args, method, OptionInfo::Radius));
    j["radius"]["results"] = total;
    j["radius"]["truncated_queries"] = truncated;
    add_query_stats(j, *index, st);
    j["memory_bytes"] = index->memory_bytes();
    write_json(args.str("stats"), j);
  }
  return 0;
}

// bhcl knn --device a,b: one copy of the index per device (MultiDeviceIndex), the batch split by
// measured throughput, rows in the caller's order (kNN or --radius).
int run_knn_multi(const Args& args, const std::vector<std::string>& devices) {
  const std::string method = args.str("method");
  const bool radius_mode = args.has("radius");
  float radius = 0;
  RadiusParams rp;
  SearchParams params;
  if (radius_mode) {
    rp = radius_options(args, radius);
  } else {
    for (const char* o : {"out-offsets", "max-results", "budget"})
      if (args.has(o)) throw UsageError(std::string("--") + o + " applies only with --radius");
    check_method_options(args, {method});
    params = search_params(args);
  }
  MethodOptions mopt = method_options(args);
  if (!mopt.save_index().empty()) throw UsageError("--save-index does not apply with several devices");
  const std::string out_ids = args.str("out-ids"), out_dist2 = args.str("out-dist2");
  check_distinct_files({{"--points", args.str("points")}, {"--queries", args.str("queries")},
                        {"--load-index", mopt.load_index()}},
                       {{"--out-ids", out_ids}, {"--out-dist2", out_dist2},
                        {"--out-offsets", args.str("out-offsets", "")},
                        {"--out-counts", args.str("out-counts", "")}, {"--stats", args.str("stats", "")}});
  std::vector<float> points, queries;
  read_points_and_queries(args, points, queries);
  const std::size_t N = points.size() / 3, n = queries.size() / 3;
  std::vector<std::shared_ptr<Runtime>> rts;
  for (const auto& spec : devices) rts.push_back(std::make_shared<Runtime>(spec));
  const bool quiet = args.flag("quiet");
  render::Progress build_bar("build " + method + " on " + std::to_string(devices.size()) + " devices", !quiet);
  MultiDeviceIndex index(rts, method, points.data(), N, mopt);
  build_bar.finish();
  const SharesSummed summed(index);
  const Answered a = answer(args, summed, queries, params, radius_mode ? &rp : nullptr, radius);
  const QueryStats& st = a.st;
  const std::size_t found = a.found;
  const std::vector<DeviceShare>& shares = summed.shares();
  std::fprintf(stderr, "bhcl knn%s: %s on %zu devices: N=%zu n=%zu  query %.4f s (slowest part)  %s %zu\n",
               radius_mode ? " --radius" : "", method.c_str(), devices.size(), N, n, st.query_s,
               radius_mode ? "results" : "neighbours found", found);
  for (const DeviceShare& d : shares)
    std::fprintf(stderr, "  %s: %zu queries (weight %.3f), query %.4f s\n", d.device.c_str(), d.queries,
                 d.weight, d.stats.query_s);
  if (args.has("stats")) {
    Json j = stats_header("knn", *rts.front());
    j["method"] = method;
    j["exact"] = index.exact();
    j["N"] = N;
    j["n"] = n;
    if (radius_mode)
      j["radius"] = {{"radius", radius}, {"max_results", rp.max_results}, {"budget", rp.budget}, {"results", found}};
    else
      j["k"] = params.k;
    Json devs = Json::array();
    for (const DeviceShare& d : shares)
      devs.push_back({{"device", d.device}, {"queries", d.queries}, {"weight", d.weight},
                      {"query_s", d.stats.query_s}, {"wall_s", d.stats.wall_s}, {"compile_s", d.stats.compile_s}});
    j["devices"] = devs;
    j["query_s"] = st.query_s;
    j["wall_s"] = st.wall_s;
    j["nonfinite_queries"] = st.nonfinite_queries;
    write_json(args.str("stats"), j);
  }
  return 0;
}

int run_knn(const Args& args) {
  if (const int rc = run_knn_distributed(args); rc >= 0) return rc;  // kNN or radius
  if (const std::string dev = args.str("device", ""); dev.find(',') != std::string::npos)
    return run_knn_multi(args, split_device_list(dev));
  if (args.has("radius")) return run_radius(args);
  for (const char* o : {"out-offsets", "max-results", "budget"})
    if (args.has(o)) throw UsageError(std::string("--") + o + " applies only with --radius");
  const std::string method = args.str("method");
  check_method_options(args, {method});
  const std::string out_ids = args.str("out-ids");
  const std::string out_dist2 = args.str("out-dist2");
  SearchParams params = search_params(args);
  const CommandInputs in = read_command_inputs(
      args, {{"--out-ids", out_ids}, {"--out-dist2", out_dist2}, {"--out-counts", args.str("out-counts", "")}});
  const auto& [mopt, points, queries, N, n, rt] = in;
  const bool quiet = args.flag("quiet");
  // The paper presets: B sized for the A and k asked (the talk's rule).
  const MethodOptions bopt = method == "blockhash" ? paper_options_for_search(mopt, params) : mopt;
  auto index = build_with_progress(method, rt, points, bopt, quiet);
  const Answered a = answer(args, *index, queries, params, nullptr, 0);
  params = a.params;
  const BatchTuning& bt = a.bt;
  const QueryStats& st = a.st;
  const std::size_t found = a.found;
  std::fprintf(stderr,
               "bhcl knn: %s on %s: N=%zu n=%zu k=%d  build %.3f s  compile %.3f s  query %.4f s "
               "(%.0f q/s)  neighbours found %zu\n",
               index->method().c_str(), rt->info().device_name.c_str(), N, n, params.k,
               index->build_seconds(), st.compile_s, st.query_s, st.queries_per_s(), found);
  if (args.has("stats")) {
    Json j = stats_header("knn", *rt);
    j["method"] = index->method();
    j["exact"] = index->exact();
    j.update(inputs_json(args, N, n, params));
    j["build"] = build_json(*index, bopt);
    j["search"] = search_json(*index, params);
    if (bt.tuned)
      j["search"]["tuning"] = {{"recall_target", bt.target}, {"A", bt.tuning.A}, {"tuned_on", "queries"},
                               {"sample", bt.tuning.sample}, {"sample_recall", bt.tuning.recall},
                               {"reached", bt.tuning.reached}, {"cached", bt.cached},
                               {"distribution", bt.distribution}, {"seconds", bt.seconds},
                               {"compile_s", bt.compile_s}};
    add_query_stats(j, *index, st);
    j["stages"] = stages_json(st, a.write_s, a.commit_s);
    j["neighbours_found"] = found;
    j["memory_bytes"] = index->memory_bytes();
    write_json(args.str("stats"), j);
  }
  return 0;
}

RegisterCommand reg_knn("knn", "k nearest neighbours of every query, written as raw arrays", declare_knn,
                        run_knn);

}  // namespace
}  // namespace bhcl::cli
