#include "knn_runner.hpp"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <exception>
#include <memory>

#include "blockhash_cl/io.hpp"
#include "blockhash_cl/runtime.hpp"
#include "progress.hpp"
#include "result_files.hpp"

namespace bhcl::cli {
namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// The first failure of a run's writes. One process: thrown at once. A job: kept, so that this
// rank still makes every remaining call the others make, and told to every rank at the end.
class Failure {
 public:
  explicit Failure(const RunPlace& place) : place_(place) {}
  template <typename F>
  void attempt(F&& f) {
    if (!err_.empty()) return;
    if (!place_.collective()) return f();
    try {
      f();
    } catch (const std::exception& e) {
      err_ = e.what();
    }
  }
  void agree() const {
    if (place_.collective()) place_.agree(err_);
  }

 private:
  const RunPlace& place_;
  std::string err_;
};

// The job's slicing: this process's own in one process, rank 0's in a job.
Slicing slicing(const RunPlace& place, const Slicing& mine) {
  return place.agree_slices ? place.agree_slices(mine) : mine;
}

// Every slice through search(first, m, part), each part appended to `files` (this process's
// outputs; none on the ranks that do not write) as it comes back; committed at the end.
template <typename Outputs, typename Part, typename Search>
QueryStats slices_to_files(const RunPlace& place, std::size_t n, const Slicing& mine, render::Progress& bar,
                           std::unique_ptr<Outputs> files, Answered& a, const Search& search) {
  Failure failure(place);
  const Slicing job = slicing(place, mine);
  Part part;
  const QueryStats st = in_slices(n, job.n_all, job.rows, bar, [&](std::size_t first, std::size_t m) {
    const QueryStats ps = search(first, m, part);
    if (files) failure.attempt([&] {
        const auto t0 = std::chrono::steady_clock::now();
        files->append(part);
        a.write_s += seconds_since(t0);
      });
    return ps;
  }, job.last_rows);
  if (files) failure.attempt([&] {
      const auto t0 = std::chrono::steady_clock::now();
      files->commit();  // after the wall time: the files' flush to the disk and their renames
      a.commit_s = seconds_since(t0);
      if constexpr (std::is_same_v<Outputs, KnnOutputs>) {
        a.found = files->found();
      } else {
        a.found = files->total();
        a.truncated = files->truncated_queries();
      }
    });
  files.reset();  // a failed write: the temporaries removed
  failure.agree();
  return st;
}

// This process's outputs (none where it does not write); a job agrees on whether every rank
// could open them before any query.
template <typename Outputs, typename... Extra>
std::unique_ptr<Outputs> open_outputs(const Args& args, const RunPlace& place, Extra... extra) {
  Failure failure(place);
  std::unique_ptr<Outputs> files;
  if (place.writes) failure.attempt([&] { files = std::make_unique<Outputs>(args, extra..., place.ids64); });
  failure.agree();
  return files;
}

// The slicing of a kNN call of n queries whose outputs are direct or not (answer_knn's and
// prefault_knn_outputs'): slices of about 32 MiB of rows and at least 2^17 queries
// (knn_slice_rows), whose two buffers are reused slice after slice (fresh pages cost on VMs),
// the last a quarter of that (direct_last_slice_rows): its write is the one that no next search
// hides.
Slicing knn_slicing(std::size_t n, const SearchParams& p, bool bar, bool direct) {
  const std::size_t rows = knn_slice_rows(n, p.k, p.count_examined, bar, direct ? direct_slice_bytes() : 0);
  return Slicing{n, rows, direct ? direct_last_slice_rows(rows) : 0};
}

template <typename Id>
Answered answer_knn(const Args& args, const SearchIndex& index, const RunPlace& place,
                    const std::vector<float>& queries, const SearchParams& asked) {
  const std::size_t n = queries.size() / 3;
  Answered a;
  a.params = index.params_for_batch(queries.data(), n, asked, &a.bt);
  render::Progress bar("query " + index.method() + " (" + std::to_string(n) + " queries)",
                       place.writes && !args.flag("quiet"));
  auto files = open_outputs<KnnOutputs>(args, place, n, a.params.k);
  const Slicing mine = knn_slicing(n, a.params, bar.enabled(), files && files->direct());
  const std::size_t rows = mine.rows;
  if constexpr (std::is_same_v<Id, std::int64_t>) {
    a.st = slices_to_files<KnnOutputs, KnnRows<Id>>(
        place, n, mine, bar, std::move(files), a, [&](std::size_t first, std::size_t m, KnnRows<Id>& part) {
          return place.query64(queries.data() + 3 * first, m, a.params, part);
        });
  } else {
    // int32 ids: each slice written by the search into the output files' mapped pages where
    // they are mapped (no copy after it), else into the runner's own rows (no fill first).
    KnnOutputs* out = files.get();
    a.st = slices_to_files<KnnOutputs, KnnSlice>(
        place, n, mine, bar, std::move(files), a, [&](std::size_t first, std::size_t m, KnnSlice& part) {
          part.reserve(rows, a.params.k, a.params.count_examined);
          part.n = m;
          KnnRowsView rows_to = part.view();
          if (out) {  // the output's pages made present: the write's share of the slice
            const auto t0 = std::chrono::steady_clock::now();
            rows_to = out->rows_for(part);
            a.write_s += seconds_since(t0);
          }
          return index.query_into(queries.data() + 3 * first, m, a.params, rows_to);
        });
  }
  return a;
}

template <typename Id>
Answered answer_radius(const Args& args, const SearchIndex& index, const RunPlace& place,
                       const std::vector<float>& queries, const RadiusParams& rp, float r) {
  const std::size_t n = queries.size() / 3;
  Answered a;
  render::Progress bar("radius " + index.method() + " (" + std::to_string(n) + " queries)",
                       place.writes && !args.flag("quiet"));
  auto files = open_outputs<RadiusOutputs>(args, place, n);
  a.st = slices_to_files<RadiusOutputs, RadiusRows<Id>>(
      place, n, Slicing{n, radius_slice_rows(n, bar.enabled()), 0}, bar, std::move(files), a,
      [&](std::size_t first, std::size_t m, RadiusRows<Id>& part) {
        if constexpr (std::is_same_v<Id, std::int64_t>)
          return place.radius64(queries.data() + 3 * first, m, r, rp, part);
        else
          return index.radius_search(queries.data() + 3 * first, m, r, rp, part);
      });
  return a;
}

}  // namespace

