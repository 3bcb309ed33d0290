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

// This rank in the job, and the error it holds for the next agree(): every rank learns there
// whether any failed (mpi_agree throws on every rank when one did).
struct Job {
  int rank = 0, ranks = 1;
  std::string err;
  void agree() const { mpi_agree(MPI_COMM_WORLD, err, "bhcl knn --distributed"); }
  // f(), its exception kept as err (told to every rank at the next agree()).
  template <typename F>
  void attempt(F&& f) {
    try {
      f();
    } catch (const std::exception& e) {
      err = e.what();
    }
  }
};

// What the command line asks of a distributed run, checked before MPI starts: every rank sees
// the same command line and fails alike.
struct DistributedRun {
  std::string method;
  bool radius_mode = false;
  float radius = 0;
  RadiusParams rparams;
  SearchParams params;
  MethodOptions mopt;
  DistributedBuildParams bp;
};

DistributedRun distributed_options(const Args& args) {
  DistributedRun run;
  const std::string& method = run.method = args.str("method");
  run.radius_mode = args.has("radius");
  if (run.radius_mode) run.rparams = radius_options(args, run.radius);  // checks the method options too
  else check_method_options(args, {method});
  const std::string out_ids = args.str("out-ids");
  const std::string out_dist2 = args.str("out-dist2");
  run.params = search_params(args);
  run.mopt = method_options(args);
  if (!run.mopt.load_index().empty() || !run.mopt.save_index().empty())
    throw UsageError("--load-index and --save-index do not apply with --distributed (each rank builds its shard)");
  check_distinct_files({{"--points", args.str("points")}, {"--queries", args.str("queries")}},
                       {{"--out-ids", out_ids}, {"--out-dist2", out_dist2},
                        {"--out-counts", args.str("out-counts", "")}, {"--stats", args.str("stats", "")},
                        {"--out-offsets", args.str("out-offsets", "")}});
  DistributedBuildParams& bp = run.bp;
  bp.method = method;
  bp.options = run.mopt;
  bp.boxes_per_rank = static_cast<int>(args.integer("boxes-per-rank", 16));
  bp.border_factor = static_cast<float>(args.number("border-factor", 2.0));
  bp.id_base = static_cast<std::int64_t>(args.integer("id-base", 0));
  if (args.has("border-factor") && method_info(method).exact)
    throw UsageError("--border-factor does not apply to method " + method + " (only to approximate methods)");
  if (!(bp.border_factor >= 1 && bp.border_factor <= 1024))
    throw UsageError("--border-factor must be in [1, 1024], got " + args.str("border-factor"));
  return run;
}

// Rank 0 reads the files, every rank opens its device; every rank learns whether all could.
std::shared_ptr<Runtime> read_inputs(const Args& args, Job& job, std::vector<float>& points,
                                     std::vector<float>& queries) {
  if (job.rank == 0) job.attempt([&] { read_points_and_queries(args, points, queries); });
  job.agree();
  std::shared_ptr<Runtime> rt;
  job.attempt([&] { rt = std::make_shared<Runtime>(args.str("device", "")); });
  job.agree();
  return rt;
}

// The query calls of a distributed run: rank 0 holds every query, so it tells every rank n and
// the slice size, and every rank makes the same calls, rank 0 passing slice s of its queries and
// the others none.
struct Slices {
  std::size_t n_global = 0, rows = 1;
  std::size_t count() const { return n_global == 0 ? 1 : (n_global + rows - 1) / rows; }
  // Slice s of this rank's n queries: (first, count).
  std::pair<std::size_t, std::size_t> of(std::size_t s, std::size_t n, int rank) const {
    if (rank != 0) return {0, 0};
    const std::size_t first = std::min(n, s * rows);
    return {first, std::min(rows, n - first)};
  }
};

// Rank 0's n (the others hold none) and its slice size: radius slices of 2^18 queries (their
// results are known only after the search), kNN slices of about 256 MiB of rows.
Slices agree_slices(std::size_t n, const DistributedRun& run, int rank) {
  std::uint64_t v[2] = {n, run.radius_mode ? std::min<std::uint64_t>(std::uint64_t(1) << 18, std::max<std::size_t>(n, 1))
                                           : knn_slice_rows(n, run.params.k, run.params.count_examined, false)};
  if (run.radius_mode && rank == 0)
    if (const char* e = std::getenv("BHCL_SLICE_ROWS"); e && *e) v[1] = knn_slice_rows(n, 1, false, false);
  MPI_Bcast(v, 2, MPI_UINT64_T, 0, MPI_COMM_WORLD);
  return {static_cast<std::size_t>(v[0]), std::max<std::size_t>(1, static_cast<std::size_t>(v[1]))};
}

// The slices' statistics summed (the per-query vectors are not kept: the tool reports their sums).
struct Totals {
  QueryStats st;
  DistributedQueryStats ds;
  std::size_t visits = 0;  // ranks visited, summed over this rank's queries

