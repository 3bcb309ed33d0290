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
#include <mpi.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <cstdio>
#include <fstream>
#include <memory>
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
  std::string data_dir, csv;
};

}  // namespace

int main(int argc, char** argv) {
  MPI_Init(&argc, &argv);
  int rank = 0, R = 1;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  MPI_Comm_size(MPI_COMM_WORLD, &R);
  Options o;
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
  cli.data_dir(o.data_dir);
  cli.csv(o.csv);
  try {
    cli.app().parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // Every rank parses the same line; rank 0 alone prints the help or the mistake.
    const bool help = e.get_exit_code() == 0;
    if (rank == 0) {
      if (help) std::fputs(cli.app().help().c_str(), stdout);
      else std::fprintf(stderr, "distributed_bench: %s (see distributed_bench --help)\n", e.what());
    }
    MPI_Finalize();
    return help ? 0 : 2;
  }
  if (o.input != "root") o.no_baseline = true;

  int status = 0;
  try {
    auto rt = std::make_shared<bhcl::Runtime>();
    std::FILE* csv = nullptr;
    if (rank == 0 && !o.csv.empty()) {
      csv = std::fopen(o.csv.c_str(), "w");
      if (!csv) throw bhcl::Error("cannot write " + o.csv);
      std::fprintf(csv, "data,method,ranks,input,N,n,k,balance,points_moved_max,points_moved_mean,"
                        "query_load_balance,queries_moved_max,queries_moved_mean,multi_rank_share,"
                        "mean_ranks_visited,mb_moved_max,shard_s,build_s,query_s,e2e_s,single_e2e_s,"
                        "e2e_ratio,query_ratio,check\n");
    }
    if (rank == 0)
      std::printf("# distributed_bench: %d rank(s), input %s, k %d, %zu queries, boxes %d, device %s\n"
                  "# moved = received from other ranks, per rank (max / mean); MB = points, queries and rows in + out;\n"
                  "# times: medians over %d round(s), the slowest rank; ratios: median of per-round distributed / one process\n",
                  R, o.input.c_str(), o.k, o.queries, o.boxes, rt->info().summary().c_str(), o.reps);
    if (rank == 0)
      std::printf("| data | method | ranks | shard max/mean | points moved/rank max / mean | queries moved/rank "
                  "max / mean | multi-rank %% | ranks/query | query load max/mean | MB/rank max | shard s | "
                  "build s | query s | end-to-end s | one process s | e2e ratio | query ratio | check |\n"
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for (const std::string& set : o.data) {
      std::vector<float> pts, qs;
      std::size_t N = o.N ? o.N : (set == "autzen" ? 0 : 1000000);
      bool ok = true;
      if (rank == 0 || o.input == "split") ok = bhcl::bench::load_set(o.data_dir, set, N, o.queries, pts, qs);
      int okv = ok, all_ok = 0;
      MPI_Allreduce(&okv, &all_ok, 1, MPI_INT, MPI_MIN, MPI_COMM_WORLD);
      if (!all_ok) continue;
      std::size_t Nall = pts.size() / 3, nall = qs.size() / 3;
      MPI_Bcast(&Nall, 1, MPI_UNSIGNED_LONG, 0, MPI_COMM_WORLD);
      MPI_Bcast(&nall, 1, MPI_UNSIGNED_LONG, 0, MPI_COMM_WORLD);
      // This rank's part of the points and queries.
      const float* my_pts = pts.data();
      const float* my_qs = qs.data();
      std::size_t my_n = pts.size() / 3, my_q = qs.size() / 3;
      if (o.input == "split") {
        const std::size_t pf = Nall * rank / R, pe = Nall * (rank + 1) / R;
        const std::size_t qf = nall * rank / R, qe = nall * (rank + 1) / R;
        my_pts += 3 * pf, my_n = pe - pf, my_qs += 3 * qf, my_q = qe - qf;
      }
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
        std::vector<double> e2e_ratio, query_ratio, shard_s, build_s, query_s, e2e_s, single_s;
        bhcl::DistributedBuildStats bs;
        bhcl::DistributedQueryStats ds;
        bhcl::KnnResult dist_rows, single_rows;
        for (int rep = 0; rep < o.reps; ++rep) {
          // Distributed: build, warm up (compile excluded), query.
          sleepy_barrier(MPI_COMM_WORLD);
          auto t0 = Clock::now();
          bhcl::DistributedIndex index(MPI_COMM_WORLD, rt, my_pts, my_n, bp);
          const double tb = max_over_ranks(since(t0));
          bs = index.build_stats();
          if (index.local_index()) index.local_index()->warm_up(p);
          sleepy_barrier(MPI_COMM_WORLD);
          t0 = Clock::now();
          index.query(my_qs, my_q, p, dist_rows, &ds);
          const double tq = max_over_ranks(since(t0));
          shard_s.push_back(max_over_ranks(bs.shard_s));
          build_s.push_back(tb);
          query_s.push_back(tq);
          e2e_s.push_back(tb + tq);
          // One process on rank 0 while the others sleep.
          if (!o.no_baseline) {
            double sb = 0, sq = 0;
            if (rank == 0) {
              auto t1 = Clock::now();
              auto single = bhcl::make_index(method, rt, pts.data(), Nall);
              sb = since(t1);
              single->warm_up(p);
              t1 = Clock::now();
              single->query(qs.data(), nall, p, single_rows);
              sq = since(t1);
            }
            sleepy_barrier(MPI_COMM_WORLD);
            MPI_Bcast(&sb, 1, MPI_DOUBLE, 0, MPI_COMM_WORLD);
            MPI_Bcast(&sq, 1, MPI_DOUBLE, 0, MPI_COMM_WORLD);
            single_s.push_back(sb + sq);
            e2e_ratio.push_back((tb + tq) / (sb + sq));
            query_ratio.push_back(tq / sq);
          }
        }
        // Volumes and balance (the same in every repetition: the sharding is deterministic).
        auto pm = spread(double(bs.points_received));
        auto qm = spread(double(ds.owner_received + ds.extra_received));
        auto load = spread(double(ds.answered));
        const double bytes = double(ds.bytes_sent + ds.bytes_received) +
                             16.0 * double(bs.points_sent + bs.points_received);
        auto mb = spread(bytes / 1e6);
        const double multi = sum_over_ranks(double(ds.multi_rank_queries));
        double visits = 0;
        for (auto v : ds.ranks_visited) visits += v;
        visits = sum_over_ranks(visits);
        std::string check = "-";
        if (!o.no_baseline && rank == 0) {
          if (bhcl::method_info(method).exact) {
            std::size_t same = 0;
            for (std::size_t i = 0; i < nall; ++i) {
              bool eq = dist_rows.counts[i] == single_rows.counts[i];
              for (int j = 0; eq && j < o.k; ++j) {
                const std::size_t at = i * std::size_t(o.k) + std::size_t(j);
                eq = dist_rows.ids[at] == single_rows.ids[at] &&
                     std::memcmp(&dist_rows.dist2[at], &single_rows.dist2[at], 4) == 0;
              }
              same += eq;
            }
            check = "identical " + std::to_string(same) + "/" + std::to_string(nall);
            if (same != nall) status = 1;
          } else {
            bhcl::KnnResult truth;
            bhcl::make_index("kdtree", rt, pts.data(), Nall)->query(qs.data(), nall, p, truth);
            // Also on the queries that visited more than one rank, where sharding could cost.
            std::vector<std::size_t> multi_q;
            for (std::size_t i = 0; i < nall; ++i)
              if (ds.ranks_visited[i] > 1) multi_q.push_back(i);
            auto rows = [&](const bhcl::KnnResult& r) {
              bhcl::KnnResult s;
              s.resize(multi_q.size(), r.k);
              for (std::size_t j = 0; j < multi_q.size(); ++j) {
                const std::size_t kk = std::size_t(r.k);
                std::copy_n(&r.ids[multi_q[j] * kk], kk, &s.ids[j * kk]);
                std::copy_n(&r.dist2[multi_q[j] * kk], kk, &s.dist2[j * kk]);
                s.counts[j] = r.counts[multi_q[j]];
              }
              return s;
            };
            char buf[200];
            std::snprintf(buf, sizeof buf, "recall %.4f (one process %.4f; multi-rank queries %.4f vs %.4f)",
                          bhcl::evaluate_accuracy(dist_rows, truth).recall,
                          bhcl::evaluate_accuracy(single_rows, truth).recall,
                          multi_q.empty() ? 0.0 : bhcl::evaluate_accuracy(rows(dist_rows), rows(truth)).recall,
                          multi_q.empty() ? 0.0 : bhcl::evaluate_accuracy(rows(single_rows), rows(truth)).recall);
            check = buf;
          }
        }
        sleepy_barrier(MPI_COMM_WORLD);
        if (rank == 0) {
          using bhcl::bench::median;
          const double e2e = median(e2e_s), single = median(single_s);
          auto num = [](bool have, double v, const char* fmt) {
            char b[32];
            if (!have) return std::string("-");
            std::snprintf(b, sizeof b, fmt, v);
            return std::string(b);
          };
          const std::string label = bhcl::method_info(method).exact
                                        ? method
                                        : method + " A" + num(true, o.A, "%g") + " b" + num(true, border, "%g");
          std::printf("| %s | %s | %d | %.4f | %.0f / %.0f | %.0f / %.0f | %.2f | %.3f | %.3f | %.1f | %.3f | %.3f "
                      "| %.3f | %.3f | %s | %s | %s | %s |\n",
                      set.c_str(), label.c_str(), R, bs.balance, pm.first, pm.second, qm.first, qm.second,
                      100.0 * multi / double(nall), visits / double(nall),
                      load.first / std::max(load.second, 1e-9), mb.first, median(shard_s),
                      median(build_s), median(query_s), e2e, num(!single_s.empty(), single, "%.3f").c_str(),
                      num(!e2e_ratio.empty(), median(e2e_ratio), "%.2f").c_str(),
                      num(!query_ratio.empty(), median(query_ratio), "%.2f").c_str(), check.c_str());
          std::fflush(stdout);
          if (csv)
            std::fprintf(csv, "%s,%s,%d,%s,%zu,%zu,%d,%.5f,%.0f,%.1f,%.4f,%.0f,%.1f,%.5f,%.4f,%.2f,%.4f,%.4f,"
                              "%.4f,%.4f,%.4f,%.4f,%.4f,%s\n",
                         set.c_str(), label.c_str(), R, o.input.c_str(), Nall, nall, o.k, bs.balance,
                         pm.first, pm.second, load.first / std::max(load.second, 1e-9), qm.first,
                         qm.second, multi / double(nall), visits / double(nall), mb.first,
                         median(shard_s), median(build_s), median(query_s), e2e, single,
                         median(e2e_ratio), median(query_ratio), check.c_str());
        }
      }
    }
    if (csv) std::fclose(csv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "distributed_bench: rank %d: %s\n", rank, e.what());
    status = 1;
  }
  MPI_Finalize();
  return status;
}
