// The bench programs' command lines, on CLI11 as bhcl's: one flag vocabulary across them and the
// tool (the same name, meaning, type and default where they overlap), lists comma separated,
// numbers range-checked (whole numbers may be written 1e6), `--help` listing every option with its
// meaning and default. A mistake is one line on stderr and exit status 2.
#pragma once

#include <CLI/CLI.hpp>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/knn.hpp"

namespace bhcl::bench {

class BenchCli {
 public:
  BenchCli(const std::string& program, const std::string& description)
      : app_(description, program), program_(program) {
    app_.set_help_flag("--help,-h", "print this help and exit");
    app_.option_defaults()->always_capture_default();
  }
  CLI::App& app() { return app_; }

  // Every option of `method`'s table in `scope` (OptionInfo::Search, ::Build) that is not declared
  // yet and not in `skip`, as --NAME with the table's help, range and default, checked by the
  // table; the given ones land in `given` (by name, as text) for apply_search or MethodOptions.
  void table_options(const std::string& method, unsigned scope, std::map<std::string, std::string>& given,
                     const std::set<std::string>& skip = {}) {
    for (const OptionInfo* o : options_in(method_info(method).options, scope)) {
      if (skip.count(o->name) || o->kind == OptionInfo::Kind::File || app_.get_option_no_throw("--" + o->name)) continue;
      app_.add_option("--" + o->name, given[o->name], method + ": " + o->help + " (" + o->range_text() + ")")
          ->check(table_check(o))
          ->default_str(o->def)
          ->type_name(o->kind == OptionInfo::Kind::Integer ? "INT" : o->kind == OptionInfo::Kind::Number ? "NUM" : "NAME");
    }
  }
  // A CLI11 check by the table's own parser: its message for a value it refuses, else none.
  static std::function<std::string(const std::string&)> table_check(const OptionInfo* o) {
    return [o](const std::string& v) {
      try {
        o->parse(v);
        return std::string();
      } catch (const std::exception& e) {
        return std::string(e.what());
      }
    };
  }
  // The given search options (table_options) into p.
  static void apply_search(const std::string& method, const std::map<std::string, std::string>& given,
                           SearchParams& p) {
    for (const OptionInfo* o : method_info(method).search_options())
      if (auto it = given.find(o->name); it != given.end() && !it->second.empty()) o->set_search(&p, o->parse(it->second));
  }

  // A whole number in [lo, hi] (1e6 accepted); for vectors, each comma-separated element.
  template <typename T>
  CLI::Option* integer(const std::string& name, T& v, const std::string& help, double lo, double hi) {
    return app_.add_option("--" + name, v, help + range(lo, hi))->transform(whole(lo, hi))->type_name("INT");
  }
  template <typename T>
  CLI::Option* integers(const std::string& name, std::vector<T>& v, const std::string& help, double lo,
                        double hi) {
    return app_.add_option("--" + name, v, help + range(lo, hi) + ", comma separated")
        ->delimiter(',')
        ->transform(whole(lo, hi))
        ->type_name("LIST");
  }
  // A finite number in [lo, hi]; for vectors, each element.
  template <typename T>
  CLI::Option* number(const std::string& name, T& v, const std::string& help, double lo, double hi) {
    return app_.add_option("--" + name, v, help)->check(CLI::Range(lo, hi))->type_name("NUM");
  }
  template <typename T>
  CLI::Option* numbers(const std::string& name, std::vector<T>& v, const std::string& help, double lo,
                       double hi) {
    return app_.add_option("--" + name, v, help + ", comma separated")
        ->delimiter(',')
        ->check(CLI::Range(lo, hi))
        ->type_name("LIST");
  }
  CLI::Option* text(const std::string& name, std::string& v, const std::string& help,
                    const std::string& type = "TEXT") {
    return app_.add_option("--" + name, v, help)->type_name(type);
  }
  CLI::Option* names(const std::string& name, std::vector<std::string>& v, const std::string& help) {
    return app_.add_option("--" + name, v, help + ", comma separated")->delimiter(',')->type_name("LIST");
  }