Answered answer(const Args& args, const SearchIndex& index, const RunPlace& place,
                const std::vector<float>& queries, const RunQuery& q) {
  if (q.radius)
    return place.ids64 ? answer_radius<std::int64_t>(args, index, place, queries, *q.radius, q.r)
                       : answer_radius<std::int32_t>(args, index, place, queries, *q.radius, q.r);
  return place.ids64 ? answer_knn<std::int64_t>(args, index, place, queries, q.params)
                     : answer_knn<std::int32_t>(args, index, place, queries, q.params);
}

namespace {

void print_summary(const RunPlace& place, const SearchIndex& index, const RunQuery& q, const Answered& a,
                   const RunReport& r) {
  const QueryStats& st = a.st;
  char what[64];
  if (q.radius) std::snprintf(what, sizeof what, "r=%g", double(q.r));
  else std::snprintf(what, sizeof what, "k=%d", a.params.k);
  std::fprintf(stderr,
               "bhcl knn%s: %s on %s: N=%zu n=%zu %s  build %.3f s  compile %.3f s  query %.4f s (%.0f q/s)  "
               "wall %.4f s  %s %zu",
               q.radius ? " --radius" : "", index.method().c_str(), place.where.c_str(), r.N, r.n, what,
               r.build_s, st.compile_s, st.query_s, st.queries_per_s(), st.wall_s,
               q.radius ? "results" : "neighbours found", a.found);
  if (q.radius)
    std::fprintf(stderr, " (%.2f per query)  truncated queries %zu", r.n ? double(a.found) / double(r.n) : 0.0,
                 a.truncated);
  std::fprintf(stderr, "%s\n", r.note.c_str());
}

// The kNN call's fields: its inputs, what the build and the search used, the tuning, the stages.
void add_knn_fields(Json& j, const Args& args, const Answered& a, const RunReport& r) {
  j.update(inputs_json(args, r.N, r.n, a.params));
  if (r.built) {
    j["build"] = build_json(*r.built, r.mopt);
    j["search"] = search_json(*r.built, a.params);
  }
  const BatchTuning& bt = a.bt;
  if (bt.tuned)
    j["search"]["tuning"] = {{"recall_target", bt.target}, {"A", bt.tuning.A}, {"tuned_on", "queries"},
                             {"sample", bt.tuning.sample}, {"sample_recall", bt.tuning.recall},
                             {"reached", bt.tuning.reached}, {"cached", bt.cached},
                             {"distribution", bt.distribution}, {"seconds", bt.seconds},
                             {"compile_s", bt.compile_s}};
}

// The radius call's fields: its inputs, the build, the radius options and the results.
void add_radius_fields(Json& j, const Args& args, const SearchIndex& index, const RunQuery& q,
                       const Answered& a, const RunReport& r) {
  j["points"] = args.str("points");
  j["queries"] = args.str("queries");
  j["N"] = r.N;
  j["n"] = r.n;
  if (r.built) j["build"] = build_json(*r.built, r.mopt);
  j["radius"] = {{"radius", q.r}, {"max_results", q.radius->max_results}, {"budget", q.radius->budget}};
  j["radius"].update(table_values(args, index.method(), OptionInfo::Radius));
  j["radius"]["results"] = a.found;
  j["radius"]["truncated_queries"] = a.truncated;
}

}  // namespace

