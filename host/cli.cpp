#include "cli.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <future>
#include <optional>

#include <sys/stat.h>

#include "blockhash_cl/config.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/numbers.hpp"
#include "progress.hpp"

namespace bhcl::cli {

namespace {
// How read_points_and_queries stored this run's coordinates (one read per bhcl run), for the stats.
bool g_coords_read = false;
Recentring g_coords;
}  // namespace


CLI::Option* Args::add(const std::string& name, const std::string& help, const std::string& def,
                       const std::string& type) {
  CLI::Option* o = app_->add_option("--" + name, values_[name], help);
  o->type_name(type)->multi_option_policy(CLI::MultiOptionPolicy::TakeLast);
  if (!def.empty()) o->default_str(def);
  if (!group_.empty()) o->group(group_);
  return o;
}

void Args::add_text(const std::string& name, const std::string& help, const std::string& def,
                    const std::string& type) {
  add(name, help, def, type);
}

void Args::add_required(const std::string& name, const std::string& help, const std::string& type) {
  add(name, help, "", type)->required();
}

void Args::add_integer(const std::string& name, const std::string& help, long long lo, long long hi,
                       const std::string& def) {
  ranges_[name] = {lo, hi};
  std::string range = hi == kNoLimit ? " (>= " + std::to_string(lo) + ")"
                                     : " (" + std::to_string(lo) + " to " + std::to_string(hi) + ")";
  add(name, help + range, def, "INT");
}

void Args::add_table_option(const OptionInfo& o, const std::string& help, const std::string& type) {
  table_[o.name] = &o;
  add(o.name, help, o.def, type);
}

OptionValue Args::table_value(const std::string& key) const {
  const std::string v = str(key);
  try {
    return table_.at(key)->parse(v, "--" + key);
  } catch (const Error& e) {
    throw UsageError(e.what());
  }
}

void Args::add_number(const std::string& name, const std::string& help, const std::string& def) {
  add(name, help, def, "NUM");
}

void Args::add_flag(const std::string& name, const std::string& help) {
  CLI::Option* o = app_->add_flag("--" + name, help);
  if (!group_.empty()) o->group(group_);
}

void Args::check_extras() const {
  for (const std::string& a : app_->remaining()) {
    if (a.rfind("--", 0) == 0 && a.size() > 2) throw UsageError("unknown option " + a.substr(0, a.find('=')));
    throw UsageError("unexpected argument '" + a + "'");
  }
}

bool Args::has(const std::string& key) const {
  const CLI::Option* o = app_->get_option_no_throw("--" + key);  // undeclared: not given
  return o && o->count() != 0;
}

std::string Args::str(const std::string& key) const {
  if (!has(key)) throw UsageError("missing required option --" + key);
  return values_.at(key);
}

std::string Args::str(const std::string& key, const std::string& fallback) const {
  return has(key) ? values_.at(key) : fallback;
}

long long Args::integer(const std::string& key) const {
  if (table_.count(key)) return table_value(key).integer;
  const std::string v = str(key);
  auto range = ranges_.find(key);
  const long long lo = range == ranges_.end() ? std::numeric_limits<long long>::min() : range->second.first;
  const long long hi = range == ranges_.end() ? kNoLimit : range->second.second;
  auto out_of_range = [&] {
    return UsageError(hi == kNoLimit ? "--" + key + " must be >= " + std::to_string(lo) + ", got " + v
                                     : "--" + key + " must be in [" + std::to_string(lo) + ", " +
                                           std::to_string(hi) + "], got " + v);
  };
  std::size_t pos = 0;
  long long x = 0;
  try {
    x = std::stoll(v, &pos);
  } catch (const std::out_of_range&) {
    throw out_of_range();
  } catch (...) {
    pos = 0;
  }
  if (pos == 0 || pos != v.size()) throw UsageError("--" + key + " expects an integer, got '" + v + "'");
  if (x < lo || x > hi) throw out_of_range();
  return x;
}

long long Args::integer(const std::string& key, long long fallback) const {
  return has(key) ? integer(key) : fallback;
}

double Args::number(const std::string& key, double fallback) const {
  if (!has(key)) return fallback;
  if (table_.count(key)) return table_value(key).number;
  std::string v = str(key);
  double x = 0;  // locale-free (numbers.hpp); past the double range: +-inf, as strtod
  if (bhcl::detail::parse_double(v, x) == bhcl::detail::NumberParse::NotNumber) throw UsageError("--" + key + " expects a number, got '" + v + "'");
  return x;
}

void write_json(const std::string& path, const Json& j) {
  // Non-finite numbers (an unbounded radius) are written as null.
  write_file(path, {j.dump(2), "\n"}, "the stats");
}

Json stats_header(const std::string& command, const Runtime& rt) {
  Json j;
  j["tool"] = "bhcl";
  j["version"] = BHCL_VERSION_STRING;
  j["command"] = command;
  j["device"] = rt.info().summary();
  return j;
}

void add_image_fields(Json& j, const Args& args, const std::string& scene, int width, int height, int spp) {
  j["scene"] = scene;
  j["scene_arg"] = args.str("scene", "cornell");
  j["width"] = width;
  j["height"] = height;
  j["spp"] = spp;
}

void add_query_stats(Json& j, const Index& index, const QueryStats& st) {
  add_query_stats(j, index.build_seconds(), st);
}

void add_query_stats(Json& j, double build_s, const QueryStats& st) {
  j["build_s"] = build_s;
  st.for_each_field([&](const char* name, auto value) { j[name] = value; });
  if (g_coords_read) {
    // The precision the stored float32 coordinates leave, in the files' units.
    j["coordinates"] = {{"recentred", g_coords.recentred},
                        {"origin", {g_coords.origin[0], g_coords.origin[1], g_coords.origin[2]}},
                        {"max_abs_relative", g_coords.max_abs_relative},
                        {"float32_step", g_coords.float32_step},
                        {"max_rounding", 0.5 * g_coords.float32_step}};
  }
}

Json stages_json(const QueryStats& st, double write_s, double commit_s) {
  // Where the call's time went, stage by stage (host clock; the kernel's from its events), and
  // what none of them covers (the exact check's double-precision rows, thread starts, waits).
  const double named = st.compile_s + st.sort_s + st.upload_s + st.query_s + st.download_s + st.unsort_s;
  Json j;
  j["compile_s"] = st.compile_s;
  j["sort_s"] = st.sort_s;
  j["upload_s"] = st.upload_s;
  j["kernel_s"] = st.query_s;
  j["download_s"] = st.download_s;
  j["unsort_s"] = st.unsort_s;
  j["write_s"] = write_s;    // the output files' appends, inside wall_s
  j["commit_s"] = commit_s;  // their flush and renames, after wall_s
  j["other_s"] = std::max(0.0, st.wall_s - named - write_s);
  j["wall_s"] = st.wall_s;
  j["wall_over_kernel"] = st.query_s > 0 ? st.wall_s / st.query_s : 0.0;
  return j;
}

Json inputs_json(const Args& args, std::size_t N, std::size_t n, const SearchParams& p) {
  Json j;
  j["points"] = args.str("points");
  j["queries"] = args.str("queries");
  j["N"] = N;
  j["n"] = n;
  j["k"] = p.k;
  j["max_radius"] = p.max_radius;  // null: unbounded
  return j;
}

Json build_json(const Index& index, const MethodOptions& options) {
  Json b = Json::object();
  for (const auto& [name, value] : index.build_used()) b[name] = Json::parse(value);
  if (index.saves()) {
    // A loaded index carries its own jitter; the seed given only matters for a build.
    if (options.load_index().empty()) b["seed"] = options.integer("seed", 1);
    if (!options.load_index().empty()) b["load_index"] = options.load_index();
    if (!options.save_index().empty()) b["save_index"] = options.save_index();
  }
  return b;
}

Json search_json(const Index& index, const SearchParams& p) {
  Json s;
  s["k"] = p.k;
  s["max_radius"] = p.max_radius;  // null: unbounded
  for (const auto& [name, value] : index.search_used(p)) s[name] = Json::parse(value);
  if (method_info(index.method()).on_device) {
    s["local_size"] = index.local_size_for(p);
    s["max_batch"] = p.max_batch;  // 0: automatic
  }
  s["sort_queries"] = p.sort_queries;
  return s;
}

namespace {

// The methods whose option table holds `name`, in display order.
std::vector<std::string> option_users(const std::string& name) {
  std::vector<std::string> users;
  for (const MethodInfo& m : methods())
    if (std::any_of(m.options.begin(), m.options.end(), [&](const OptionInfo& o) { return o.name == name; }))
      users.push_back(m.name);
  return users;
}

std::string joined(const std::vector<std::string>& v, const char* sep) {
  std::string s;
  for (const auto& x : v) s += (s.empty() ? "" : sep) + x;
  return s;
}

// Every option of the registry's tables in `scope` once (the first entry that declares it
// describes it).
std::vector<const OptionInfo*> table_options(unsigned scope) {
  std::vector<const OptionInfo*> all;
  for (const MethodInfo& m : methods())
    for (const OptionInfo* o : options_in(m.options, scope))
      if (std::none_of(all.begin(), all.end(), [&](const OptionInfo* x) { return x->name == o->name; }))
        all.push_back(o);
  return all;
}
std::vector<const OptionInfo*> build_options() { return table_options(OptionInfo::Build); }

// Declares one table option, its help prefixed by the methods that read it.
void declare_table_option(Args& a, const OptionInfo& o, std::string help) {
  switch (o.kind) {
    case OptionInfo::Kind::Integer:
    case OptionInfo::Kind::Number:
      a.add_table_option(o, help + " (" + o.range_text() + ")", o.kind == OptionInfo::Kind::Integer ? "INT" : "NUM");
      break;
    case OptionInfo::Kind::Choice:
      a.add_table_option(o, help + " (" + joined(o.choices, ", ") + ")", "NAME");
      break;
    case OptionInfo::Kind::File:
      a.add_table_option(o, help, "FILE");
      break;
  }
}

}  // namespace

void declare_device_option(Args& a) {
  a.add_text("device", "OpenCL device: P:D, cpu, gpu or a name fragment (default: BHCL_DEVICE, then PoCL); knn takes a comma list for several devices",
             "", "SPEC");
}

void declare_data_options(Args& a, const std::string& method_help) {
  a.add_required("points", "the point set: PLY, NPY (N x 3 float32/float64), text (x y z per line) or raw float32");
  a.add_required("queries", "the query points (same formats as --points)");
  a.add_required("method", method_help, "NAME");
}

void declare_run_options(Args& a, const std::string& stats_help) {
  a.add_text("stats", stats_help, "", "FILE");
  declare_device_option(a);
  a.add_flag("quiet", "no progress bars");
  declare_index_options(a, 10, false, true);
}

void declare_index_options(Args& a, int default_k, bool render, bool radius) {
  a.group("Search options");
  a.add_integer("k", "neighbours per query", 1, kMaxK, std::to_string(default_k));
  a.add_number("max-radius", "only neighbours within this Euclidean distance", "inf");
  // From the method tables: each option once, with the methods that read it.
  for (const OptionInfo* o : table_options(OptionInfo::Search)) declare_table_option(a, *o, joined(option_users(o->name), ", ") + ": " + o->help);
  if (radius) {
    a.group("Radius search");
    for (const OptionInfo* o : table_options(OptionInfo::Radius))
      if (!(o->scope & OptionInfo::Search)) declare_table_option(a, *o, "with --radius, " + joined(option_users(o->name), ", ") + ": " + o->help);
  }
  a.group("Build options");
  for (const OptionInfo* o : build_options()) {
    std::string help = joined(option_users(o->name), ", ") + ": " + o->help;
    if (render && o->name == "seed") help = "seed of the rays (and of the photons unless --photon-seed), and " + help;
    if (render && o->name == "threads") help = "host threads of Embree and the photon tracer, and " + help;
    declare_table_option(a, *o, help);
  }
  a.group("");
}

void check_method_options(const Args& args, const std::vector<std::string>& methods,
                          std::set<std::string> also) {
  const auto known = method_names();
  for (const auto& m : methods)
    if (std::find(known.begin(), known.end(), m) == known.end()) return;
  std::vector<std::string> only;
  for (const OptionInfo* o : table_options(OptionInfo::Build | OptionInfo::Search | OptionInfo::Radius)) only.push_back(o->name);
  for (const OptionInfo* o : table_options(OptionInfo::Radius))  // kNN: refused later, as radius-only
    if (!(o->scope & OptionInfo::Search) && !args.has("radius")) also.insert(o->name);
  for (const auto& option : only) {
    if (!args.has(option) || also.count(option)) continue;
    const std::vector<std::string> users = option_users(option);
    bool used = false;
    for (const auto& m : methods) used = used || std::find(users.begin(), users.end(), m) != users.end();
    if (used) continue;
    throw UsageError("--" + option + " does not apply to method " + joined(methods, " and ") +
                     " (only to " + joined(users, ", ") + ")");
  }
}

RadiusParams radius_search_options(const Args& args, const std::vector<std::string>& methods, float& radius) {
  for (const char* o : {"k", "max-radius"})
    if (args.has(o)) throw UsageError(std::string("--") + o + " does not apply with --radius");
  for (const OptionInfo* o : table_options(OptionInfo::Search))
    if (!(o->scope & OptionInfo::Radius) && args.has(o->name))
      throw UsageError("--" + o->name + " does not apply with --radius");
  check_method_options(args, methods);
  const double r = args.number("radius", 0.0);
  if (!std::isfinite(r) || r < 0 || !std::isfinite(static_cast<float>(r)))
    throw UsageError("--radius must be a finite number >= 0");
  radius = static_cast<float>(r);
  RadiusParams rp;
  for (const OptionInfo* o : table_options(OptionInfo::Radius))
    if (args.has(o->name)) o->set_radius(&rp, args.table_value(o->name));
  return rp;
}

Json table_values(const Args& args, const std::string& method, unsigned scope) {
  Json j = Json::object();
  for (const OptionInfo* o : options_in(method_info(method).options, scope)) {
    if (o->kind == OptionInfo::Kind::File) continue;
    const OptionValue v = args.has(o->name) ? args.table_value(o->name) : o->parse(o->def.empty() ? "0" : o->def);
    if (o->kind == OptionInfo::Kind::Integer) j[o->name] = v.integer;
    else if (o->kind == OptionInfo::Kind::Number) j[o->name] = v.number;
    else j[o->name] = v.text;
  }
  return j;
}

// The count in environment variable `var` (unset or empty: nullopt); anything but a count (or 0,
// where `positive`) is a usage error that names the variable.
static std::optional<std::size_t> env_count(const char* var, bool positive) {
  const char* e = std::getenv(var);
  if (!e || !*e) return std::nullopt;
  char* end = nullptr;
  const unsigned long long v = std::strtoull(e, &end, 10);
  if (*end != '\0' || (positive && v == 0))
    throw UsageError(std::string(var) + (positive ? " must be a positive count" : " must be a count") + ", got '" + e + "'");
  return static_cast<std::size_t>(v);
}

// BHCL_SLICE_ROWS (a positive count): the most queries a slice holds, overriding the sizes below
// (the tests drive many slices through small batches with it). 0: not set.
static std::size_t slice_rows_override() { return env_count("BHCL_SLICE_ROWS", true).value_or(0); }

std::size_t direct_slice_bytes() {
  // BHCL_DIRECT_SLICE_MB (a positive count of MiB) overrides the 32 MiB (experiments).
  if (const char* e = std::getenv("BHCL_DIRECT_SLICE_MB"); e && *e) {
    char* end = nullptr;
    const unsigned long long v = std::strtoull(e, &end, 10);
    if (*end == '\0' && v > 0) return static_cast<std::size_t>(v) << 20;
  }
  return std::size_t(32) << 20;
}

std::size_t knn_slice_rows(std::size_t n, int k, bool count_examined, bool bar, std::size_t slice_bytes) {
  if (const std::size_t o = slice_rows_override()) return std::max<std::size_t>(1, std::min(o, n));
  // About 256 MiB of rows a slice (ids, squared distances, the count, the examined count), at
  // least 2^15 queries (large enough for the Hilbert dispatch order and full devices); with a
  // progress bar also about a hundredth of the batch. Counted with the query's 12 bytes as the
  // library's chunks are (Index::KnnKind::chunk_rows: 8 k + 12 a query), so that a slice is one
  // chunk: at k = 50 a 664k-query slice had been a 651k chunk and a 13k one (two launches, and
  // no gather in the sort's pass).
  const std::size_t row = static_cast<std::size_t>(k) * 8 + 12 + (count_examined ? 4 : 0);
  // A smaller slice_bytes (direct outputs) keeps at least 2^17 queries a slice: 81k-query slices
  // in 4 KiB pages made the kernel 1.2x slower at 1M x 50 (Cornell 1M, AVX-512, 2 threads); in the
  // direct buffers' 2 MiB pages 2^17 against 2^18: kernel 1.045, process 0.875 (half the fresh
  // memory), 2^16 against 2^17: 0.99 (bench/results/e2e/direct_output_h37f.md).
  const std::size_t floor_rows = slice_bytes ? std::size_t(1) << 17 : std::size_t(1) << 15;
  if (slice_bytes == 0) slice_bytes = std::size_t(256) << 20;
  std::size_t rows = std::max<std::size_t>(floor_rows, slice_bytes / row);
  rows = std::min(rows, std::max<std::size_t>(std::size_t(1) << 15, (std::size_t(256) << 20) / row));
  if (bar) rows = std::min(rows, std::max<std::size_t>(std::size_t(1) << 15, n / 100));
  return std::max<std::size_t>(1, std::min(rows, n));
}

std::size_t direct_last_slice_rows(std::size_t rows) {
  if (const std::optional<std::size_t> v = env_count("BHCL_LAST_SLICE_ROWS", false)) return *v;  // experiments
  // The slice before it writes its `rows` rows beside this one's search of rows / 4 queries; at
  // k = 10 (Cornell 1M, AVX-512, 2 threads) a query's search took 270 ns and a row's 40 bytes
  // about 40 ns to write, so the quarter's search still outlasts that write.
  return std::max<std::size_t>(std::size_t(1) << 15, rows / 4);
}

std::vector<std::size_t> slice_starts(std::size_t n_all, std::size_t rows, std::size_t last_rows) {
  rows = std::max<std::size_t>(rows, 1);
  std::vector<std::size_t> starts{0};
  if (n_all == 0) return starts.push_back(0), starts;
  // No taper where the batch fits one slice, or where the last slice would not be smaller.
  const std::size_t last = last_rows && last_rows < rows && n_all > rows ? last_rows : 0;
  const std::size_t rest = n_all - last, slices = (rest + rows - 1) / rows;
  for (std::size_t s = 1; s <= slices; ++s)  // tapered: the rest even; else slices of `rows`, the remainder last
    starts.push_back(last ? rest / slices * s + std::min(s, rest % slices) : std::min(rest, s * rows));
  if (last) starts.push_back(n_all);
  return starts;
}

QueryStats in_slices(std::size_t n, std::size_t n_all, std::size_t rows, render::Progress& bar,
                     const std::function<QueryStats(std::size_t, std::size_t)>& answer, std::size_t last_rows) {
  auto t0 = std::chrono::steady_clock::now();
  QueryStats total;
  const std::vector<std::size_t> starts = slice_starts(n_all, rows, last_rows);
  for (std::size_t s = 0; s + 1 < starts.size(); ++s) {
    const std::size_t first = std::min(n, starts[s]), m = std::min(starts[s + 1], n) - first;
    total.add_slice(answer(first, m));
    bar.update(double(starts[s + 1]) / double(std::max<std::size_t>(n_all, 1)));
  }
  bar.finish();
  total.n_queries = n;
  total.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return total;
}

std::size_t radius_slice_rows(std::size_t n, bool bar) {
  if (const std::size_t o = slice_rows_override()) return o;
  // A slice's result is known only after its search: 2^18 queries bound it (with a bar, about a
  // hundredth of the batch, at least 2^15).
  std::size_t rows = std::size_t(1) << 18;
  if (bar) rows = std::min(rows, std::max<std::size_t>(std::size_t(1) << 15, n / 100));
  return rows;
}

QueryStats radius_in_slices(const SearchIndex& index, const std::vector<float>& queries, float radius,
                            const RadiusParams& params, bool quiet, const RadiusSink& sink) {
  const std::size_t n = queries.size() / 3;
  render::Progress bar("radius " + index.method() + " (" + std::to_string(n) + " queries)", !quiet);
  RadiusResult part;
  return in_slices(n, n, radius_slice_rows(n, bar.enabled()), bar, [&](std::size_t first, std::size_t m) {
    const QueryStats st = index.radius_search(queries.data() + 3 * first, m, radius, params, part);
    sink(first, part);
    return st;
  });
}

QueryStats radius_with_progress(const SearchIndex& index, const std::vector<float>& queries, float radius,
                                const RadiusParams& params, RadiusResult& all, bool quiet) {
  all = RadiusResult{};
  all.offsets.assign(1, 0);
  QueryStats st = radius_in_slices(index, queries, radius, params, quiet, [&](std::size_t, const RadiusResult& part) {
    const std::int64_t base = all.offsets.back();
    for (std::size_t i = 1; i <= part.n; ++i) all.offsets.push_back(base + part.offsets[i]);
    all.ids.insert(all.ids.end(), part.ids.begin(), part.ids.end());
    all.dist2.insert(all.dist2.end(), part.dist2.begin(), part.dist2.end());
    all.found.insert(all.found.end(), part.found.begin(), part.found.end());
    all.examined.insert(all.examined.end(), part.examined.begin(), part.examined.end());
    all.truncated_queries += part.truncated_queries;
  });
  all.n = queries.size() / 3;
  return st;
}

std::unique_ptr<Index> build_with_progress(const std::string& method, std::shared_ptr<Runtime> rt,
                                           const std::vector<float>& points,
                                           const MethodOptions& options, bool quiet) {
  const std::size_t N = points.size() / 3;
  render::Progress bar((options.load_index().empty() ? "build " : "load ") + method + " (" +
                           std::to_string(N) + " points)",
                       !quiet);
  bar.update(0.0);
  auto index = make_index(method, std::move(rt), points.data(), N, options);
  bar.finish();
  return index;
}

QueryStats query_in_slices(const SearchIndex& index, const std::vector<float>& queries, const SearchParams& params,
                           bool quiet, const KnnSink& sink) {
  const std::size_t n = queries.size() / 3;
  render::Progress bar("query " + index.method() + " (" + std::to_string(n) + " queries)", !quiet);
  const std::size_t slice = knn_slice_rows(n, params.k, params.count_examined, bar.enabled());
  KnnResult part;
  return in_slices(n, n, slice, bar, [&](std::size_t first, std::size_t m) {
    const QueryStats st = index.query(queries.data() + 3 * first, m, params, part);
    sink(first, part);
    return st;
  });
}

QueryStats query_with_progress(const SearchIndex& index, const std::vector<float>& queries,
                               const SearchParams& params, KnnResult& out, bool quiet) {
  const std::size_t n = queries.size() / 3, k = static_cast<std::size_t>(params.k);
  out.resize(n, params.k);
  if (params.count_examined) out.examined.assign(n, 0);
  return query_in_slices(index, queries, params, quiet, [&](std::size_t first, const KnnResult& part) {
    std::copy(part.ids.begin(), part.ids.end(), out.ids.begin() + first * k);
    std::copy(part.dist2.begin(), part.dist2.end(), out.dist2.begin() + first * k);
    std::copy(part.counts.begin(), part.counts.end(), out.counts.begin() + first);
    if (params.count_examined) std::copy(part.examined.begin(), part.examined.end(), out.examined.begin() + first);
  });
}

namespace {

// One file's identity: device and inode when it exists, else its resolved absolute path.
std::string file_identity(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0)
    return "inode " + std::to_string(st.st_dev) + ":" + std::to_string(st.st_ino);
  std::error_code ec;
  std::filesystem::path p = std::filesystem::weakly_canonical(std::filesystem::absolute(path, ec), ec);
  return "path " + (ec ? path : p.string());
}

}  // namespace

