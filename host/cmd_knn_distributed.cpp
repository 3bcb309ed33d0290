// bhcl knn --distributed: the knn command over an MPI job (mpirun -np R bhcl knn ... --distributed),
// answered by bhcl::DistributedIndex. Rank 0 reads --points and --queries and passes them all to
// the index, which shards the points by Hilbert-key range and routes the queries; rank 0 gets
// every row back and writes the outputs. MPI is initialised here, only in this mode.
#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/runtime.hpp"
#include "cli.hpp"
#include "commands.hpp"
#include "result_files.hpp"

#if BHCL_HAVE_MPI
#include "blockhash_cl/distributed.hpp"
#endif

namespace bhcl::cli {

void declare_knn_distributed(Args& a) {
  a.group("Distributed (MPI)");
  a.add_flag("distributed", "answer over an MPI job (mpirun -np R bhcl knn ... --distributed): rank 0 "
                            "reads the files and writes the results, the points are sharded over the "
                            "ranks by Hilbert-key range; exact methods give the single-process result");
  a.add_integer("boxes-per-rank", "with --distributed: the boxes each rank shares to route queries", 1,
                1024, "16");
  a.add_number("border-factor", "with --distributed, blockhash: a query meeting other ranks is answered "
                                "again by its owner with this times A (1: not again)", "2");
  a.add_integer("id-base", "with --distributed: the global id of the first point (ids are this plus the "
                           "point's place); ids past 2^31 - 1 are written as int64 (NPY '<i8', 8 bytes raw)",
                0, std::int64_t(1) << 62, "0");
  a.group("");
}

RadiusParams radius_options(const Args& args, float& radius);  // cmd_knn.cpp: --radius's options

#if !BHCL_HAVE_MPI

int run_knn_distributed(const Args& args) {
  for (const char* o : {"boxes-per-rank", "border-factor", "id-base"})
    if (args.has(o)) throw UsageError(std::string("--") + o + " needs --distributed");
  if (!args.flag("distributed")) return -1;
  throw Error("--distributed: this bhcl was built without MPI (install libopenmpi-dev and configure "
              "with BHCL_WITH_MPI=ON)");
}

#else

namespace {

// MPI_Init on entry (unless the program did it already), MPI_Finalize on exit, so that the
// other commands never start MPI.
class MpiSession {
 public:
  MpiSession() {
    int done = 0;
    MPI_Initialized(&done);
    if (!done) {
      int provided = 0;
      MPI_Init_thread(nullptr, nullptr, MPI_THREAD_FUNNELED, &provided);
      owned_ = true;
    }
  }
  ~MpiSession() {
    int done = 0;
    MPI_Finalized(&done);
    if (owned_ && !done) MPI_Finalize();
  }
  MpiSession(const MpiSession&) = delete;
  MpiSession& operator=(const MpiSession&) = delete;