void prefault_knn_outputs(const Args& args, const SearchParams& params) {
  const std::uint64_t n = declared_point_count(args.str("queries"));
  const std::size_t k = static_cast<std::size_t>(params.k);
  if (n == 0 || k == 0 || !direct_output_expected(n * k * 4)) return;
  const bool bar = !args.flag("quiet") && render::Progress::stderr_is_terminal();
  const Slicing s = knn_slicing(static_cast<std::size_t>(n), params, bar, true);
  const std::vector<std::size_t> starts = slice_starts(s.n_all, s.rows, s.last_rows);
  std::size_t largest = 0;
  for (std::size_t i = 0; i + 1 < starts.size(); ++i) largest = std::max(largest, starts[i + 1] - starts[i]);
  // A pair (ids, dist2) a slice, two pairs where a slice's write runs beside the next's search.
  prefault_direct_buffers(largest * k * 4, starts.size() > 2 ? 4 : 2);
}

void report(const Args& args, const RunPlace& place, const Runtime& rt, const SearchIndex& index,
            const RunQuery& q, const Answered& a, const RunReport& r) {
  if (!place.writes) return;
  print_summary(place, index, q, a, r);
  if (!args.has("stats")) return;
  Json j = stats_header("knn", rt);
  j["method"] = index.method();
  j["exact"] = index.exact();
  j["index_kind"] = place.kind == IndexKind::device ? "device" : place.kind == IndexKind::devices ? "devices"
                                                                                                  : "distributed";
  if (q.radius) add_radius_fields(j, args, index, q, a, r);
  else add_knn_fields(j, args, a, r);
  // Whether this run's rows are exact: an exact method, or a kNN search in an exact mode (block
  // hashing's grid at A = +inf, its default); "exact": false had read as an approximate run.
  if (!q.radius && j.contains("search") && j["search"].value("exact", false)) j["exact"] = true;
  add_query_stats(j, r.build_s, a.st);
  if (!q.radius) {
    j["stages"] = stages_json(a.st, a.write_s, a.commit_s);
    j["stages"]["prepare_beside_reading_s"] = a.prepare_beside_s;
    j["stages"]["output_buffers_ahead"] = direct_buffers_taken_ahead();  // made present beside the reading
    j["neighbours_found"] = a.found;
  }
  if (place.kind == IndexKind::device && r.built) j["memory_bytes"] = r.built->memory_bytes();
  j.update(r.extra);
  write_json(args.str("stats"), j);
}

}  // namespace bhcl::cli