  void add(const QueryStats& ps, const DistributedQueryStats& pds) {
    st.n_queries += ps.n_queries;
    st.wall_s += ps.wall_s;
    st.add_slice(ps);
    using D = DistributedQueryStats;
    for (std::size_t D::*count : {&D::multi_rank_queries, &D::owner_sent, &D::owner_received, &D::extra_sent,
                                  &D::extra_received, &D::reanswered, &D::answered, &D::bytes_sent, &D::bytes_received})
      ds.*count += pds.*count;
    for (double D::*seconds : {&D::phase1_s, &D::phase2_s}) ds.*seconds += pds.*seconds;
    for (auto v : pds.ranks_visited) visits += static_cast<std::size_t>(v);
  }
};

// Every slice through `search` (each rank calls it for each; the others pass none), each written
// on rank 0 as it comes back (`Outputs`: KnnOutputs or RadiusOutputs), so that the whole result is
// never held there; a failure there is told to every rank after the last slice. `done` reads the
// committed files' counts on rank 0.
template <typename Outputs, typename Part, typename Search, typename Done>
void answer_in_slices(Job& job, const Slices& slices, std::size_t n, std::unique_ptr<Outputs> files,
                      Totals& t, const Search& search, const Done& done) {
  for (std::size_t s = 0; s < slices.count(); ++s) {
    const auto [first, m] = slices.of(s, n, job.rank);
    Part part;
    DistributedQueryStats pds;
    const QueryStats ps = search(first, m, part, pds);
    t.add(ps, pds);
    if (job.rank == 0 && job.err.empty()) job.attempt([&] { files->append(part); });
  }
  if (job.rank == 0 && job.err.empty())
    job.attempt([&] {
      files->commit();
      done(*files);
    });
  files.reset();  // a failed write: the temporaries removed
  job.agree();
}

// Radius search: rank 0's queries, the slices written there (FAISS layout, as bhcl knn --radius).
int run_radius(const Args& args, Job& job, const DistributedIndex& index, const DistributedRun& run,
               const std::vector<float>& queries, const Slices& slices, const Runtime& rt) {
  const std::size_t N = index.size(), n = queries.size() / 3;
  std::unique_ptr<RadiusOutputs> files;
  if (job.rank == 0) job.attempt([&] { files = std::make_unique<RadiusOutputs>(args, n, !index.ids_fit_int32()); });
  job.agree();
  Totals t;
  std::size_t total = 0, truncated = 0;
  answer_in_slices<RadiusOutputs, RadiusResult64>(
      job, slices, n, std::move(files), t,
      [&](std::size_t first, std::size_t m, RadiusResult64& part, DistributedQueryStats& pds) {
        return index.radius_search(queries.data() + 3 * first, m, run.radius, run.rparams, part, &pds);
      },
      [&](const RadiusOutputs& f) {
        total = f.total();
        truncated = f.truncated_queries();
      });
  const QueryStats& rst = t.st;
  const DistributedQueryStats& rds = t.ds;
  if (job.rank == 0) job.attempt([&] {
      std::fprintf(stderr,
                   "bhcl knn --distributed --radius: %s on %d rank(s): N=%zu n=%zu r=%g  build %.3f s  "
                   "query %.3f s  queries on more than one rank %zu (%.1f %%)  results %zu  truncated %zu\n",
                   index.method().c_str(), job.ranks, N, n, double(run.radius), index.build_stats().wall_s,
                   rst.wall_s, rds.multi_rank_queries, n ? 100.0 * double(rds.multi_rank_queries) / double(n) : 0.0,
                   total, truncated);
      if (!args.has("stats")) return;
      Json j = stats_header("knn", rt);
      j["method"] = index.method();
      j["exact"] = index.exact();
      j["N"] = N;
      j["n"] = n;
      j["radius"] = {{"radius", run.radius}, {"max_results", run.rparams.max_results},
                     {"budget", run.rparams.budget}, {"results", total}, {"truncated_queries", truncated}};
      j["build_s"] = index.build_stats().wall_s;
      j["wall_s"] = rst.wall_s;
      j["nonfinite_queries"] = rst.nonfinite_queries;
      j["distributed"] = {{"ranks", job.ranks}, {"multi_rank_queries", rds.multi_rank_queries}};
      write_json(args.str("stats"), j);
    });
  job.agree();
  return 0;
}

// Per-rank figures gathered on rank 0 (every rank takes part in the gathers).
Json per_rank_json(const Job& job, const DistributedBuildStats& bs, const Totals& t) {
  const auto all = [&](double v) { return gathered(v, job.rank, job.ranks); };
  Json j = Json::object();
  j["shard_points"] = all(double(bs.shard_points));
  j["points_received"] = all(double(bs.points_received));
  j["queries_received"] = all(double(t.ds.owner_received + t.ds.extra_received));
  j["queries_answered"] = all(double(t.ds.answered));
  j["build_s"] = all(bs.build_s);
  j["query_s"] = all(t.st.query_s);
  j["compile_s"] = all(t.st.compile_s);
  return j;
}

