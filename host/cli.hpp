// Argument parsing and JSON output for the bhcl tool.
#pragma once

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <functional>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/knn.hpp"

namespace bhcl::render {
class Progress;
}

namespace bhcl::cli {

// A command-line mistake: bhcl prints it as one line and exits with status 2.
struct UsageError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// The options of one sub-command, on CLI11: declared with their meaning and default (what
// `bhcl CMD --help` lists), parsed, then read back with their checks (integers range-checked
// against the declared range, never narrowed). Values are kept as the text given, so that every
// check says what was wrong in the same words.
class Args {
 public:
  static constexpr long long kNoLimit = std::numeric_limits<long long>::max();

  Args(CLI::App* app, std::string command) : app_(app), command_(std::move(command)) {}
  Args(const Args&) = delete;
  Args& operator=(const Args&) = delete;

  // Declarations, before parsing. `def` is the default as shown by --help ("" shows none).
  void add_text(const std::string& name, const std::string& help, const std::string& def = "",
                const std::string& type = "TEXT");
  void add_required(const std::string& name, const std::string& help, const std::string& type = "FILE");
  void add_integer(const std::string& name, const std::string& help, long long lo, long long hi,
                   const std::string& def);
  void add_number(const std::string& name, const std::string& help, const std::string& def);
  void add_flag(const std::string& name, const std::string& help);
  // An option of a method table: parsed and range-checked by its entry (OptionInfo::parse).
  void add_table_option(const OptionInfo& o, const std::string& help, const std::string& type);
  // The help group of the options declared next ("" for the main list).
  void group(const std::string& name) { group_ = name; }

  // After parsing: throws UsageError for an option nobody declared or a stray argument.
  void check_extras() const;

  const std::string& command() const { return command_; }
  bool has(const std::string& key) const;
  std::string str(const std::string& key) const;  // required
  std::string str(const std::string& key, const std::string& fallback) const;
  // Range-checked against the declared range (UsageError naming the option otherwise).
  long long integer(const std::string& key, long long fallback) const;
  long long integer(const std::string& key) const;  // required
  double number(const std::string& key, double fallback) const;
  bool flag(const std::string& key) const { return has(key); }
  // A table option's value, checked by its entry (UsageError naming the option otherwise).
  OptionValue table_value(const std::string& key) const;

