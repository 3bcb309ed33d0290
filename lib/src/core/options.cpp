// Option tables (blockhash_cl/options.hpp): parsing and range checks that every front end shares.
#include "blockhash_cl/options.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <sstream>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/knn.hpp"
#include "blockhash_cl/numbers.hpp"

namespace bhcl {
namespace {

std::string num_text(double x) {
  if (x == std::numeric_limits<double>::max() || x == double(std::numeric_limits<float>::max())) return "inf";
  std::ostringstream os;
  os << x;
  return os.str();
}

std::string joined(const std::vector<std::string>& v, const std::string& sep, const std::string& last) {
  std::string s;
  for (std::size_t i = 0; i < v.size(); ++i) s += (i == 0 ? "" : i + 1 == v.size() ? last : sep) + v[i];
  return s;
}

}  // namespace

std::string OptionInfo::keyword_name() const {
  if (!keyword.empty()) return keyword;
  std::string k = name;
  std::replace(k.begin(), k.end(), '-', '_');
  return k;
}

std::string OptionInfo::range_text() const {
  std::string r;
  switch (kind) {
    case Kind::Integer:
      r = hi == std::numeric_limits<long long>::max() ? ">= " + std::to_string(lo)
                                                     : "in [" + std::to_string(lo) + ", " + std::to_string(hi) + "]";
      break;
    case Kind::Number:
      r = std::string("in ") + (lo_open ? "(" : "[") + num_text(xlo) + ", " + num_text(xhi) +
          (xhi == std::numeric_limits<double>::max() || xhi == double(std::numeric_limits<float>::max()) ? ")" : "]");
      break;
    case Kind::Choice:
      return joined(choices, ", ", " or ");
    case Kind::File:
      return "a file";
  }
  if (has_unset) r += " (or " + std::to_string(unset) + ")";
  return r;
}

bool OptionInfo::in_range(const OptionValue& v) const {
  switch (kind) {
    case Kind::Integer:
      return (v.integer >= lo && v.integer <= hi) || (has_unset && v.integer == unset);
    case Kind::Number:
      if (has_unset && v.number == double(unset)) return true;
      // +inf only where the range reaches it (xhi = +inf: e.g. block hashing's exact A).
      return !std::isnan(v.number) && (lo_open ? v.number > xlo : v.number >= xlo) && v.number <= xhi;
    case Kind::Choice:
      return std::find(choices.begin(), choices.end(), v.text) != choices.end();
    case Kind::File:
      return true;
  }
  return false;
}

OptionValue OptionInfo::parse(const std::string& text, const std::string& shown) const {
  const std::string who = shown.empty() ? name : shown;
  OptionValue v;
  v.text = text;
  auto refuse = [&] { return Error(who + " must be " + range_text() + ", got " + text); };
  if (kind == Kind::Integer) {
    // Locale-free (numbers.hpp): the text of a Python int or a command line, whatever setlocale said.
    const detail::NumberParse r = detail::parse_integer(text, v.integer);
    if (r == detail::NumberParse::OutOfRange) throw refuse();
    if (r != detail::NumberParse::Ok) throw Error(who + " expects an integer, got '" + text + "'");
    v.number = double(v.integer);
  } else if (kind == Kind::Number) {
    if (detail::parse_double(text, v.number) == detail::NumberParse::NotNumber)
      throw Error(who + " expects a number, got '" + text + "'");
    v.integer = static_cast<long long>(std::isfinite(v.number) ? v.number : 0);
  } else if (kind == Kind::Choice && !in_range(v)) {
    throw Error(who + " must be " + range_text() + ", got '" + text + "'");
  }
  if (!in_range(v)) throw refuse();
  return v;
}

std::string MethodOptions::text(const std::string& name, const std::string& fallback) const {
  auto it = values.find(name);
  return it == values.end() ? fallback : it->second;
}

long long MethodOptions::integer(const std::string& name, long long fallback) const {
  auto it = values.find(name);
  if (it == values.end()) return fallback;
  std::size_t pos = 0;
  long long x = 0;
  try {
    x = std::stoll(it->second, &pos);
  } catch (...) {
    pos = 0;
  }
  if (pos == 0 || pos != it->second.size())
    throw Error(name + " expects an integer, got '" + it->second + "'");
  return x;
}

std::vector<const OptionInfo*> options_in(const std::vector<OptionInfo>& table, unsigned scope) {
  std::vector<const OptionInfo*> out;
  for (const OptionInfo& o : table)
    if (o.scope & scope) out.push_back(&o);
  return out;
}

void apply_build_options(const std::vector<OptionInfo>& table, const MethodOptions& given,
                         void* params, const std::string& method) {
  for (const auto& entry : given.values) {
    // Not a structured binding: C++17 lambdas cannot capture one (clang refuses it).
    const std::string& name = entry.first;
    const std::string& text = entry.second;
    auto it = std::find_if(table.begin(), table.end(),
                           [&](const OptionInfo& o) { return o.name == name && (o.scope & OptionInfo::Build); });
    if (it == table.end()) continue;  // another method's (one MethodOptions may serve several)
    const OptionValue v = it->parse(text, method + ": " + name);
    if (it->set) it->set(params, v);
  }
}

void check_build_fields(const std::vector<OptionInfo>& table, const void* params,
                        const std::string& method) {
  for (const OptionInfo& o : table) {
    if (!o.get || o.kind == OptionInfo::Kind::Choice) continue;
    OptionValue v;
    o.get(params, v);
    if (!o.in_range(v))
      throw Error(method + ": " + o.keyword_name() + " must be " + o.range_text() + ", got " +
                  (o.kind == OptionInfo::Kind::Integer ? std::to_string(v.integer) : num_text(v.number)));
  }
}

std::vector<OptionInfo> device_search_options() {
  return {
      option::search<&SearchParams::local_size, &RadiusParams::local_size>(
          option::integer("local-size", "device methods: OpenCL work-group size (0: the device default)", 0, 1 << 20, "0"),
          "SearchParams::local_size"),
      option::search<&SearchParams::max_batch, &RadiusParams::max_batch>(
          option::integer("max-batch", "device methods: at most this many queries per dispatch (0: automatic)", 0,
                          std::numeric_limits<long long>::max(), "0"),
          "SearchParams::max_batch"),
  };
}

namespace option {

namespace {
OptionInfo named(std::string name, std::string help, std::string def, OptionInfo::Kind kind) {
  OptionInfo o;
  o.name = std::move(name);
  o.help = std::move(help);
  o.def = std::move(def);
  o.kind = kind;
  return o;
}
}  // namespace

OptionInfo integer(std::string name, std::string help, long long lo, long long hi, std::string def) {
  OptionInfo o = named(std::move(name), std::move(help), std::move(def), OptionInfo::Kind::Integer);
  o.lo = lo;
  o.hi = hi;
  return o;
}

OptionInfo number(std::string name, std::string help, double lo, double hi, std::string def, bool lo_open) {
  OptionInfo o = named(std::move(name), std::move(help), std::move(def), OptionInfo::Kind::Number);
  o.xlo = lo;
  o.xhi = hi;
  o.lo_open = lo_open;
  return o;
}

OptionInfo choice(std::string name, std::string help, std::vector<std::string> choices, std::string def) {
  OptionInfo o = named(std::move(name), std::move(help), std::move(def), OptionInfo::Kind::Choice);
  o.choices = std::move(choices);
  return o;
}

OptionInfo file(std::string name, std::string help) {
  return named(std::move(name), std::move(help), "", OptionInfo::Kind::File);
}

}  // namespace option
}  // namespace bhcl