 private:
  bool owned_ = false;
};

// Per-rank figures gathered on rank 0 (a JSON array in rank order there; empty elsewhere).
Json gathered(double v, int rank, int ranks) {
  std::vector<double> all(static_cast<std::size_t>(ranks));
  MPI_Gather(&v, 1, MPI_DOUBLE, all.data(), 1, MPI_DOUBLE, 0, MPI_COMM_WORLD);
  Json j = Json::array();
  if (rank == 0)
    for (double x : all) j.push_back(x);
  return j;
}

// The query calls of a distributed run: rank 0 holds every query, so it tells every rank n and
// the slice size, and every rank makes the same calls, rank 0 passing slice s of its queries and
// the others none.
std::size_t g_n_global = 0, g_slice_rows = 1;
std::size_t slice_count() { return g_n_global == 0 ? 1 : (g_n_global + g_slice_rows - 1) / g_slice_rows; }
std::pair<std::size_t, std::size_t> slice_of(std::size_t s, std::size_t n, int rank) {
  if (rank != 0) return {0, 0};
  const std::size_t first = std::min(n, s * g_slice_rows);
  return {first, std::min(g_slice_rows, n - first)};
}
// One slice's statistics into the run's (sums; the per-query vectors are not kept: the tool
// reports their sums).
std::size_t ds_visits = 0;
void add_distributed_stats(QueryStats& st, DistributedQueryStats& ds, const QueryStats& ps,
                           const DistributedQueryStats& pds) {
  st.n_queries += ps.n_queries;
  st.nonfinite_queries += ps.nonfinite_queries;
  st.batches += ps.batches;
  st.compile_s += ps.compile_s;
  st.upload_s += ps.upload_s;
  st.query_s += ps.query_s;
  st.download_s += ps.download_s;
  st.wall_s += ps.wall_s;
  ds.multi_rank_queries += pds.multi_rank_queries;
  ds.owner_sent += pds.owner_sent;
  ds.owner_received += pds.owner_received;
  ds.extra_sent += pds.extra_sent;
  ds.extra_received += pds.extra_received;
  ds.reanswered += pds.reanswered;
  ds.answered += pds.answered;
  ds.bytes_sent += pds.bytes_sent;
  ds.bytes_received += pds.bytes_received;
  ds.phase1_s += pds.phase1_s;
  ds.phase2_s += pds.phase2_s;
  for (auto v : pds.ranks_visited) ds_visits += static_cast<std::size_t>(v);
}

}  // namespace

int run_knn_distributed(const Args& args) {
  for (const char* o : {"boxes-per-rank", "border-factor", "id-base"})
    if (args.has(o) && !args.flag("distributed")) throw UsageError(std::string("--") + o + " needs --distributed");
  if (!args.flag("distributed")) return -1;

  // Usage checks before MPI: every rank sees the same command line and fails alike.
  const std::string method = args.str("method");
  const bool radius_mode = args.has("radius");
  float radius = 0;
  RadiusParams rparams;
  if (radius_mode) rparams = radius_options(args, radius);  // checks the method options too
  else check_method_options(args, {method});
  const std::string out_ids = args.str("out-ids");
  const std::string out_dist2 = args.str("out-dist2");
  SearchParams params = search_params(args);
  MethodOptions mopt = method_options(args);
  if (!mopt.load_index().empty() || !mopt.save_index().empty())
    throw UsageError("--load-index and --save-index do not apply with --distributed (each rank builds its shard)");
  check_distinct_files({{"--points", args.str("points")}, {"--queries", args.str("queries")}},
                       {{"--out-ids", out_ids}, {"--out-dist2", out_dist2},
                        {"--out-counts", args.str("out-counts", "")}, {"--stats", args.str("stats", "")},
                        {"--out-offsets", args.str("out-offsets", "")}});
  DistributedBuildParams bp;
  bp.method = method;
  bp.options = mopt;
  bp.boxes_per_rank = static_cast<int>(args.integer("boxes-per-rank", 16));
  bp.border_factor = static_cast<float>(args.number("border-factor", 2.0));
  bp.id_base = static_cast<std::int64_t>(args.integer("id-base", 0));
  if (args.has("border-factor") && method_info(method).exact)
    throw UsageError("--border-factor does not apply to method " + method + " (only to approximate methods)");
  if (!(bp.border_factor >= 1 && bp.border_factor <= 1024))
    throw UsageError("--border-factor must be in [1, 1024], got " + args.str("border-factor"));

  MpiSession mpi;
  try {
  int rank = 0, ranks = 1;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  MPI_Comm_size(MPI_COMM_WORLD, &ranks);
  const std::string what = "bhcl knn --distributed";

  // Rank 0 reads; every rank learns whether it could.
  std::vector<float> points, queries;
  std::string err;
  if (rank == 0) try {
      read_points_and_queries(args, points, queries);
    } catch (const std::exception& e) {
      err = e.what();
    }
  mpi_agree(MPI_COMM_WORLD, err, what);
  std::shared_ptr<Runtime> rt;
  try {
    rt = std::make_shared<Runtime>(args.str("device", ""));
  } catch (const std::exception& e) {
    err = e.what();
  }
  mpi_agree(MPI_COMM_WORLD, err, what);

  DistributedIndex index(MPI_COMM_WORLD, rt, points.data(), points.size() / 3, bp);
  const std::size_t N = index.size(), n = queries.size() / 3;
  {
    // Rank 0's n (the others hold none) and its slice size: radius slices of 2^18 queries (their
    // results are known only after the search), kNN slices of about 256 MiB of rows.
    std::uint64_t v[2] = {n, radius_mode ? std::min<std::uint64_t>(std::uint64_t(1) << 18, std::max<std::size_t>(n, 1))
                                         : knn_slice_rows(n, params.k, params.count_examined, false)};
    if (radius_mode && rank == 0)
      if (const char* e = std::getenv("BHCL_SLICE_ROWS"); e && *e) v[1] = knn_slice_rows(n, 1, false, false);
    MPI_Bcast(v, 2, MPI_UINT64_T, 0, MPI_COMM_WORLD);
    g_n_global = static_cast<std::size_t>(v[0]);
    g_slice_rows = std::max<std::size_t>(1, static_cast<std::size_t>(v[1]));
  }
  std::vector<float>().swap(points);
  if (radius_mode) {
    // Radius search: rank 0's queries, the slices written there (FAISS layout, as bhcl knn --radius).
    // In slices (every rank calls each; the others pass none), each written on rank 0 as it
    // comes back (RadiusOutputs): the whole result is never held there.
    DistributedQueryStats rds;
    QueryStats rst;
    std::unique_ptr<RadiusOutputs> files;
    if (rank == 0) try {
        files = std::make_unique<RadiusOutputs>(args, n, !index.ids_fit_int32());
      } catch (const std::exception& e) {
        err = e.what();
      }
    mpi_agree(MPI_COMM_WORLD, err, what);
    const std::size_t slices = slice_count();
    for (std::size_t s = 0; s < slices; ++s) {
      const auto [first, m] = slice_of(s, n, rank);
      RadiusResult64 part;
      DistributedQueryStats pds;
      const QueryStats ps = index.radius_search(queries.data() + 3 * first, m, radius, rparams, part, &pds);
      add_distributed_stats(rst, rds, ps, pds);
      if (rank == 0 && err.empty()) try {
          files->append(part);
        } catch (const std::exception& e) {
          err = e.what();  // told to every rank after the last slice
        }
    }
    std::size_t rank_total = 0, rank_truncated = 0;
    if (rank == 0 && err.empty()) try {
        files->commit();
        rank_total = files->total();
        rank_truncated = files->truncated_queries();
      } catch (const std::exception& e) {
        err = e.what();
      }
    files.reset();  // a failed write: the temporaries removed
    mpi_agree(MPI_COMM_WORLD, err, what);
    if (rank == 0) try {
        const std::size_t total = rank_total, truncated = rank_truncated;
        std::fprintf(stderr,
                     "bhcl knn --distributed --radius: %s on %d rank(s): N=%zu n=%zu r=%g  build %.3f s  "
                     "query %.3f s  queries on more than one rank %zu (%.1f %%)  results %zu  truncated %zu\n",
                     index.method().c_str(), ranks, N, n, double(radius), index.build_stats().wall_s, rst.wall_s,
                     rds.multi_rank_queries, n ? 100.0 * double(rds.multi_rank_queries) / double(n) : 0.0,
                     total, truncated);
        if (args.has("stats")) {
          Json j = stats_header("knn", *rt);
          j["method"] = index.method();
          j["exact"] = index.exact();
          j["N"] = N;
          j["n"] = n;
          j["radius"] = {{"radius", radius}, {"max_results", rparams.max_results}, {"budget", rparams.budget},
                         {"results", total}, {"truncated_queries", truncated}};
          j["build_s"] = index.build_stats().wall_s;
          j["wall_s"] = rst.wall_s;
          j["nonfinite_queries"] = rst.nonfinite_queries;
          j["distributed"] = {{"ranks", ranks}, {"multi_rank_queries", rds.multi_rank_queries}};
          write_json(args.str("stats"), j);
        }
      } catch (const std::exception& e) {
        err = e.what();
      }
    mpi_agree(MPI_COMM_WORLD, err, what);
    return 0;
  }
  // In slices (every rank calls each; the others pass none), each written on rank 0 as it comes
  // back (KnnOutputs): the whole result is never held there.
  DistributedQueryStats ds;
  QueryStats st;
  std::unique_ptr<KnnOutputs> files;
  if (rank == 0) try {
      files = std::make_unique<KnnOutputs>(args, n, params.k, !index.ids_fit_int32());
    } catch (const std::exception& e) {
      err = e.what();
    }
  mpi_agree(MPI_COMM_WORLD, err, what);
  std::size_t found = 0;
  {
    const std::size_t slices = slice_count();
    for (std::size_t s = 0; s < slices; ++s) {
      const auto [first, m] = slice_of(s, n, rank);
      KnnResult64 part;
      DistributedQueryStats pds;
      const QueryStats ps = index.query(queries.data() + 3 * first, m, params, part, &pds);
      add_distributed_stats(st, ds, ps, pds);
      if (rank == 0 && err.empty()) try {
          files->append(part);
        } catch (const std::exception& e) {
          err = e.what();  // told to every rank after the last slice
        }
    }
    if (rank == 0 && err.empty()) try {
        files->commit();
        found = files->found();
      } catch (const std::exception& e) {
        err = e.what();
      }
    files.reset();  // a failed write: the temporaries removed
    mpi_agree(MPI_COMM_WORLD, err, what);
  }

  // Per-rank figures gathered on rank 0 (every rank takes part in the gathers).
  const DistributedBuildStats& bs = index.build_stats();
  Json shard_points = gathered(double(bs.shard_points), rank, ranks);
  Json points_received = gathered(double(bs.points_received), rank, ranks);
  Json queries_received = gathered(double(ds.owner_received + ds.extra_received), rank, ranks);
  Json answered = gathered(double(ds.answered), rank, ranks);
  Json build_s = gathered(bs.build_s, rank, ranks);
  Json query_s = gathered(st.query_s, rank, ranks);
  Json compile_s = gathered(st.compile_s, rank, ranks);

  // Rank 0 writes; a failure there fails every rank.
  if (rank == 0) try {
      const std::size_t visits = ds_visits;
      std::fprintf(stderr,
                   "bhcl knn --distributed: %s on %d rank(s) (%s on rank 0): N=%zu n=%zu k=%d  build %.3f s  "
                   "query %.3f s  queries on more than one rank %zu (%.1f %%)  neighbours found %zu\n",
                   index.method().c_str(), ranks, rt->info().device_name.c_str(), N, n, params.k,
                   bs.wall_s, st.wall_s, ds.multi_rank_queries,
                   n ? 100.0 * double(ds.multi_rank_queries) / double(n) : 0.0, found);
      if (args.has("stats")) {
        Json j = stats_header("knn", *rt);
        j["method"] = index.method();
        j["exact"] = index.exact();
        j.update(inputs_json(args, N, n, params));
        if (index.local_index()) {
          // Rank 0's local index: parameters every rank derives the same way from its own shard.
          j["build"] = build_json(*index.local_index(), mopt);
          j["search"] = search_json(*index.local_index(), params);
        }
        j["build_s"] = bs.wall_s;
        j["wall_s"] = st.wall_s;
        j["nonfinite_queries"] = st.nonfinite_queries;
        j["neighbours_found"] = found;
        Json d;
        d["ranks"] = ranks;
        d["input"] = "rank 0 reads the files and passes every point and query";
        d["boxes_per_rank"] = bp.boxes_per_rank;
        d["border_factor"] = bp.border_factor;
        d["balance"] = bs.balance;
        d["multi_rank_queries"] = ds.multi_rank_queries;
        d["mean_ranks_visited"] = n ? double(visits) / double(n) : 0.0;
        d["reanswered_queries"] = ds.reanswered;
        d["phase1_s"] = ds.phase1_s;
        d["phase2_s"] = ds.phase2_s;
        d["per_rank"] = {{"shard_points", shard_points},   {"points_received", points_received},
                         {"queries_received", queries_received}, {"queries_answered", answered},
                         {"build_s", build_s},             {"query_s", query_s},
                         {"compile_s", compile_s}};
        j["distributed"] = d;
        write_json(args.str("stats"), j);
      }
    } catch (const std::exception& e) {
      err = e.what();
    }
  mpi_agree(MPI_COMM_WORLD, err, what);
  return 0;
  } catch (const std::exception& e) {
    // mpirun kills every rank at the first non-zero exit: each rank prints its message first and
    // waits (a bounded while, never a hang when a rank failed alone) until all have printed.
    std::fprintf(stderr, "bhcl knn: error: %s\n", e.what());
    std::fflush(stderr);
    MPI_Request req;
    if (MPI_Ibarrier(MPI_COMM_WORLD, &req) == MPI_SUCCESS) {
      int done = 0;
      const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(10);
      while (!done && std::chrono::steady_clock::now() < until) {
        MPI_Test(&req, &done, MPI_STATUS_IGNORE);
        if (!done) std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
      // A rank that failed alone: the others will not come; end the job rather than hang.
      if (!done) MPI_Abort(MPI_COMM_WORLD, 1);
    }
    return 1;
  }
}

#endif

}  // namespace bhcl::cli
