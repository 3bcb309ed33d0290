// distributed_bench: what scale-out of bhcl::DistributedIndex depends on, measured at the rank
// count it is started with (mpirun -np R build/bench/distributed_bench ...):
//  - points moved by the sharding (per rank: received from other ranks), the load balance
//    (largest shard / mean shard) and the query load balance (most queries a rank answered / mean),
//  - queries moved per rank (received from other ranks, both phases), the share of queries that
//    visit more than one rank and the mean number of ranks a query visits, the bytes moved,
//  - the end-to-end time (build + query, kernel compile excluded) against one process: the same
//    method built and queried by a plain Index on rank 0 while the other ranks sleep, interleaved
//    with the distributed runs (per-round ratio, median over rounds),
//  - and a check against that one process: exact methods must give identical rows (the count of
//    identical rows is printed), block hashing's recall@k (against the exact kd-tree) is printed
//    for both.
// Input modes: `root` (rank 0 reads everything and passes all points and queries, the bhcl tool's
// mode) and `split` (each rank passes a contiguous slice of the file order, as if each read its
// part; no check then, the rows are spread over the ranks).
// --update (issue 39): the distributed index's insert and remove instead (update_bench's ratio):
// per set a base of 1/1.1 of the (shuffled) points, and per method and round, for each of
// insert 1 %, insert 10 % (of the base) and remove 10 % (random base ids): a fresh distributed
// build of the result, then a distributed build of the base and the update, timed (the slowest
// rank); the ratio update / fresh build per round, the median over rounds. Every rank passes a
// contiguous slice of the base, of the new points and of the ids. After each update the answers
// (the index's default search: exact) are compared with one process's index (rank 0) after the
// same update: ids and distances must be identical.
#include <mpi.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <cstdio>
#include <fstream>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "bench_cli.hpp"
#include "bench_util.hpp"
#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/distributed.hpp"

namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// A barrier that sleeps instead of spinning, so that the ranks waiting for rank 0's one-process
// baseline leave it the cores.
void sleepy_barrier(MPI_Comm comm) {
  MPI_Request req;
  MPI_Ibarrier(comm, &req);
  int done = 0;
  while (!done) {
    MPI_Test(&req, &done, MPI_STATUS_IGNORE);
    if (!done) usleep(500);
  }
}

double max_over_ranks(double v) {
  double m = 0;
  MPI_Allreduce(&v, &m, 1, MPI_DOUBLE, MPI_MAX, MPI_COMM_WORLD);
  return m;
}
// (max, mean) over ranks.
std::pair<double, double> spread(double v) {
  double mx = 0, sum = 0;
  int R = 1;
  MPI_Comm_size(MPI_COMM_WORLD, &R);
  MPI_Allreduce(&v, &mx, 1, MPI_DOUBLE, MPI_MAX, MPI_COMM_WORLD);
  MPI_Allreduce(&v, &sum, 1, MPI_DOUBLE, MPI_SUM, MPI_COMM_WORLD);
  return {mx, sum / R};
}
double sum_over_ranks(double v) {
  double s = 0;
  MPI_Allreduce(&v, &s, 1, MPI_DOUBLE, MPI_SUM, MPI_COMM_WORLD);
  return s;
}

struct Options {
  std::vector<std::string> data = {"autzen", "cornell"};
  std::size_t N = 0;  // 0: the whole file, 1M for generated sets
  std::size_t queries = 100000;
  int k = 10;
  std::vector<std::string> methods = {"kdtree", "blockhash"};
  float A = 8;
  std::vector<float> border = {2};
  int boxes = 16;
  std::string input = "root";
  int reps = 3;
  bool no_baseline = false;
  bool update = false;
  std::string data_dir, csv;
};