// The kNN stats file (rank 0).
Json knn_stats(const Args& args, const Job& job, const DistributedIndex& index, const DistributedRun& run,
               const Runtime& rt, std::size_t n, const Totals& t, std::size_t found, Json per_rank) {
  const DistributedBuildStats& bs = index.build_stats();
  const std::size_t N = index.size();
  Json j = stats_header("knn", rt);
  j["method"] = index.method();
  j["exact"] = index.exact();
  j.update(inputs_json(args, N, n, run.params));
  if (index.local_index()) {
    // Rank 0's local index: parameters every rank derives the same way from its own shard.
    j["build"] = build_json(*index.local_index(), run.mopt);
    j["search"] = search_json(*index.local_index(), run.params);
  }
  j["build_s"] = bs.wall_s;
  j["wall_s"] = t.st.wall_s;
  j["nonfinite_queries"] = t.st.nonfinite_queries;
  j["neighbours_found"] = found;
  Json d;
  d["ranks"] = job.ranks;
  d["input"] = "rank 0 reads the files and passes every point and query";
  d["boxes_per_rank"] = run.bp.boxes_per_rank;
  d["border_factor"] = run.bp.border_factor;
  d["balance"] = bs.balance;
  d["multi_rank_queries"] = t.ds.multi_rank_queries;
  d["mean_ranks_visited"] = n ? double(t.visits) / double(n) : 0.0;
  d["reanswered_queries"] = t.ds.reanswered;
  d["phase1_s"] = t.ds.phase1_s;
  d["phase2_s"] = t.ds.phase2_s;
  d["per_rank"] = std::move(per_rank);
  j["distributed"] = d;
  return j;
}

// kNN: rank 0's queries, the rows written there; the per-rank figures gathered for the stats.
int run_knn(const Args& args, Job& job, const DistributedIndex& index, const DistributedRun& run,
            const std::vector<float>& queries, const Slices& slices, const Runtime& rt) {
  const std::size_t N = index.size(), n = queries.size() / 3;
  std::unique_ptr<KnnOutputs> files;
  if (job.rank == 0)
    job.attempt([&] { files = std::make_unique<KnnOutputs>(args, n, run.params.k, !index.ids_fit_int32()); });
  job.agree();
  Totals t;
  std::size_t found = 0;
  answer_in_slices<KnnOutputs, KnnResult64>(
      job, slices, n, std::move(files), t,
      [&](std::size_t first, std::size_t m, KnnResult64& part, DistributedQueryStats& pds) {
        return index.query(queries.data() + 3 * first, m, run.params, part, &pds);
      },
      [&](const KnnOutputs& f) { found = f.found(); });
  Json per_rank = per_rank_json(job, index.build_stats(), t);
  // Rank 0 writes; a failure there fails every rank.
  if (job.rank == 0) job.attempt([&] {
      std::fprintf(stderr,
                   "bhcl knn --distributed: %s on %d rank(s) (%s on rank 0): N=%zu n=%zu k=%d  build %.3f s  "
                   "query %.3f s  queries on more than one rank %zu (%.1f %%)  neighbours found %zu\n",
                   index.method().c_str(), job.ranks, rt.info().device_name.c_str(), N, n, run.params.k,
                   index.build_stats().wall_s, t.st.wall_s, t.ds.multi_rank_queries,
                   n ? 100.0 * double(t.ds.multi_rank_queries) / double(n) : 0.0, found);
      if (args.has("stats")) write_json(args.str("stats"), knn_stats(args, job, index, run, rt, n, t, found, per_rank));
    });
  job.agree();
  return 0;
}

// mpirun kills every rank at the first non-zero exit: each rank prints its message first and
// waits (a bounded while, never a hang when a rank failed alone) until all have printed.
int fail_every_rank(const std::exception& e) {
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

}  // namespace

int run_knn_distributed(const Args& args) {
  for (const char* o : {"boxes-per-rank", "border-factor", "id-base"})
    if (args.has(o) && !args.flag("distributed")) throw UsageError(std::string("--") + o + " needs --distributed");
  if (!args.flag("distributed")) return -1;
  const DistributedRun run = distributed_options(args);

  MpiSession mpi;
  try {
    Job job;
    MPI_Comm_rank(MPI_COMM_WORLD, &job.rank);
    MPI_Comm_size(MPI_COMM_WORLD, &job.ranks);
    std::vector<float> points, queries;
    const std::shared_ptr<Runtime> rt = read_inputs(args, job, points, queries);
    const DistributedIndex index(MPI_COMM_WORLD, rt, points.data(), points.size() / 3, run.bp);
    const Slices slices = agree_slices(queries.size() / 3, run, job.rank);
    std::vector<float>().swap(points);
    if (run.radius_mode) return run_radius(args, job, index, run, queries, slices, *rt);
    return run_knn(args, job, index, run, queries, slices, *rt);
  } catch (const std::exception& e) {
    return fail_every_rank(e);
  }
}

#endif

}  // namespace bhcl::cli