  // The shared vocabulary. Each binds the caller's variable, whose value is the default shown.
  CLI::Option* data_dir(std::string& v) {
    const char* env = std::getenv("BHCL_DATA_DIR");
    v = env ? env : BHCL_DEFAULT_DATA_DIR;
    return text("data-dir", v, "folder of the file data sets (bunny, dragon, autzen); default: BHCL_DATA_DIR, then ../shared/data", "DIR");
  }
  // --data-dir, then --data (the set names, `help` listing them).
  CLI::Option* data_sets(std::string& dir, std::vector<std::string>& data, const std::string& help) {
    data_dir(dir);
    return names("data", data, help);
  }
  CLI::Option* device(std::string& v) {
    return text("device", v, "OpenCL device: P:D, cpu, gpu or a name fragment (default: BHCL_DEVICE, then PoCL)", "SPEC");
  }
  CLI::Option* queries(std::size_t& v) { return integer("queries", v, "queries per data set", 1, 1e9); }
  CLI::Option* ks(std::vector<int>& v) { return integers("k", v, "neighbours per query", 1, kMaxK); }
  CLI::Option* As(std::vector<float>& v) {
    return numbers("A", v, "blockhash: examine at most A*k points per query", 1e-3, 1e6);
  }
  CLI::Option* presets(std::vector<std::string>& v) {
    return names("presets", v, "blockhash presets (auto, paper, paper-cells)")->check(CLI::IsMember({"auto", "paper", "paper-cells"}));
  }
  // The query side of a sweep of block hashing's budget (knn_bench, blockhash_accuracy): --queries,
  // --k, --A and --presets.
  void budget_sweep(std::size_t& queries, std::vector<int>& ks, std::vector<float>& As, std::vector<std::string>& preset_list) {
    this->queries(queries);
    this->ks(ks);
    this->As(As);
    presets(preset_list);
  }
  CLI::Option* reps(int& v) { return integer("reps", v, "timed repetitions (the median is reported)", 1, 1000); }
  CLI::Option* csv(std::string& v) { return text("csv", v, "write the rows here as CSV", "FILE"); }
  CLI::Option* methods(std::vector<std::string>& v) {
    return names("methods", v, "the methods to run (default: every method)")->check(CLI::IsMember(method_names()));
  }
  CLI::Option* seed(unsigned long long& v) { return integer("seed", v, "blockhash: seed of the threshold jitter", 0, 9.0e18); }

  // Parses; on --help prints the help and exits 0, on a mistake prints one line and exits 2.
  void parse(int argc, char** argv) {
    try {
      app_.parse(argc, argv);
    } catch (const CLI::CallForHelp&) {
      std::fputs(app_.help().c_str(), stdout);
      std::exit(0);
    } catch (const CLI::ParseError& e) {
      fail(e.what());
    }
  }
  // --csv's file, opened for writing with its header line; null when `path` is empty, a mistake
  // (fail) when it cannot be written.
  std::FILE* csv_file(const std::string& path, const char* header) const {
    if (path.empty()) return nullptr;
    std::FILE* out = std::fopen(path.c_str(), "w");
    if (!out) fail("--csv: cannot write " + path);
    std::fputs(header, out);
    return out;
  }
  // A mistake found after parsing (e.g. an unknown data set): one line, exit status 2.
  [[noreturn]] void fail(const std::string& why) const {
    std::fprintf(stderr, "%s: %s (see %s --help)\n", program_.c_str(), why.c_str(), program_.c_str());
    std::exit(2);
  }

 private:
  static std::string range(double lo, double hi) {
    auto s = [](double x) { return x >= 9e18 ? std::string("max") : std::to_string(static_cast<long long>(x)); };
    return " (" + s(lo) + " to " + s(hi) + ")";
  }
  // Rewrites "1e6" as "1000000" after checking it is a whole number in [lo, hi].
  static CLI::Validator whole(double lo, double hi) {
    return CLI::Validator(
        [lo, hi](std::string& s) -> std::string {
          char* end = nullptr;
          const double x = std::strtod(s.c_str(), &end);
          if (s.empty() || *end || !std::isfinite(x) || x != std::floor(x))
            return "'" + s + "' is not a whole number";
          if (x < lo || x > hi) return "'" + s + "' is outside" + range(lo, hi);
          s = std::to_string(static_cast<long long>(x));
          return {};
        },
        "");
  }

  CLI::App app_;
  std::string program_;
};

}  // namespace bhcl::bench