void check_distinct_files(const std::vector<FileArg>& inputs, const std::vector<FileArg>& outputs) {
  std::vector<std::pair<std::string, const FileArg*>> seen;  // identity, and who named it
  for (const FileArg& in : inputs)
    if (!in.path.empty()) seen.emplace_back(file_identity(in.path), &in);
  const std::size_t n_inputs = seen.size();
  for (const FileArg& out : outputs) {
    if (out.path.empty()) continue;
    const std::string id = file_identity(out.path);
    // A character device (/dev/null) takes any number of outputs (render --out /dev/null sends
    // its PNG preview there too); as an input it is still refused below.
    struct stat st {};
    const bool device = ::stat(out.path.c_str(), &st) == 0 && S_ISCHR(st.st_mode);
    for (std::size_t i = 0; i < seen.size(); ++i) {
      if (seen[i].first != id || (device && i >= n_inputs)) continue;
      if (i < n_inputs)
        throw UsageError(out.option + " " + out.path + " is the input " + seen[i].second->option +
                         ": writing it would destroy it");
      throw UsageError(out.option + " and " + seen[i].second->option + " name the same file " + out.path);
    }
    seen.emplace_back(id, &out);
  }
}

std::string method_list(const std::vector<std::string>& names) {
  std::string s;
  for (std::size_t i = 0; i < names.size(); ++i)
    s += (i == 0 ? "" : i + 1 == names.size() ? " or " : ", ") + names[i];
  return s;
}

