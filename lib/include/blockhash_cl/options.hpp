// Options as each method describes them, once: one table per method (lib/src/<method>/options.cpp)
// of its build, search and radius options -- name, kind, range, default, help and the field it
// sets. The library's range checks, the bhcl tool, the Python module, the benchmarks and the tests
// all read these tables (registry.hpp lists them per method), so that a knob added to a table
// reaches every front end with no other edit.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <map>
#include <string>
#include <type_traits>
#include <vector>

namespace bhcl {

struct SearchParams;
struct RadiusParams;

// One value of an option: the text given, and its number for Integer and Number options.
struct OptionValue {
  std::string text;
  long long integer = 0;
  double number = 0;
};

struct OptionInfo {
  enum class Kind { Integer, Number, Choice, File };
  // Where an option applies (a bit set): the build, kNN search, radius search.
  enum Scope : unsigned { Build = 1, Search = 2, Radius = 4 };

  std::string name;     // as the command line spells it, without "--": "L", "leaf-size", "probes"
  std::string keyword;  // the Python keyword ("" = name with '-' as '_'); keyword() resolves it
  std::string help;     // its meaning, without the method names or the range (front ends add them)
  std::string def;      // the default as shown ("-1" where -1 means "derive")
  Kind kind = Kind::Integer;
  unsigned scope = Build;
  std::string field;    // the field it sets, e.g. "BlockHashBuildParams::L" ("" = read by the maker)
  long long lo = 0, hi = 0;  // Integer: the accepted range
  double xlo = 0, xhi = 0;   // Number: the accepted range, [xlo, xhi] or (xlo, xhi] when lo_open
  bool lo_open = false;
  // Integer and Number: one more value outside the range, meaning "the method decides" (-1).
  bool has_unset = false;
  long long unset = -1;
  std::vector<std::string> choices;  // Choice: the accepted values
  // Other options a build with this one set must set too, as "NAME=VALUE" words (e.g. "grid=0":
  // block hashing's block-layout options, which the grid refuses); "" = none.
  std::string needs;

  // Build options: read and write the method's build-parameter struct (type-erased; the table
  // that holds the entry knows the struct). nullptr: the method's maker reads the value itself.
  void (*get)(const void* params, OptionValue& v) = nullptr;
  void (*set)(void* params, const OptionValue& v) = nullptr;
  // Search options: write SearchParams (Search) and RadiusParams (Radius).
  void (*set_search)(void* params, const OptionValue& v) = nullptr;
  void (*set_radius)(void* params, const OptionValue& v) = nullptr;

  std::string keyword_name() const;
  // "[1, 64] or -1", "(0, 1]", "auto or paper": the accepted values, as messages and help show them.
  std::string range_text() const;
  bool in_range(const OptionValue& v) const;
  // Parses text against the kind and range; throws bhcl::Error "NAME must be ..., got TEXT"
  // (NAME as `shown`, e.g. "--L"; empty: the option's name).
  OptionValue parse(const std::string& text, const std::string& shown = "") const;
  OptionInfo& or_unset(long long v = -1) { has_unset = true; unset = v; return *this; }
  OptionInfo& with_keyword(std::string k) { keyword = std::move(k); return *this; }
  OptionInfo& needing(std::string n) { needs = std::move(n); return *this; }
};

// The build options given for a method, by table name, as text; make_index parses and
// range-checks them against the method's table (front ends refuse an option no chosen method reads).
struct MethodOptions {
  std::map<std::string, std::string> values;
  MethodOptions& set(const std::string& name, const std::string& text) {
    values[name] = text;
    return *this;
  }
  bool has(const std::string& name) const { return values.count(name) != 0; }
  std::string text(const std::string& name, const std::string& fallback = "") const;
  long long integer(const std::string& name, long long fallback) const;  // throws Error if not one
  std::string load_index() const { return text("load-index"); }
  std::string save_index() const { return text("save-index"); }
};

// Options of `table` in `scope`.
std::vector<const OptionInfo*> options_in(const std::vector<OptionInfo>& table, unsigned scope);
// Writes every given build option of `table` into params (the method's build struct), each parsed
// and range-checked by its entry (throws Error naming it). Names the table does not hold are
// left alone: one MethodOptions may serve several methods (eval's truth, the renderer's pair).
void apply_build_options(const std::vector<OptionInfo>& table, const MethodOptions& given,
                         void* params, const std::string& method);
// The library's range checks of a build struct: every field a table entry sets, against its range.
void check_build_fields(const std::vector<OptionInfo>& table, const void* params,
                        const std::string& method);
// The search options every device method reads (local-size, max-batch).
std::vector<OptionInfo> device_search_options();

// Helpers for the tables.
namespace option {

template <class T> struct member;
template <class C, class F> struct member<F C::*> {
  using owner = C;
  using type = F;
};

template <auto M> void get(const void* p, OptionValue& v) {
  using Mb = member<decltype(M)>;
  const auto& f = static_cast<const typename Mb::owner*>(p)->*M;
  if constexpr (std::is_floating_point_v<typename Mb::type>) {
    v.number = static_cast<double>(f);
    v.integer = static_cast<long long>(f);
  } else {
    v.integer = static_cast<long long>(f);
    v.number = static_cast<double>(f);
  }
}
template <auto M> void set(void* p, const OptionValue& v) {
  using Mb = member<decltype(M)>;
  auto& f = static_cast<typename Mb::owner*>(p)->*M;
  if constexpr (std::is_floating_point_v<typename Mb::type>)
    f = static_cast<typename Mb::type>(v.number);
  else if constexpr (std::is_same_v<typename Mb::type, std::string>)
    f = v.text;
  else
    f = static_cast<typename Mb::type>(v.integer);
}

OptionInfo integer(std::string name, std::string help, long long lo, long long hi, std::string def);
OptionInfo number(std::string name, std::string help, double lo, double hi, std::string def,
                  bool lo_open = false);
OptionInfo choice(std::string name, std::string help, std::vector<std::string> choices, std::string def);
OptionInfo file(std::string name, std::string help);

// A build option that sets field M of the method's build struct.
template <auto M> OptionInfo build(OptionInfo o, std::string field) {
  o.scope = OptionInfo::Build;
  o.field = std::move(field);
  o.get = &get<M>;
  o.set = &set<M>;
  return o;
}
// A search option (kNN: field MS of SearchParams; radius: field MR of RadiusParams; either may be
// nullptr for an option of one search only).
template <auto MS, auto MR> OptionInfo search(OptionInfo o, std::string field) {
  o.scope = 0;
  o.field = std::move(field);
  if constexpr (MS != nullptr) {
    o.scope |= OptionInfo::Search;
    o.set_search = &set<MS>;
  }
  if constexpr (MR != nullptr) {
    o.scope |= OptionInfo::Radius;
    o.set_radius = &set<MR>;
  }
  return o;
}

}  // namespace option

// A build option naming the field it sets: BHCL_BUILD_OPTION(BlockHashBuildParams, L, option::integer(...)).
#define BHCL_BUILD_OPTION(Struct, Field, info) \
  ::bhcl::option::build<&Struct::Field>(info, #Struct "::" #Field)

}  // namespace bhcl
