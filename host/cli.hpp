// Argument parsing and JSON output for the bhcl tool.
#pragma once

#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/knn.hpp"

namespace bhcl::cli {

// A command-line mistake: bhcl prints it as one line and exits with status 2.
struct UsageError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// "--key value" options and "--flag" switches after the sub-command.
class Args {
 public:
  // flags: options that take no value.
  Args(int argc, char** argv, int first, const std::set<std::string>& flags = {});

  bool has(const std::string& key) const { return values_.count(key) != 0; }
  std::string str(const std::string& key) const;  // required
  std::string str(const std::string& key, const std::string& fallback) const;
  long long integer(const std::string& key, long long fallback) const;
  long long integer(const std::string& key) const;  // required
  double number(const std::string& key, double fallback) const;
  bool flag(const std::string& key) const { return has(key); }
  // Throws UsageError naming any option not in `known`.
  void allow_only(const std::set<std::string>& known) const;

 private:
  std::map<std::string, std::string> values_;
};

// A flat JSON object written in insertion order.
class Json {
 public:
  Json& add(const std::string& key, const std::string& value);
  Json& add(const std::string& key, const char* value) { return add(key, std::string(value)); }
  Json& add(const std::string& key, double value);
  Json& add(const std::string& key, long long value);
  Json& add(const std::string& key, std::size_t value) { return add(key, static_cast<long long>(value)); }
  Json& add(const std::string& key, int value) { return add(key, static_cast<long long>(value)); }
  Json& add(const std::string& key, bool value);
  Json& add_raw(const std::string& key, const std::string& json);
  std::string str() const;
  void write(const std::string& path) const;

 private:
  std::vector<std::pair<std::string, std::string>> items_;
};

std::string json_escape(const std::string& s);

// Options shared by every command that builds and queries an index (knn, eval, bench, render):
// --k --max-radius --A --probes --local-size --max-batch and the build options
// --preset --L --P --B --X --threads --seed --load-index --save-index.
extern const std::set<std::string> kIndexOptions;
MethodOptions method_options(const Args& args);
SearchParams search_params(const Args& args, int default_k = 10);
// Reads --points and --queries (raw float32 x y z files); an empty file is an error naming it.
void read_points_and_queries(const Args& args, std::vector<float>& points, std::vector<float>& queries);

// Merges option sets for allow_only.
std::set<std::string> merge(std::set<std::string> a, const std::set<std::string>& b);

}  // namespace bhcl::cli