CommandInputs read_command_inputs(const Args& args, std::vector<FileArg> outputs,
                                  const std::function<void(const Runtime&, const MethodOptions&)>& beside_reading) {
  CommandInputs in;
  in.mopt = method_options(args);
  outputs.push_back({"--stats", args.str("stats", "")});
  outputs.push_back({"--save-index", in.mopt.save_index()});
  check_distinct_files({{"--points", args.str("points")}, {"--queries", args.str("queries")},
                        {"--load-index", in.mopt.load_index()}},
                       outputs);
  std::future<void> beside;
  if (beside_reading) {
    in.rt = std::make_shared<Runtime>(args.str("device", ""));
    beside = std::async(std::launch::async, [&beside_reading, &in] {
      const auto t0 = std::chrono::steady_clock::now();
      try {
        beside_reading(*in.rt, in.mopt);
      } catch (const std::exception&) {
      }
      in.beside.own_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    });
  }
  read_points_and_queries(args, in.points, in.queries);
  if (beside.valid()) {
    const auto t0 = std::chrono::steady_clock::now();
    beside.get();
    in.beside.wait_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
  in.N = in.points.size() / 3;
  in.n = in.queries.size() / 3;
  if (!in.rt) in.rt = std::make_shared<Runtime>(args.str("device", ""));
  return in;
}

void read_points_and_queries(const Args& args, std::vector<float>& points, std::vector<float>& queries) {
  // float64 kept: the files' coordinates in double, re-centred on the points' box where that
  // gains precision (georeferenced data), then stored in float32 relative to it; the queries
  // relative to the same origin, so distances stay in the files' units.
  std::vector<double> pw = read_points_file_f64(args.str("points"), &points);
  if (points.empty()) throw Error(args.str("points") + ": the point file is empty (0 points)");
  std::vector<double> qw = read_points_file_f64(args.str("queries"), &queries);
  if (queries.empty()) throw Error(args.str("queries") + ": the query file is empty (0 queries)");
  g_coords = choose_origin(pw.data(), pw.size() / 3);
  if (g_coords.recentred) {
    points = relative_points(pw.data(), pw.size() / 3, g_coords, args.str("points"));
    queries = relative_points(qw.data(), qw.size() / 3, g_coords, args.str("queries"));
  } else {
    relative_points(pw.data(), pw.size() / 3, g_coords, args.str("points"));  // the figures only
  }
  g_coords_read = true;
}

MethodOptions method_options(const Args& args) {
  MethodOptions m;
  for (const OptionInfo* o : build_options()) {
    if (!args.has(o->name)) continue;
    args.table_value(o->name);  // checked against the table (UsageError naming the option)
    m.set(o->name, args.str(o->name));
  }
  // A saved index carries its own build parameters: a build option beside --load-index would be
  // silently ignored, so it is refused.
  if (!m.load_index().empty())
    for (const MethodInfo& method : methods())
      for (const OptionInfo* o : method.build_options())
        if (method.saves && o->name != "load-index" && o->name != "save-index" && args.has(o->name))
          throw UsageError("--" + o->name + " does not apply with --load-index (the saved index carries its build parameters)");
  return m;
}

SearchParams search_params(const Args& args, int default_k) {
  SearchParams p;
  p.k = static_cast<int>(args.integer("k", default_k));  // range-checked: [1, kMaxK]
  p.max_radius = static_cast<float>(args.number("max-radius", INFINITY));
  if (std::isnan(p.max_radius) || p.max_radius < 0)
    throw UsageError("--max-radius must be a non-negative number");
  for (const OptionInfo* o : table_options(OptionInfo::Radius))
    if (!(o->scope & OptionInfo::Search) && args.has(o->name))
      throw UsageError("--" + o->name + " applies only with --radius");
  for (const OptionInfo* o : table_options(OptionInfo::Search))
    if (args.has(o->name)) o->set_search(&p, args.table_value(o->name));
  if (p.recall_target > 0 && args.has("A")) throw UsageError("--recall and --A both set: give one");
  return p;
}

void parse_image_size(const std::string& s, int& w, int& h) {
  auto x = s.find('x');
  if (x == std::string::npos || bhcl::detail::parse_integer(s.substr(0, x), w) != bhcl::detail::NumberParse::Ok ||
      bhcl::detail::parse_integer(s.substr(x + 1), h) != bhcl::detail::NumberParse::Ok) {
    throw UsageError("--size expects WxH (e.g. 512x512), got '" + s + "'");
  }
  if (w < 1 || h < 1 || w > 16384 || h > 16384) throw UsageError("--size must be between 1x1 and 16384x16384");
}

bool names_device(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0 && !S_ISREG(st.st_mode) && !S_ISDIR(st.st_mode);
}

std::string beside_output(const std::string& out, const std::string& base, const std::string& suffix) {
  // A device or FIFO (/dev/null) has no directory of its own to put a file beside: the companion
  // goes to the same device (issue 38: --out /dev/null made a regular file /dev/null.png).
  return names_device(out) ? out : base + suffix;
}

std::string strip_extension(const std::string& path) {
  auto slash = path.find_last_of('/');
  auto dot = path.find_last_of('.');
  if (dot == std::string::npos || (slash != std::string::npos && dot < slash)) return path;
  return path.substr(0, dot);
}

}  // namespace bhcl::cli