 private:
  CLI::Option* add(const std::string& name, const std::string& help, const std::string& def,
                   const std::string& type);
  CLI::App* app_;
  std::string command_;
  std::string group_;
  std::map<std::string, std::string> values_;  // node-based: CLI11 keeps pointers into it
  std::map<std::string, std::pair<long long, long long>> ranges_;
  std::map<std::string, const OptionInfo*> table_;  // the registry's entries (static storage)
};

// Stats files: JSON objects in insertion order (nlohmann-json).
using Json = nlohmann::ordered_json;
// Writes `j` (indented) to `path`; throws bhcl::Error naming the path on failure.
void write_json(const std::string& path, const Json& j);
// What every stats file starts with: the tool and library version, the command and the device.
Json stats_header(const std::string& command, const Runtime& rt);
// The fields every image's stats file carries next: scene, scene_arg (--scene), width, height, spp.
void add_image_fields(Json& j, const Args& args, const std::string& scene, int width, int height, int spp);
// The timings and counts of a query call (with the index's build time) into a stats object.
void add_query_stats(Json& j, const Index& index, const QueryStats& st);
void add_query_stats(Json& j, double build_s, const QueryStats& st);  // an index built elsewhere
// The stats file's "stages": compile, sort, upload, kernel, download, unsort, write (the output
// files' appends, timed by the caller), other (the rest of wall), wall, wall / kernel, and commit
// (the files' flush and renames after the call).
Json stages_json(const QueryStats& st, double write_s, double commit_s);
// The inputs of a knn or eval run: the point and query files, N, n, k and the radius.
Json inputs_json(const Args& args, std::size_t N, std::size_t n, const SearchParams& p);
// The build parameters an index actually used (SearchIndex::build_used: derived ones
// filled in) and the search parameters of a query with `p` (defaults resolved: the work-group
// size, SearchIndex::search_used), so that a run can be reproduced.
Json build_json(const Index& index, const MethodOptions& options);
Json search_json(const Index& index, const SearchParams& p);

// --device, as every command that runs kernels reads it.
void declare_device_option(Args& args);
// --points, --queries (required, any point format) and the required --method of knn and eval.
void declare_data_options(Args& args, const std::string& method_help);

// The tail of knn's and eval's options: --stats (with `stats_help`), --device, --quiet and the
// index options below.
void declare_run_options(Args& args, const std::string& stats_help);

// Options shared by every command that builds and queries an index (knn, eval, render): --k,
// --max-radius and every search and build option of the method tables (the radius-only ones
// with `radius`). `render`: --seed and --threads also drive the renderer (their help says so).
void declare_index_options(Args& args, int default_k = 10, bool render = false, bool radius = false);
MethodOptions method_options(const Args& args);
SearchParams search_params(const Args& args, int default_k = 10);
// Throws UsageError for a method option given although none of `methods` reads it (e.g. --A for
// kdtree, --threads for anything but flann); `also` lists options the command itself reads.
// An unknown method skips the check: make_index names it.
void check_method_options(const Args& args, const std::vector<std::string>& methods,
                          std::set<std::string> also = {});
// Builds the index (make_index) and answers the queries in slices, drawing a progress bar on a
// terminal (unless `quiet`): the build, then the query batches. Results do not depend on the
// slicing (the contract); the stats are the slices' sums (wall time: the whole call).
std::unique_ptr<Index> build_with_progress(const std::string& method, std::shared_ptr<Runtime> rt,
                                           const std::vector<float>& points,
                                           const MethodOptions& options, bool quiet);
QueryStats query_with_progress(const SearchIndex& index, const std::vector<float>& queries,
                               const SearchParams& params, KnnResult& out, bool quiet);
// The same for a radius search (Index::radius_search; the slices concatenated).
QueryStats radius_with_progress(const SearchIndex& index, const std::vector<float>& queries, float radius,
                                const RadiusParams& params, RadiusResult& out, bool quiet);
// The same, each slice handed to `sink` as it finishes (first query, its rows) and then dropped,
// so that the whole result is never held (bhcl knn writes the slices as they come, ResultFiles).
// kNN slices hold about 256 MiB of rows (knn_slice_rows), radius slices 2^18 queries; with a
// progress bar also about a hundredth of the batch each.
using KnnSink = std::function<void(std::size_t first, const KnnResult& part)>;
using RadiusSink = std::function<void(std::size_t first, const RadiusResult& part)>;
QueryStats query_in_slices(const SearchIndex& index, const std::vector<float>& queries, const SearchParams& params,
                           bool quiet, const KnnSink& sink);
QueryStats radius_in_slices(const SearchIndex& index, const std::vector<float>& queries, float radius,
                            const RadiusParams& params, bool quiet, const RadiusSink& sink);
// slice_bytes: the rows' bytes a slice aims at (0: 256 MiB); direct outputs ask direct_slice_bytes().
std::size_t knn_slice_rows(std::size_t n, int k, bool count_examined, bool bar, std::size_t slice_bytes = 0);
std::size_t direct_slice_bytes();
std::size_t radius_slice_rows(std::size_t n, bool bar);
// The last slice of a batch whose slices' writes run beside the next slice's search (direct
// outputs): a quarter of `rows`, at least 2^15 queries (BHCL_LAST_SLICE_ROWS overrides; 0: as
// the others). Its write is the one no search hides.
std::size_t direct_last_slice_rows(std::size_t rows);
// Where each slice of a call of n_all queries starts (and n_all at the end): slices of `rows`, the
// remainder last; with last_rows (0: none), a last slice of last_rows and the rest spread evenly
// over as few slices of at most `rows` as hold them. The same on every rank of a job (n_all and
// rows are).
std::vector<std::size_t> slice_starts(std::size_t n_all, std::size_t rows, std::size_t last_rows = 0);
// The slice loop under bhcl's runners: the slices of slice_starts(n_all, rows, last_rows) of a
// call of n_all, each through answer(first, m) for this process's part of it (n of them: n_all in
// one process; an MPI job's ranks make every call, rank 0 with its queries, the others with none,
// n = 0); no queries: one empty slice. The stats summed, the bar drawn, the wall time of the loop.
QueryStats in_slices(std::size_t n, std::size_t n_all, std::size_t rows, render::Progress& bar,
                     const std::function<QueryStats(std::size_t, std::size_t)>& answer, std::size_t last_rows = 0);
// --radius and the tables' radius options, checked for `methods`: --k, --max-radius and the
// kNN-only options are refused with it, r must be finite and >= 0 (the caller adds its own, e.g.
// knn's --max-results).
RadiusParams radius_search_options(const Args& args, const std::vector<std::string>& methods, float& radius);
// The method table's options in `scope` as JSON, by name: the value given, else the default.
Json table_values(const Args& args, const std::string& method, unsigned scope);

// A file a command reads or writes, by the option that names it.
struct FileArg {
  std::string option;  // e.g. "--points"; for derived outputs a description ("the PNG beside --out")
  std::string path;
};
// Before any work: throws UsageError when an output names an input, or two outputs name one file
// (the same path after resolving symlinks and "..", or the same existing file by device and
// inode). Empty paths are skipped.
void check_distinct_files(const std::vector<FileArg>& inputs, const std::vector<FileArg>& outputs);

// "a, b or c" from the registry's names, for --method's help.
std::string method_list(const std::vector<std::string>& names);
// Reads --points and --queries; an empty file is an error naming it.
void read_points_and_queries(const Args& args, std::vector<float>& points, std::vector<float>& queries);
// What knn and eval read before they search, in this order: the method options; the files,
// checked against each other before any work (inputs --points, --queries, --load-index; the
// command's `outputs` and --stats, --save-index); the points and queries; the device (--device).
// With `beside_reading`: the device first, then that run (with the device and the method
// options) on a thread of its own while the files are read (reading is one thread's work: bhcl
// knn builds its query's program there), joined after; what it throws is dropped (the build and
// the query name any real error again).
struct CommandInputs {
  MethodOptions mopt;
  std::vector<float> points, queries;
  std::size_t N = 0, n = 0;  // points and queries
  std::shared_ptr<Runtime> rt;
  struct Beside {
    double own_s = 0;   // beside_reading's own time
    double wait_s = 0;  // the time the join after the reading waited for it
  } beside;
};
CommandInputs read_command_inputs(const Args& args, std::vector<FileArg> outputs,
                                  const std::function<void(const Runtime&, const MethodOptions&)>& beside_reading = {});

// --size WxH (each 1 to 16384); UsageError otherwise.
void parse_image_size(const std::string& s, int& w, int& h);
// The path without its last extension ("a/b.exr" -> "a/b"; "a.d/b" stays).
std::string strip_extension(const std::string& path);
// True for a path that exists and is neither a regular file nor a directory (/dev/null, a FIFO).
bool names_device(const std::string& path);
// The file written beside the output `out` (base: out without its extension): base + suffix, or
// out itself when out names a device or FIFO (a PNG preview of --out /dev/null goes to /dev/null).
std::string beside_output(const std::string& out, const std::string& base, const std::string& suffix);

}  // namespace bhcl::cli