// Parses on every rank (every rank sees the same line); rank 0 alone prints the help or the
// mistake. Returns the exit status when the program is to end (0 after --help, 2), else -1.
int parse(int argc, char** argv, int rank, Options& o) {
  bhcl::bench::BenchCli cli("distributed_bench",
                            "Scale-out figures of the MPI-distributed index (run under mpirun -np R)");
  cli.names("data", o.data, "data sets: autzen (../shared/data), cornell, uniform, clustered (generated)");
  cli.integer("N", o.N, "points per set (0: the whole file; 1e6 for generated sets)", 0, 2e9);
  cli.queries(o.queries);
  cli.integer("k", o.k, "neighbours per query", 1, bhcl::kMaxK);
  cli.methods(o.methods);
  cli.number("A", o.A, "blockhash: examine at most A*k points per query", 1e-3, 1e6);
  cli.numbers("border", o.border, "blockhash: border queries' second answer at this many times A (1: none)", 1, 1024);
  cli.integer("boxes", o.boxes, "boxes each rank shares", 1, 1024);
  cli.text("input", o.input, "root: rank 0 passes every point and query; split: each rank a slice", "MODE")
      ->check(CLI::IsMember({"root", "split"}));
  cli.reps(o.reps);
  cli.app().add_flag("--no-baseline", o.no_baseline, "skip the one-process baseline and check");
  cli.app().add_flag("--update", o.update,
                     "time insert 1 %, insert 10 % and remove 10 % against fresh distributed builds of the result, "
                     "answers (the default search) checked against one process after the same update");
  cli.data_dir(o.data_dir);
  cli.csv(o.csv);
  try {
    cli.app().parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const bool help = e.get_exit_code() == 0;
    if (rank == 0) {
      if (help) std::fputs(cli.app().help().c_str(), stdout);
      else std::fprintf(stderr, "distributed_bench: %s (see distributed_bench --help)\n", e.what());
    }
    return help ? 0 : 2;
  }
  if (o.input != "root" && !o.update) o.no_baseline = true;
  return -1;
}

// Rank 0's CSV file with its header (null without --csv and on the other ranks).
std::FILE* open_csv(const Options& o, int rank) {
  if (rank != 0 || o.csv.empty()) return nullptr;
  std::FILE* csv = std::fopen(o.csv.c_str(), "w");
  if (!csv) throw bhcl::Error("cannot write " + o.csv);
  std::fprintf(csv, "data,method,ranks,input,N,n,k,balance,points_moved_max,points_moved_mean,"
                    "query_load_balance,queries_moved_max,queries_moved_mean,multi_rank_share,"
                    "mean_ranks_visited,mb_moved_max,shard_s,build_s,query_s,e2e_s,single_e2e_s,"
                    "e2e_ratio,query_ratio,check\n");
  return csv;
}

