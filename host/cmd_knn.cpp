// bhcl knn: k nearest neighbours (or, with --radius, every point within a radius) of every query
// of a point file, written as raw arrays.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <functional>

#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/multi_device.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "commands.hpp"
#include "knn_runner.hpp"
#include "progress.hpp"
#include "result_files.hpp"

namespace bhcl::cli {
void declare_knn_distributed(Args& a);      // cmd_knn_distributed.cpp: --distributed and its options
int run_knn_distributed(const Args& args);  // -1 unless --distributed, else the MPI run's status
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

RunQuery asked_query(const Args& args) {
  RunQuery q;
  if (args.has("radius")) {
    if (!args.has("out-offsets")) throw UsageError("--radius needs --out-offsets (where each query's results start)");
    q.radius = radius_search_options(args, {args.str("method")}, q.r);
    q.radius->max_results = static_cast<std::size_t>(args.integer("max-results", 0));
    return q;
  }
  for (const char* o : {"out-offsets", "max-results", "budget"})
    if (args.has(o)) throw UsageError(std::string("--") + o + " applies only with --radius");
  check_method_options(args, {args.str("method")});
  q.params = search_params(args);
  return q;
}

// --out-offsets only with --radius (asked_query refuses it otherwise).
std::vector<FileArg> knn_output_files(const Args& args) {
  return {{"--out-ids", args.str("out-ids")}, {"--out-dist2", args.str("out-dist2")},
          {"--out-offsets", args.str("out-offsets", "")}, {"--out-counts", args.str("out-counts", "")}};
}

namespace {

// A MultiDeviceIndex as the runner queries it: each device's share summed over the slices.
class SharesSummed final : public SearchThrough<MultiDeviceIndex> {
 public:
  using SearchThrough::SearchThrough;
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
  mutable std::vector<DeviceShare> shares_;
};

// Each device's share of the call: the summary line's tail and the stats file's "devices".
void add_shares(RunReport& r, const std::vector<DeviceShare>& shares) {
  Json devs = Json::array();
  char line[512];
  for (const DeviceShare& d : shares) {
    std::snprintf(line, sizeof line, "\n  %s: %zu queries (weight %.3f), query %.4f s", d.device.c_str(), d.queries,
                  d.weight, d.stats.query_s);
    r.note += line;
    devs.push_back({{"device", d.device}, {"queries", d.queries}, {"weight", d.weight},
                    {"query_s", d.stats.query_s}, {"wall_s", d.stats.wall_s}, {"compile_s", d.stats.compile_s}});
  }
  r.extra["devices"] = devs;
}

// bhcl knn --device a,b: one copy of the index per device (MultiDeviceIndex), the batch split by
// measured throughput, rows in the caller's order (kNN or --radius).
int run_knn_multi(const Args& args, const std::vector<std::string>& devices) {
  const std::string method = args.str("method");
  const RunQuery q = asked_query(args);
  MethodOptions mopt = method_options(args);
  if (!mopt.save_index().empty()) throw UsageError("--save-index does not apply with several devices");
  std::vector<FileArg> outputs = knn_output_files(args);
  outputs.push_back({"--stats", args.str("stats", "")});
  check_distinct_files({{"--points", args.str("points")}, {"--queries", args.str("queries")},
                        {"--load-index", mopt.load_index()}},
                       outputs);
  std::vector<float> points, queries;
  read_points_and_queries(args, points, queries);
  std::vector<std::shared_ptr<Runtime>> rts;
  for (const auto& spec : devices) rts.push_back(std::make_shared<Runtime>(spec));
  render::Progress build_bar("build " + method + " on " + std::to_string(devices.size()) + " devices",
                             !args.flag("quiet"));
  const auto t0 = std::chrono::steady_clock::now();
  MultiDeviceIndex index(rts, method, points.data(), points.size() / 3, mopt);
  const double build_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  build_bar.finish();
  const SharesSummed summed(index);
  RunPlace place;
  place.kind = IndexKind::devices;
  place.where = std::to_string(devices.size()) + " devices";
  const Answered a = answer(args, summed, place, queries, q);
  RunReport r;
  r.mopt = mopt;
  r.build_s = build_s;
  r.N = points.size() / 3;
  r.n = queries.size() / 3;
  add_shares(r, summed.shares());
  report(args, place, *rts.front(), summed, q, a, r);
  return 0;
}

// bhcl knn on one device: the index built (or loaded) there, kNN or --radius.
int run_knn_one_device(const Args& args) {
  const RunQuery q = asked_query(args);
  const std::string method = args.str("method");
  // kNN: the query's program built while the files are read (one thread reads, a core is idle),
  // not at the first query (10-30 ms from the program cache, beside the query's sort).
  std::function<void(const Runtime&, const MethodOptions&)> prepare;
  // With it, the direct outputs' slice buffers made present (on that core too; timed as the
  // write stage when the search made them: 48 MB, 5-7 ms at 1M x 10).
  if (!q.radius) prepare = [&](const Runtime& rt, const MethodOptions& o) {
    prepare_knn(method, rt, o, q.params);
    prefault_knn_outputs(args, q.params);
  };
  const CommandInputs in = read_command_inputs(args, knn_output_files(args), prepare);
  const auto& [mopt, points, queries, N, n, rt, beside] = in;
  // The paper presets: B sized for the A and k asked (the talk's rule).
  const MethodOptions bopt = !q.radius && method == "blockhash" ? paper_options_for_search(mopt, q.params) : mopt;
  auto index = build_with_progress(method, rt, points, bopt, args.flag("quiet"));
  RunPlace place;
  place.where = rt->info().device_name;
  Answered a = answer(args, *index, place, queries, q);
  // What was left of the program's build when the files were read is the search's, as the
  // query's own build was: counted in its compile and wall times.
  a.st.compile_s += beside.wait_s;
  a.st.wall_s += beside.wait_s;
  a.prepare_beside_s = beside.own_s;
  RunReport r;
  r.built = index.get();
  r.mopt = bopt;
  r.build_s = index->build_seconds();
  r.N = N;
  r.n = n;
  report(args, place, *rt, *index, q, a, r);
  return 0;
}

int run_knn(const Args& args) {
  if (const int rc = run_knn_distributed(args); rc >= 0) return rc;  // kNN or radius
  if (const std::string dev = args.str("device", ""); dev.find(',') != std::string::npos)
    return run_knn_multi(args, split_device_list(dev));
  return run_knn_one_device(args);
}

RegisterCommand reg_knn("knn", "k nearest neighbours of every query, written as raw arrays", declare_knn,
                        run_knn);

}  // namespace
}  // namespace bhcl::cli
