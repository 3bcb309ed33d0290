// bhcl knn's one runner (issue 35): every index kind (one device, several devices, an MPI job)
// answers through the same slices, output files, summary line and stats file; what differs
// between the kinds is data (RunPlace), not a second copy of the loop.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "blockhash_cl/knn.hpp"
#include "cli.hpp"

namespace bhcl::cli {

enum class IndexKind { device, devices, distributed };

// A call's slices: n_all queries in slices of `rows`, the last of last_rows where not 0 (slice_starts).
struct Slicing {
  std::size_t n_all = 0, rows = 0, last_rows = 0;
};

// Where the runner answers, as data. One process: the defaults (it writes, int32 ids, nothing to
// agree). An MPI job: every rank makes every call (rank 0 with the queries, the others with
// none), only rank 0 writes, and the ranks agree on the slices and on any failure.
struct RunPlace {
  IndexKind kind = IndexKind::device;
  std::string where;     // the summary line's "on ...": a device, "2 devices", "3 rank(s) (...)"
  bool writes = true;    // this process writes the outputs, the summary and the stats
  bool ids64 = false;    // the ids are int64 (a distributed index past 2^31)
  // A job: this rank's slicing (its queries, slice rows, last slice) -> the job's (rank 0's).
  // Unset: one process.
  std::function<Slicing(const Slicing&)> agree_slices;
  // A job: every rank learns whether any failed (`err` non-empty here) and throws when one did.
  std::function<void(const std::string& err)> agree;
  // ids64: the calls that answer with int64 ids (SearchIndex's answer with int32 ones).
  std::function<QueryStats(const float*, std::size_t, const SearchParams&, KnnResult64&)> query64;
  std::function<QueryStats(const float*, std::size_t, float, const RadiusParams&, RadiusResult64&)> radius64;

  bool collective() const { return static_cast<bool>(agree); }
};

// What a query call asks: kNN with `params`, or (radius set) radius search of radius r.
struct RunQuery {
  SearchParams params;
  std::optional<RadiusParams> radius;
  float r = 0;
};

// The query bhcl knn's command line asks, its options checked (cmd_knn.cpp; also for
// --distributed): with --radius, radius search, else kNN.
RunQuery asked_query(const Args& args);
// bhcl knn's output files, by the option that names each (cmd_knn.cpp).
std::vector<FileArg> knn_output_files(const Args& args);

// A SearchIndex over another index, as the runner queries it (the wrapper sums what the inner
// index's richer overloads report per slice): the inner index's name, exactness, size and batch
// parameters forwarded.
template <typename Inner>
class SearchThrough : public SearchIndex {
 public:
  explicit SearchThrough(const Inner& inner) : index_(inner) {}
  std::string method() const override { return index_.method(); }
  bool exact() const override { return index_.exact(); }
  std::size_t size() const override { return index_.size(); }
  SearchParams params_for_batch(const float* queries, std::size_t n, const SearchParams& params,
                                BatchTuning* info = nullptr) const override {
    return index_.params_for_batch(queries, n, params, info);
  }

 protected:
  const Inner& index_;
};

// What the runner did.
struct Answered {
  QueryStats st;
  SearchParams params;  // kNN: the parameters the batch ran with (SearchIndex::params_for_batch)
  BatchTuning bt;       // kNN: what params_for_batch did
  double write_s = 0;         // the output files' appends, inside the query call's wall time
  double commit_s = 0;        // their flush to the disk and renames, after it
  double prepare_beside_s = 0;  // the program built beside reading the inputs, before the call
  std::size_t found = 0;      // neighbours found, or radius results
  std::size_t truncated = 0;  // radius: queries cut at --max-results
};

// The direct (O_DIRECT) outputs' slice buffers of `bhcl knn` on one device, made present now
// (prefault_direct_buffers) for the query count its --queries file declares, the slicing answer
// will use and its k: called beside reading the inputs, where a core is idle, so that the search
// finds them made. Nothing where the file declares no count or the outputs will not be direct.
void prefault_knn_outputs(const Args& args, const SearchParams& params);

// The query call over any SearchIndex: kNN with the batch's parameters (block hashing: a recall
// target, or the block layouts' default one, tuned on a sample of these queries, not on the
// index's own points) or radius search; in slices (a progress bar on a terminal), each slice's
// rows written as it finishes (no second copy of the result), renamed in place at the end: a
// failure leaves the old files and no temporary. Results do not depend on the slicing.
Answered answer(const Args& args, const SearchIndex& index, const RunPlace& place,
                const std::vector<float>& queries, const RunQuery& q);

// What the summary line and the stats file say about the index beyond the call's figures.
struct RunReport {
  const Index* built = nullptr;  // the index whose build and search parameters are reported
  MethodOptions mopt;            // the options it was built with
  double build_s = 0;
  std::size_t N = 0, n = 0;
  std::string note;              // the summary line's tail: the kind's own figures
  Json extra = Json::object();   // the stats file's: the kind's own fields (devices, distributed)
};

// The summary line (stderr) and, with --stats, the stats file: the same fields for every kind.
void report(const Args& args, const RunPlace& place, const Runtime& rt, const SearchIndex& index,
            const RunQuery& q, const Answered& a, const RunReport& r);

}  // namespace bhcl::cli