void print_header(const Options& o, int R, const bhcl::Runtime& rt) {
  std::printf("# distributed_bench: %d rank(s), input %s, k %d, %zu queries, boxes %d, device %s\n"
              "# moved = received from other ranks, per rank (max / mean); MB = points, queries and rows in + out;\n"
              "# times: medians over %d round(s), the slowest rank; ratios: median of per-round distributed / one process\n",
              R, o.input.c_str(), o.k, o.queries, o.boxes, rt.info().summary().c_str(), o.reps);
  std::printf("| data | method | ranks | shard max/mean | points moved/rank max / mean | queries moved/rank "
              "max / mean | multi-rank %% | ranks/query | query load max/mean | MB/rank max | shard s | "
              "build s | query s | end-to-end s | one process s | e2e ratio | query ratio | check |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
}

// One data set: rank 0's whole set (every rank's with --input split), and this rank's part.
struct SetData {
  std::vector<float> pts, qs;
  std::size_t Nall = 0, nall = 0;
  const float* my_pts = nullptr;
  const float* my_qs = nullptr;
  std::size_t my_n = 0, my_q = 0;
};

// Loads the set (false on every rank when any rank could not) and cuts this rank's part.
bool load_part(const Options& o, const std::string& set, int rank, int R, SetData& d) {
  std::size_t N = o.N ? o.N : (set == "autzen" ? 0 : 1000000);
  bool ok = true;
  if (rank == 0 || o.input == "split") ok = bhcl::bench::load_set(o.data_dir, set, N, o.queries, d.pts, d.qs);
  int okv = ok, all_ok = 0;
  MPI_Allreduce(&okv, &all_ok, 1, MPI_INT, MPI_MIN, MPI_COMM_WORLD);
  if (!all_ok) return false;
  d.Nall = d.pts.size() / 3, d.nall = d.qs.size() / 3;
  MPI_Bcast(&d.Nall, 1, MPI_UNSIGNED_LONG, 0, MPI_COMM_WORLD);
  MPI_Bcast(&d.nall, 1, MPI_UNSIGNED_LONG, 0, MPI_COMM_WORLD);
  d.my_pts = d.pts.data();
  d.my_qs = d.qs.data();
  d.my_n = d.pts.size() / 3, d.my_q = d.qs.size() / 3;
  if (o.input == "split") {
    const std::size_t pf = d.Nall * rank / R, pe = d.Nall * (rank + 1) / R;
    const std::size_t qf = d.nall * rank / R, qe = d.nall * (rank + 1) / R;
    d.my_pts += 3 * pf, d.my_n = pe - pf, d.my_qs += 3 * qf, d.my_q = qe - qf;
  }
  return true;
}

// The repetitions of one (method, border) on a set: per repetition the distributed build and
// query, and the one-process baseline on rank 0.
struct Reps {
  std::vector<double> e2e_ratio, query_ratio, shard_s, build_s, query_s, e2e_s, single_s;
  bhcl::DistributedBuildStats bs;
  bhcl::DistributedQueryStats ds;
  bhcl::KnnResult dist_rows, single_rows;
};

void run_reps(const Options& o, const std::shared_ptr<bhcl::Runtime>& rt, const SetData& d, int rank,
              const bhcl::DistributedBuildParams& bp, const bhcl::SearchParams& p, Reps& t) {
  for (int rep = 0; rep < o.reps; ++rep) {
    // Distributed: build, warm up (compile excluded), query.
    sleepy_barrier(MPI_COMM_WORLD);
    auto t0 = Clock::now();
    bhcl::DistributedIndex index(MPI_COMM_WORLD, rt, d.my_pts, d.my_n, bp);
    const double tb = max_over_ranks(since(t0));
    t.bs = index.build_stats();
    if (index.local_index()) index.local_index()->warm_up(p);
    sleepy_barrier(MPI_COMM_WORLD);
    t0 = Clock::now();
    index.query(d.my_qs, d.my_q, p, t.dist_rows, &t.ds);
    const double tq = max_over_ranks(since(t0));
    t.shard_s.push_back(max_over_ranks(t.bs.shard_s));
    t.build_s.push_back(tb);
    t.query_s.push_back(tq);
    t.e2e_s.push_back(tb + tq);
    // One process on rank 0 while the others sleep.
    if (!o.no_baseline) {
      double sb = 0, sq = 0;
      if (rank == 0) {
        auto t1 = Clock::now();
        auto single = bhcl::make_index(bp.method, rt, d.pts.data(), d.Nall);
        sb = since(t1);
        single->warm_up(p);
        t1 = Clock::now();
        single->query(d.qs.data(), d.nall, p, t.single_rows);
        sq = since(t1);
      }
      sleepy_barrier(MPI_COMM_WORLD);
      MPI_Bcast(&sb, 1, MPI_DOUBLE, 0, MPI_COMM_WORLD);
      MPI_Bcast(&sq, 1, MPI_DOUBLE, 0, MPI_COMM_WORLD);
      t.single_s.push_back(sb + sq);
      t.e2e_ratio.push_back((tb + tq) / (sb + sq));
      t.query_ratio.push_back(tq / sq);
    }
  }
}

// The rows of r at the queries `rows`.
bhcl::KnnResult rows_of(const bhcl::KnnResult& r, const std::vector<std::size_t>& rows) {
  bhcl::KnnResult s;
  s.resize(rows.size(), r.k);
  for (std::size_t j = 0; j < rows.size(); ++j) {
    const std::size_t kk = std::size_t(r.k);
    std::copy_n(&r.ids[rows[j] * kk], kk, &s.ids[j * kk]);
    std::copy_n(&r.dist2[rows[j] * kk], kk, &s.dist2[j * kk]);
    s.counts[j] = r.counts[rows[j]];
  }
  return s;
}

// Rank 0's check against the one process: exact methods' identical rows (status 1 when any
// differs); block hashing's recall against the exact kd-tree, also on the queries that visited
// more than one rank, where sharding could cost.
std::string check_rows(const Options& o, const std::shared_ptr<bhcl::Runtime>& rt, const SetData& d,
                       const std::string& method, const bhcl::SearchParams& p, const Reps& t, int& status) {
  const std::size_t nall = d.nall;
  if (bhcl::method_info(method).exact) {
    std::size_t same = 0;
    for (std::size_t i = 0; i < nall; ++i) {
      bool eq = t.dist_rows.counts[i] == t.single_rows.counts[i];
      for (int j = 0; eq && j < o.k; ++j) {
        const std::size_t at = i * std::size_t(o.k) + std::size_t(j);
        eq = t.dist_rows.ids[at] == t.single_rows.ids[at] &&
             std::memcmp(&t.dist_rows.dist2[at], &t.single_rows.dist2[at], 4) == 0;
      }
      same += eq;
    }
    if (same != nall) status = 1;
    return "identical " + std::to_string(same) + "/" + std::to_string(nall);
  }
  bhcl::KnnResult truth;
  bhcl::make_index("kdtree", rt, d.pts.data(), d.Nall)->query(d.qs.data(), nall, p, truth);
  std::vector<std::size_t> multi_q;
  for (std::size_t i = 0; i < nall; ++i)
    if (t.ds.ranks_visited[i] > 1) multi_q.push_back(i);
  char buf[200];
  std::snprintf(buf, sizeof buf, "recall %.4f (one process %.4f; multi-rank queries %.4f vs %.4f)",
                bhcl::evaluate_accuracy(t.dist_rows, truth).recall,
                bhcl::evaluate_accuracy(t.single_rows, truth).recall,
                multi_q.empty() ? 0.0 : bhcl::evaluate_accuracy(rows_of(t.dist_rows, multi_q), rows_of(truth, multi_q)).recall,
                multi_q.empty() ? 0.0 : bhcl::evaluate_accuracy(rows_of(t.single_rows, multi_q), rows_of(truth, multi_q)).recall);
  return buf;
}

// Volumes and balance over the ranks (the same in every repetition: the sharding is
// deterministic); collective.
struct Volumes {
  std::pair<double, double> pm, qm, load, mb;  // (max, mean) over ranks
  double multi = 0, visits = 0;                // sums over ranks
};

Volumes volumes(const Reps& t) {
  Volumes v;
  v.pm = spread(double(t.bs.points_received));
  v.qm = spread(double(t.ds.owner_received + t.ds.extra_received));
  v.load = spread(double(t.ds.answered));
  const double bytes = double(t.ds.bytes_sent + t.ds.bytes_received) +
                       16.0 * double(t.bs.points_sent + t.bs.points_received);
  v.mb = spread(bytes / 1e6);
  v.multi = sum_over_ranks(double(t.ds.multi_rank_queries));
  double visits = 0;
  for (auto x : t.ds.ranks_visited) visits += x;
  v.visits = sum_over_ranks(visits);
  return v;
}

// Rank 0's table row and CSV row.
void print_row(const Options& o, const std::string& set, const std::string& method, float border, int R,
               const SetData& d, const Reps& t, const Volumes& v, const std::string& check, std::FILE* csv) {
  using bhcl::bench::median;
  const std::size_t nall = d.nall;
  const double e2e = median(t.e2e_s), single = median(t.single_s);
  auto num = [](bool have, double x, const char* fmt) {
    char b[32];
    if (!have) return std::string("-");
    std::snprintf(b, sizeof b, fmt, x);
    return std::string(b);
  };
  const std::string label = bhcl::method_info(method).exact
                                ? method
                                : method + " A" + num(true, o.A, "%g") + " b" + num(true, border, "%g");
  std::printf("| %s | %s | %d | %.4f | %.0f / %.0f | %.0f / %.0f | %.2f | %.3f | %.3f | %.1f | %.3f | %.3f "
              "| %.3f | %.3f | %s | %s | %s | %s |\n",
              set.c_str(), label.c_str(), R, t.bs.balance, v.pm.first, v.pm.second, v.qm.first, v.qm.second,
              100.0 * v.multi / double(nall), v.visits / double(nall),
              v.load.first / std::max(v.load.second, 1e-9), v.mb.first, median(t.shard_s),
              median(t.build_s), median(t.query_s), e2e, num(!t.single_s.empty(), single, "%.3f").c_str(),
              num(!t.e2e_ratio.empty(), median(t.e2e_ratio), "%.2f").c_str(),
              num(!t.query_ratio.empty(), median(t.query_ratio), "%.2f").c_str(), check.c_str());
  std::fflush(stdout);
  if (csv)
    std::fprintf(csv, "%s,%s,%d,%s,%zu,%zu,%d,%.5f,%.0f,%.1f,%.4f,%.0f,%.1f,%.5f,%.4f,%.2f,%.4f,%.4f,"
                      "%.4f,%.4f,%.4f,%.4f,%.4f,%s\n",
                 set.c_str(), label.c_str(), R, o.input.c_str(), d.Nall, nall, o.k, t.bs.balance,
                 v.pm.first, v.pm.second, v.load.first / std::max(v.load.second, 1e-9), v.qm.first,
                 v.qm.second, v.multi / double(nall), v.visits / double(nall), v.mb.first,
                 median(t.shard_s), median(t.build_s), median(t.query_s), e2e, single,
                 median(t.e2e_ratio), median(t.query_ratio), check.c_str());
}

// One set: each method (and, for approximate ones, each border factor) measured and reported.
void run_set(const Options& o, const std::shared_ptr<bhcl::Runtime>& rt, const std::string& set, int rank, int R,
             std::FILE* csv, int& status) {
  SetData d;
  if (!load_part(o, set, rank, R, d)) return;
  for (const std::string& method : o.methods)
    for (float border : o.border) {
      if (bhcl::method_info(method).exact && border != o.border.front()) continue;
      bhcl::SearchParams p;
      p.k = o.k;
      p.A = o.A;
      bhcl::DistributedBuildParams bp;
      bp.method = method;
      bp.boxes_per_rank = o.boxes;
      bp.border_factor = border;
      Reps t;
      run_reps(o, rt, d, rank, bp, p, t);
      const Volumes v = volumes(t);
      std::string check = "-";
      if (!o.no_baseline && rank == 0) check = check_rows(o, rt, d, method, p, t, status);
      sleepy_barrier(MPI_COMM_WORLD);
      if (rank == 0) print_row(o, set, method, border, R, d, t, v, check, csv);
    }
}


// --update: the distributed index's insert and remove against fresh distributed builds.
struct UpdateOp {
  const char* name;
  double frac;
  bool insert;
};
const UpdateOp kUpdateOps[] = {{"insert 1%", 0.01, true}, {"insert 10%", 0.10, true}, {"remove 10%", 0.10, false}};

// Every rank's copy of one set: the points shuffled (so that a prefix is a uniform sample: files
// are in scan order), the base (the first B), the ids a remove drops and the points kept then.
struct UpdateSet {
  std::vector<float> all, qs, kept;
  std::size_t B = 0;
  std::vector<std::int64_t> drop;  // ascending
};

bool load_update_set(const Options& o, const std::string& set, UpdateSet& u) {
  std::vector<float> pts;
  const std::size_t N = o.N ? o.N + o.N / 10 : (set == "autzen" ? 0 : 1100000);
  int ok = bhcl::bench::load_set(o.data_dir, set, N, o.queries, pts, u.qs), all_ok = 0;
  MPI_Allreduce(&ok, &all_ok, 1, MPI_INT, MPI_MIN, MPI_COMM_WORLD);
  if (!all_ok) return false;
  const std::size_t n = pts.size() / 3;
  std::vector<std::size_t> perm(n);
  for (std::size_t i = 0; i < n; ++i) perm[i] = i;
  std::shuffle(perm.begin(), perm.end(), std::mt19937_64(3));
  u.all.resize(pts.size());
  for (std::size_t i = 0; i < n; ++i) std::copy_n(&pts[3 * perm[i]], 3, &u.all[3 * i]);
  u.B = static_cast<std::size_t>(double(n) / 1.1);
  std::vector<std::int64_t> ids(u.B);
  for (std::size_t i = 0; i < u.B; ++i) ids[i] = std::int64_t(i);
  std::shuffle(ids.begin(), ids.end(), std::mt19937_64(5));
  u.drop.assign(ids.begin(), ids.begin() + std::ptrdiff_t(u.B / 10));
  std::sort(u.drop.begin(), u.drop.end());
  std::vector<char> gone(u.B, 0);
  for (auto id : u.drop) gone[std::size_t(id)] = 1;
  for (std::size_t i = 0; i < u.B; ++i)
    if (!gone[i]) u.kept.insert(u.kept.end(), u.all.begin() + std::ptrdiff_t(3 * i), u.all.begin() + std::ptrdiff_t(3 * i + 3));
  return true;
}

// This rank's contiguous slice [first, end) of n items.
std::pair<std::size_t, std::size_t> slice(std::size_t n, int rank, int R) {
  return {n * std::size_t(rank) / std::size_t(R), n * std::size_t(rank + 1) / std::size_t(R)};
}

// A distributed index over this rank's slice of the n points pts.
std::unique_ptr<bhcl::DistributedIndex> build_sliced(const std::shared_ptr<bhcl::Runtime>& rt, const float* pts,
                                                     std::size_t n, const bhcl::DistributedBuildParams& bp, int rank,
                                                     int R) {
  const auto [a, b] = slice(n, rank, R);
  return std::make_unique<bhcl::DistributedIndex>(MPI_COMM_WORLD, rt, pts + 3 * a, b - a, bp);
}

// The update `op` on the index over the base, each rank passing its slice (collective).
void apply_update(bhcl::DistributedIndex& ix, const UpdateSet& u, const UpdateOp& op, int rank, int R,
                  bhcl::DistributedUpdateStats* st) {
  if (op.insert) {
    const std::size_t m = static_cast<std::size_t>(op.frac * double(u.B));
    const auto [a, b] = slice(m, rank, R);
    ix.insert(u.all.data() + 3 * (u.B + a), b - a, st);
  } else {
    const auto [a, b] = slice(u.drop.size(), rank, R);
    ix.remove(u.drop.data() + a, b - a, st);
  }
}

// Rank 0: one process's index of the base after the same update, queried; "identical x/n" of
// the distributed rows (gathered to rank 0 by query, int64 ids) against it; status 1 if any differ.
std::string check_update(const std::shared_ptr<bhcl::Runtime>& rt, const UpdateSet& u, const UpdateOp& op,
                         const std::string& method, const bhcl::SearchParams& p, const bhcl::KnnResult64& dist,
                         int& status) {
  auto single = bhcl::make_index(method, rt, u.all.data(), u.B);
  if (op.insert) {
    single->insert(u.all.data() + 3 * u.B, static_cast<std::size_t>(op.frac * double(u.B)));
  } else {
    std::vector<std::int32_t> ids(u.drop.begin(), u.drop.end());
    single->remove(ids.data(), ids.size());
  }
  bhcl::KnnResult one;
  const std::size_t nq = u.qs.size() / 3;
  single->query(u.qs.data(), nq, p, one);
  std::size_t same = 0;
  for (std::size_t i = 0; i < nq; ++i) {
    bool eq = dist.counts[i] == one.counts[i];
    for (int j = 0; eq && j < p.k; ++j) {
      const std::size_t at = i * std::size_t(p.k) + std::size_t(j);
      eq = dist.ids[at] == std::int64_t(one.ids[at]) && std::memcmp(&dist.dist2[at], &one.dist2[at], 4) == 0;
    }
    same += eq;
  }
  if (same != nq) status = 1;
  return "identical " + std::to_string(same) + "/" + std::to_string(nq);
}

// One (method, op): rounds of a fresh build of the result and the update, then the check.
void run_update_op(const Options& o, const std::shared_ptr<bhcl::Runtime>& rt, const UpdateSet& u,
                   const std::string& set, const std::string& method, const UpdateOp& op, int rank, int R,
                   std::FILE* csv, int& status) {
  using bhcl::bench::median;
  bhcl::DistributedBuildParams bp;
  bp.method = method;
  bp.boxes_per_rank = o.boxes;
  bhcl::SearchParams p;
  p.k = o.k;  // A: the index's default (block hashing's exact grid)
  const std::size_t m = static_cast<std::size_t>(op.frac * double(u.B));
  const float* after = op.insert ? u.all.data() : u.kept.data();
  const std::size_t n_after = op.insert ? u.B + m : u.kept.size() / 3;
  std::vector<double> fresh_s, update_s, ratio, route_s, local_s, boxes_s;
  bhcl::KnnResult64 rows;
  for (int rep = 0; rep < o.reps; ++rep) {
    sleepy_barrier(MPI_COMM_WORLD);
    auto t0 = Clock::now();
    build_sliced(rt, after, n_after, bp, rank, R).reset();
    const double tf = max_over_ranks(since(t0));
    auto ix = build_sliced(rt, u.all.data(), u.B, bp, rank, R);
    bhcl::DistributedUpdateStats st;
    sleepy_barrier(MPI_COMM_WORLD);
    t0 = Clock::now();
    apply_update(*ix, u, op, rank, R, &st);
    const double tu = max_over_ranks(since(t0));
    fresh_s.push_back(tf);
    update_s.push_back(tu);
    ratio.push_back(tu / tf);
    route_s.push_back(max_over_ranks(st.route_s));
    local_s.push_back(max_over_ranks(st.local_s));
    boxes_s.push_back(max_over_ranks(st.boxes_s));
    // The last round's index answers for the check: rank 0 passes every query (its rows come back
    // to it in its order).
    if (rep + 1 == o.reps) ix->query(u.qs.data(), rank == 0 ? u.qs.size() / 3 : 0, p, rows);
  }
  std::string check = "-";
  if (!o.no_baseline && rank == 0) check = check_update(rt, u, op, method, p, rows, status);
  sleepy_barrier(MPI_COMM_WORLD);
  if (rank != 0) return;
  std::printf("| %s | %s | %d | %s | %zu | %zu | %.4f | %.4f | **%.3f** | %.4f | %.4f | %.4f | %s |\n", set.c_str(),
              method.c_str(), R, op.name, u.B, m, median(fresh_s), median(update_s), median(ratio), median(route_s),
              median(local_s), median(boxes_s), check.c_str());
  std::fflush(stdout);
  if (csv)
    std::fprintf(csv, "%s,%s,%d,%s,%zu,%zu,%.6f,%.6f,%.4f,%.6f,%.6f,%.6f,%s\n", set.c_str(), method.c_str(), R, op.name,
                 u.B, m, median(fresh_s), median(update_s), median(ratio), median(route_s), median(local_s),
                 median(boxes_s), check.c_str());
}

void run_update_set(const Options& o, const std::shared_ptr<bhcl::Runtime>& rt, const std::string& set, int rank,
                    int R, std::FILE* csv, int& status) {
  UpdateSet u;
  if (!load_update_set(o, set, u)) return;
  for (const std::string& method : o.methods)
    for (const UpdateOp& op : kUpdateOps) run_update_op(o, rt, u, set, method, op, rank, R, csv, status);
}

void print_update_header(const Options& o, int R, const bhcl::Runtime& rt, std::FILE* csv) {
  std::printf("# distributed_bench --update: %d rank(s), k %d, %zu queries, boxes %d, device %s\n"
              "# each rank passes a contiguous slice of the base, the new points and the ids; times: the slowest rank;\n"
              "# ratio: median over %d round(s) of update / a fresh distributed build of the result; route/local/boxes:\n"
              "# the update's stages (DistributedUpdateStats, slowest rank); check: the default search's rows\n"
              "# against one process's index after the same update\n",
              R, o.k, o.queries, o.boxes, rt.info().summary().c_str(), o.reps);
  std::printf("| data | method | ranks | update | base N | points/ids | fresh build s | update s | ratio | route s | "
              "local s | boxes s | check |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  if (csv) std::fprintf(csv, "data,method,ranks,op,base_n,m,fresh_s,update_s,ratio,route_s,local_s,boxes_s,check\n");
}

}  // namespace

int main(int argc, char** argv) {
  MPI_Init(&argc, &argv);
  int rank = 0, R = 1;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  MPI_Comm_size(MPI_COMM_WORLD, &R);
  Options o;
  if (const int rc = parse(argc, argv, rank, o); rc >= 0) {
    MPI_Finalize();
    return rc;
  }
  int status = 0;
  try {
    auto rt = std::make_shared<bhcl::Runtime>();
    if (o.update) {
      std::FILE* csv = rank == 0 && !o.csv.empty() ? std::fopen(o.csv.c_str(), "w") : nullptr;
      if (rank == 0 && !o.csv.empty() && !csv) throw bhcl::Error("cannot write " + o.csv);
      if (rank == 0) print_update_header(o, R, *rt, csv);
      for (const std::string& set : o.data) run_update_set(o, rt, set, rank, R, csv, status);
      if (csv) std::fclose(csv);
      MPI_Finalize();
      return status;
    }
    std::FILE* csv = open_csv(o, rank);
    if (rank == 0) print_header(o, R, *rt);
    for (const std::string& set : o.data) run_set(o, rt, set, rank, R, csv, status);
    if (csv) std::fclose(csv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "distributed_bench: rank %d: %s\n", rank, e.what());
    status = 1;
  }
  MPI_Finalize();
  return status;
}
