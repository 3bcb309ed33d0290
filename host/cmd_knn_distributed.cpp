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
#include "knn_runner.hpp"
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
  RunQuery q;
  MethodOptions mopt;
  DistributedBuildParams bp;
};

DistributedRun distributed_options(const Args& args) {
  DistributedRun run;
  const std::string method = args.str("method");
  run.q = asked_query(args);
  run.mopt = method_options(args);
  if (!run.mopt.load_index().empty() || !run.mopt.save_index().empty())
    throw UsageError("--load-index and --save-index do not apply with --distributed (each rank builds its shard)");
  std::vector<FileArg> outputs = knn_output_files(args);
  outputs.push_back({"--stats", args.str("stats", "")});
  check_distinct_files({{"--points", args.str("points")}, {"--queries", args.str("queries")}}, outputs);
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

// The distributed index as the runner queries it: this rank's DistributedQueryStats summed over
// the slices, with the int64-id calls the runner takes when the ids pass 2^31 (RunPlace::ids64).
class RanksSummed final : public SearchThrough<DistributedIndex> {
 public:
  using SearchThrough::SearchThrough;
  QueryStats query(const float* q, std::size_t n, const SearchParams& p, KnnResult& out) const override {
    return add(index_.query(q, n, p, out, &slice_));
  }
  QueryStats query64(const float* q, std::size_t n, const SearchParams& p, KnnResult64& out) const {
    return add(index_.query(q, n, p, out, &slice_));
  }
  QueryStats radius_search(const float* q, std::size_t n, float r, const RadiusParams& p,
                           RadiusResult& out) const override {
    return add(index_.radius_search(q, n, r, p, out, &slice_));
  }
  QueryStats radius64(const float* q, std::size_t n, float r, const RadiusParams& p, RadiusResult64& out) const {
    return add(index_.radius_search(q, n, r, p, out, &slice_));
  }
  const DistributedQueryStats& sums() const { return sums_; }
  std::size_t visits() const { return visits_; }  // ranks visited, summed over this rank's queries

 private:
  QueryStats add(const QueryStats& st) const {
    using D = DistributedQueryStats;
    for (std::size_t D::*count : {&D::multi_rank_queries, &D::owner_sent, &D::owner_received, &D::extra_sent,
                                  &D::extra_received, &D::reanswered, &D::answered, &D::bytes_sent, &D::bytes_received})
      sums_.*count += slice_.*count;
    for (double D::*seconds : {&D::phase1_s, &D::phase2_s}) sums_.*seconds += slice_.*seconds;
    for (auto v : slice_.ranks_visited) visits_ += static_cast<std::size_t>(v);
    return st;
  }
  mutable DistributedQueryStats slice_, sums_;
  mutable std::size_t visits_ = 0;
};

// The MPI job as the runner's data: rank 0 writes, every rank makes every call (the slice count
// and size rank 0's), a failure anywhere is told to every rank (mpi_agree).
RunPlace job_place(const Job& job, const DistributedIndex& index, const Runtime& rt, const RanksSummed& summed) {
  RunPlace place;
  place.kind = IndexKind::distributed;
  place.where = std::to_string(job.ranks) + " rank(s) (" + rt.info().device_name + " on rank 0)";
  place.writes = job.rank == 0;
  place.ids64 = !index.ids_fit_int32();
  place.agree_slices = [](const Slicing& mine) {
    std::uint64_t v[3] = {mine.n_all, mine.rows, mine.last_rows};
    MPI_Bcast(v, 3, MPI_UINT64_T, 0, MPI_COMM_WORLD);
    return Slicing{static_cast<std::size_t>(v[0]), static_cast<std::size_t>(v[1]), static_cast<std::size_t>(v[2])};
  };
  place.agree = [](const std::string& err) { mpi_agree(MPI_COMM_WORLD, err, "bhcl knn --distributed"); };
  place.query64 = [&summed](const float* q, std::size_t n, const SearchParams& p, KnnResult64& out) {
    return summed.query64(q, n, p, out);
  };
  place.radius64 = [&summed](const float* q, std::size_t n, float r, const RadiusParams& p, RadiusResult64& out) {
    return summed.radius64(q, n, r, p, out);
  };
  return place;
}

// Per-rank figures gathered on rank 0 (every rank takes part in the gathers).
Json per_rank_json(const Job& job, const DistributedBuildStats& bs, const RanksSummed& summed, const QueryStats& st) {
  const auto all = [&](double v) { return gathered(v, job.rank, job.ranks); };
  const DistributedQueryStats& ds = summed.sums();
  Json j = Json::object();
  j["shard_points"] = all(double(bs.shard_points));
  j["points_received"] = all(double(bs.points_received));
  j["queries_received"] = all(double(ds.owner_received + ds.extra_received));
  j["queries_answered"] = all(double(ds.answered));
  j["build_s"] = all(bs.build_s);
  j["query_s"] = all(st.query_s);
  j["compile_s"] = all(st.compile_s);
  return j;
}

// The job's own figures: the summary line's tail and the stats file's "distributed" (collective:
// the per-rank figures are gathered on every rank).
void add_job_figures(RunReport& r, const Job& job, const DistributedIndex& index, const DistributedRun& run,
                     const RanksSummed& summed, const QueryStats& st) {
  const DistributedQueryStats& ds = summed.sums();
  const std::size_t n = r.n;
  char note[160];
  std::snprintf(note, sizeof note, "  queries on more than one rank %zu (%.1f %%)", ds.multi_rank_queries,
                n ? 100.0 * double(ds.multi_rank_queries) / double(n) : 0.0);
  r.note = note;
  const DistributedBuildStats& bs = index.build_stats();
  Json d;
  d["ranks"] = job.ranks;
  d["input"] = "rank 0 reads the files and passes every point and query";
  d["boxes_per_rank"] = run.bp.boxes_per_rank;
  d["border_factor"] = run.bp.border_factor;
  d["balance"] = bs.balance;
  d["multi_rank_queries"] = ds.multi_rank_queries;
  d["mean_ranks_visited"] = n ? double(summed.visits()) / double(n) : 0.0;
  d["reanswered_queries"] = ds.reanswered;
  d["phase1_s"] = ds.phase1_s;
  d["phase2_s"] = ds.phase2_s;
  d["per_rank"] = per_rank_json(job, bs, summed, st);
  r.extra["distributed"] = d;
}

// kNN or radius search over the job through bhcl knn's runner: rank 0's queries, the rows written
// there as they come back; the summary and the stats file from rank 0.
int run_job(const Args& args, Job& job, const DistributedIndex& index, const DistributedRun& run,
            const std::vector<float>& queries, const Runtime& rt) {
  const RanksSummed summed(index);
  const RunPlace place = job_place(job, index, rt, summed);
  const Answered a = answer(args, summed, place, queries, run.q);
  RunReport r;
  // Rank 0's local index: parameters every rank derives the same way from its own shard.
  r.built = index.local_index();
  r.mopt = run.mopt;
  r.build_s = index.build_stats().wall_s;
  r.N = index.size();
  r.n = queries.size() / 3;
  add_job_figures(r, job, index, run, summed, a.st);
  job.attempt([&] { report(args, place, rt, summed, run.q, a, r); });  // a failure there fails every rank
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
    std::vector<float>().swap(points);
    return run_job(args, job, index, run, queries, *rt);
  } catch (const std::exception& e) {
    return fail_every_rank(e);
  }
}

#endif

}  // namespace bhcl::cli
