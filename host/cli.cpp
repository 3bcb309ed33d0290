#include "cli.hpp"

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <fstream>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"

namespace bhcl::cli {

Args::Args(int argc, char** argv, int first, const std::set<std::string>& flags) {
  for (int i = first; i < argc; ++i) {
    std::string a = argv[i];
    if (a.rfind("--", 0) != 0 || a.size() < 3) throw UsageError("unexpected argument '" + a + "'");
    std::string key = a.substr(2);
    std::string value;
    size_t eq = key.find('=');
    if (eq != std::string::npos) {
      value = key.substr(eq + 1);
      key = key.substr(0, eq);
    } else if (!flags.count(key)) {
      if (i + 1 >= argc) throw UsageError("option --" + key + " needs a value");
      value = argv[++i];
    }
    values_[key] = value;
  }
}

std::string Args::str(const std::string& key) const {
  auto it = values_.find(key);
  if (it == values_.end()) throw UsageError("missing required option --" + key);
  return it->second;
}

std::string Args::str(const std::string& key, const std::string& fallback) const {
  auto it = values_.find(key);
  return it == values_.end() ? fallback : it->second;
}

long long Args::integer(const std::string& key) const {
  std::string v = str(key);
  size_t pos = 0;
  long long x = 0;
  try {
    x = std::stoll(v, &pos);
  } catch (...) {
    pos = 0;
  }
  if (pos == 0 || pos != v.size()) throw UsageError("--" + key + " expects an integer, got '" + v + "'");
  return x;
}

long long Args::integer(const std::string& key, long long fallback) const {
  return has(key) ? integer(key) : fallback;
}

double Args::number(const std::string& key, double fallback) const {
  if (!has(key)) return fallback;
  std::string v = str(key);
  size_t pos = 0;
  double x = 0;
  try {
    x = std::stod(v, &pos);
  } catch (...) {
    pos = 0;
  }
  if (pos == 0 || pos != v.size()) throw UsageError("--" + key + " expects a number, got '" + v + "'");
  return x;
}

void Args::allow_only(const std::set<std::string>& known) const {
  for (const auto& kv : values_)
    if (!known.count(kv.first)) throw UsageError("unknown option --" + kv.first);
}

std::string json_escape(const std::string& s) {
  std::string o = "\"";
  for (char c : s) {
    switch (c) {
      case '"': o += "\\\""; break;
      case '\\': o += "\\\\"; break;
      case '\n': o += "\\n"; break;
      case '\t': o += "\\t"; break;
      default:
        if (static_cast<unsigned char>(c) < 0x20) {
          char b[8];
          std::snprintf(b, sizeof b, "\\u%04x", c);
          o += b;
        } else {
          o += c;
        }
    }
  }
  return o + "\"";
}

Json& Json::add(const std::string& key, const std::string& value) {
  items_.emplace_back(key, json_escape(value));
  return *this;
}
Json& Json::add(const std::string& key, double value) {
  char b[64];
  if (std::isfinite(value)) std::snprintf(b, sizeof b, "%.9g", value);
  else std::snprintf(b, sizeof b, "null");
  items_.emplace_back(key, b);
  return *this;
}
Json& Json::add(const std::string& key, long long value) {
  items_.emplace_back(key, std::to_string(value));
  return *this;
}
Json& Json::add(const std::string& key, bool value) {
  items_.emplace_back(key, value ? "true" : "false");
  return *this;
}
Json& Json::add_raw(const std::string& key, const std::string& json) {
  items_.emplace_back(key, json);
  return *this;
}

std::string Json::str() const {
  std::string o = "{";
  for (size_t i = 0; i < items_.size(); ++i)
    o += (i ? ",\n  " : "\n  ") + json_escape(items_[i].first) + ": " + items_[i].second;
  return o + "\n}\n";
}

void Json::write(const std::string& path) const {
  std::ofstream out(path);
  if (!out) throw bhcl::Error(path + ": cannot open the stats file for writing");
  out << str();
  if (!out) throw bhcl::Error(path + ": write failed");
}

const std::set<std::string> kIndexOptions = {
    "k", "max-radius", "A", "probes", "local-size", "max-batch", "preset", "L", "P", "B", "X",
    "threads", "seed", "load-index", "save-index"};

void read_points_and_queries(const Args& args, std::vector<float>& points, std::vector<float>& queries) {
  points = read_points_file(args.str("points"));
  if (points.empty()) throw Error(args.str("points") + ": the point file is empty (0 points)");
  queries = read_points_file(args.str("queries"));
  if (queries.empty()) throw Error(args.str("queries") + ": the query file is empty (0 queries)");
}

std::set<std::string> merge(std::set<std::string> a, const std::set<std::string>& b) {
  a.insert(b.begin(), b.end());
  return a;
}

MethodOptions method_options(const Args& args) {
  MethodOptions m;
  m.preset = args.str("preset", "");
  if (!m.preset.empty() && m.preset != "auto" && m.preset != "paper")
    throw UsageError("--preset must be auto or paper, got '" + m.preset + "'");
  m.L = static_cast<int>(args.integer("L", -1));
  m.P = static_cast<int>(args.integer("P", -1));
  m.B = static_cast<int>(args.integer("B", -1));
  m.X = static_cast<int>(args.integer("X", -1));
  m.threads = static_cast<int>(args.integer("threads", 0));
  if (m.threads < 0) throw UsageError("--threads must be >= 0");
  m.seed = static_cast<std::uint64_t>(args.integer("seed", 1));
  m.load_index = args.str("load-index", "");
  m.save_index = args.str("save-index", "");
  return m;
}

SearchParams search_params(const Args& args, int default_k) {
  SearchParams p;
  long long k = args.integer("k", default_k);
  if (k < 1 || k > kMaxK)
    throw UsageError("--k must be in [1, " + std::to_string(kMaxK) + "], got " + std::to_string(k));
  p.k = static_cast<int>(k);
  p.max_radius = static_cast<float>(args.number("max-radius", INFINITY));
  if (std::isnan(p.max_radius) || p.max_radius < 0)
    throw UsageError("--max-radius must be a non-negative number");
  p.A = static_cast<float>(args.number("A", p.A));
  if (!(p.A > 0) || !std::isfinite(p.A)) throw UsageError("--A must be a positive number");
  p.neighbour_probes = static_cast<int>(args.integer("probes", -1));
  long long ls = args.integer("local-size", 0);
  if (ls < 0) throw UsageError("--local-size must be >= 0");
  p.local_size = static_cast<std::size_t>(ls);
  long long mb = args.integer("max-batch", 0);
  if (mb < 0) throw UsageError("--max-batch must be >= 0");
  p.max_batch = static_cast<std::size_t>(mb);
  return p;
}

}  // namespace bhcl::cli
