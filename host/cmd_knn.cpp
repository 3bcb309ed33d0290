// bhcl knn: k nearest neighbours of every query of a point file, written as raw arrays.
#include <cstdio>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "commands.hpp"

namespace bhcl::cli {
void declare_knn_distributed(Args& a);      // cmd_knn_distributed.cpp: --distributed and its options
int run_knn_distributed(const Args& args);  // -1 unless --distributed, else the MPI run's status
namespace {

void declare_knn(Args& a) {
  declare_data_options(a, method_list(method_names()));
  a.add_required("out-ids", "write the neighbour ids here (int32, n x k, row-major; NPY when named .npy)");
  a.add_required("out-dist2", "write the squared distances here (float32, n x k, row-major; NPY when named .npy)");
  a.add_text("out-counts", "write the neighbours found per query here (int32, n; NPY when named .npy)", "", "FILE");
  declare_run_options(a, "write timings and parameters here as JSON");
  declare_knn_distributed(a);
}

int run_knn(const Args& args) {
  if (const int rc = run_knn_distributed(args); rc >= 0) return rc;
  const std::string method = args.str("method");
  check_method_options(args, {method});
  const std::string out_ids = args.str("out-ids");
  const std::string out_dist2 = args.str("out-dist2");
  SearchParams params = search_params(args);
  MethodOptions mopt = method_options(args);
  check_distinct_files({{"--points", args.str("points")}, {"--queries", args.str("queries")},
                        {"--load-index", mopt.load_index}},
                       {{"--out-ids", out_ids}, {"--out-dist2", out_dist2},
                        {"--out-counts", args.str("out-counts", "")}, {"--stats", args.str("stats", "")},
                        {"--save-index", mopt.save_index}});

  std::vector<float> points, queries;
  read_points_and_queries(args, points, queries);
  const std::size_t N = points.size() / 3, n = queries.size() / 3;

  auto rt = std::make_shared<Runtime>(args.str("device", ""));
  const bool quiet = args.flag("quiet");
  auto index = build_with_progress(method, rt, points, mopt, quiet);
  KnnResult result;
  QueryStats st = query_with_progress(*index, queries, params, result, quiet);

  write_array_file(out_ids, result.ids.data(), n, static_cast<std::size_t>(params.k));
  write_array_file(out_dist2, result.dist2.data(), n, static_cast<std::size_t>(params.k));
  if (args.has("out-counts")) write_array_file(args.str("out-counts"), result.counts.data(), n, 0);

  std::size_t found = 0;
  for (auto c : result.counts) found += static_cast<std::size_t>(c);
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
    j["build"] = build_json(*index, mopt);
    j["search"] = search_json(*index, params);
    j["build_s"] = index->build_seconds();
    j["compile_s"] = st.compile_s;
    j["query_s"] = st.query_s;
    j["upload_s"] = st.upload_s;
    j["download_s"] = st.download_s;
    j["wall_s"] = st.wall_s;
    j["queries_per_s"] = st.queries_per_s();
    j["batches"] = st.batches;
    j["nonfinite_queries"] = st.nonfinite_queries;
    j["neighbours_found"] = found;
    j["memory_bytes"] = index->memory_bytes();
    write_json(args.str("stats"), j);
  }
  return 0;
}

RegisterCommand reg("knn", "k nearest neighbours of every query, written as raw arrays", declare_knn,
                    run_knn);

}  // namespace
}  // namespace bhcl::cli
