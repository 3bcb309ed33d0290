// The method tables (blockhash_cl/options.hpp) against the library and the bhcl tool: every
// option of every method's table accepted at its bounds and refused outside them.
#include "test_util.hpp"

#include <cmath>
#include <limits>
#include <sstream>

#include "blockhash_cl/options.hpp"

using namespace bhcl;

namespace {

// The values just inside and just outside an option's range, as text.
struct Bounds {
  std::vector<std::string> inside, outside;
};

std::string num(double x) {
  std::ostringstream os;
  os.precision(17);
  os << x;
  return os.str();
}

Bounds bounds_of(const OptionInfo& o) {
  Bounds b;
  if (o.kind == OptionInfo::Kind::Integer) {
    b.inside = {std::to_string(o.lo), std::to_string(o.hi)};
    if (o.lo != std::numeric_limits<long long>::min() && !(o.has_unset && o.lo - 1 == o.unset))
      b.outside.push_back(std::to_string(o.lo - 1));
    if (o.hi != std::numeric_limits<long long>::max()) b.outside.push_back(std::to_string(o.hi + 1));
    if (o.has_unset) b.inside.push_back(std::to_string(o.unset));
  } else if (o.kind == OptionInfo::Kind::Number) {
    // Relative steps of 1e-6 (not nextafter: a subnormal neighbour of 0 does not parse back).
    auto step = [](double x) { return 1e-6 * std::max(1.0, std::abs(x)); };
    const double below = o.xlo - step(o.xlo);
    b.inside = {num(o.lo_open ? o.xlo + step(o.xlo) : o.xlo), num(o.xhi)};
    b.outside.push_back(num(o.lo_open ? o.xlo : below));
    if (o.has_unset && double(o.unset) == std::stod(b.outside.back())) b.outside.pop_back();
    // A range reaching +inf (block hashing's exact A) has nothing above it.
    if (!std::isinf(o.xhi))
      b.outside.push_back(o.xhi == std::numeric_limits<double>::max() ? "inf" : num(o.xhi + step(o.xhi)));
    if (o.has_unset) b.inside.push_back(std::to_string(o.unset));
  } else if (o.kind == OptionInfo::Kind::Choice) {
    b.inside = o.choices;
    b.outside = {"no-such-" + o.name};
  }
  return b;
}

}  // namespace

TEST_CASE("option tables: every entry is complete and its default is accepted") {
  for (const MethodInfo& m : methods()) {
    CHECK(bool(m.make));
    for (const OptionInfo& o : m.options) {
      INFO(m.name << " " << o.name);
      CHECK(!o.name.empty());
      CHECK(!o.help.empty());
      CHECK(o.scope != 0);
      if (o.scope & OptionInfo::Search) CHECK(bool(o.set_search));
      if (o.scope & OptionInfo::Radius) CHECK(bool(o.set_radius));
      if (o.kind != OptionInfo::Kind::File) {
        CHECK(!o.def.empty());
        CHECK_NOTHROW(o.parse(o.def));
      }
      if (o.set) CHECK(!o.field.empty());
    }
  }
}

TEST_CASE("option tables: the parser accepts every bound and refuses beyond it") {
  for (const MethodInfo& m : methods())
    for (const OptionInfo& o : m.options) {
      const Bounds b = bounds_of(o);
      for (const std::string& v : b.inside) {
        INFO(m.name << " " << o.name << " = " << v);
        CHECK_NOTHROW(o.parse(v));
      }
      for (const std::string& v : b.outside) {
        INFO(m.name << " " << o.name << " = " << v);
        CHECK_THROWS_WITH_AS(o.parse(v), doctest::Contains((o.name + " must be").c_str()), Error);
      }
    }
}

TEST_CASE("option tables: the library builds at every bound of a build option and refuses beyond it") {
  const std::vector<float> pts = datasets::uniform(600, 3);
  for (const MethodInfo& m : methods())
    for (const OptionInfo* o : m.build_options()) {
      if (!o->set) continue;  // read by the maker (load-index, save-index)
      const Bounds b = bounds_of(*o);
      for (const std::string& v : b.inside) {
        INFO(m.name << " " << o->name << " = " << v);
        MethodOptions mo;
        mo.set(o->name, v);
        std::istringstream needs(o->needs);  // the options this one needs, from the table
        for (std::string w; needs >> w;) mo.set(w.substr(0, w.find('=')), w.substr(w.find('=') + 1));
        CHECK_NOTHROW(make_index(m.name, test::runtime(), pts.data(), 600, mo));
      }
      for (const std::string& v : b.outside) {
        INFO(m.name << " " << o->name << " = " << v);
        MethodOptions mo;
        mo.set(o->name, v);
        std::istringstream needs(o->needs);
        for (std::string w; needs >> w;) mo.set(w.substr(0, w.find('=')), w.substr(w.find('=') + 1));
        CHECK_THROWS_WITH_AS(make_index(m.name, test::runtime(), pts.data(), 600, mo),
                             doctest::Contains((o->name + " must be").c_str()), Error);
      }
    }
}

TEST_CASE("option tables: block hashing's own range checks agree with its table") {
  // The struct set directly (no table parse): the library's checks refuse what the table refuses.
  const std::vector<float> pts = datasets::uniform(600, 4);
  for (const OptionInfo* o : method_info("blockhash").build_options()) {
    if (!o->set || o->kind == OptionInfo::Kind::Choice) continue;
    for (const std::string& v : bounds_of(*o).outside) {
      if (v == "inf") continue;  // not representable as a parsed value
      INFO(o->name << " = " << v);
      OptionValue val;
      val.text = v;
      val.number = std::stod(v);
      val.integer = static_cast<long long>(val.number);
      BlockHashBuildParams p;
      o->set(&p, val);
      OptionValue back;
      o->get(&p, back);
      if (back.integer != val.integer || back.number != val.number) continue;  // the field cannot hold it
      CHECK_THROWS_AS(BlockHashIndex::build(test::runtime(), pts.data(), 600, p), Error);
    }
  }
}

TEST_CASE("option tables: block hashing answers at every bound of a search option") {
  // On the grid and on auto's L tables; the L tables' probes on the grid are refused, not ignored.
  const std::vector<float> pts = datasets::uniform(600, 5), qs = datasets::uniform(20, 6);
  for (const char* layout : {"-1", "0"}) {
    CAPTURE(layout);
    auto index = make_index("blockhash", test::runtime(), pts.data(), 600, MethodOptions().set("grid", layout));
    const bool grid = std::string(layout) == "-1";
    for (const OptionInfo* o : method_info("blockhash").search_options()) {
      if (o->name == "local-size" || o->name == "max-batch") continue;  // bounded by the device
      for (const std::string& v : bounds_of(*o).inside) {
        if (o->name == "recall" && v != "0") continue;  // a tuning run per target: covered elsewhere
        INFO(o->name << " = " << v);
        SearchParams p = test::knn_params(8);
        o->set_search(&p, o->parse(v));
        if (grid && o->name == "probes" && v != "-1")
          CHECK_THROWS_WITH_AS(index->query(qs, p), doctest::Contains("an option of the L tables"), Error);
        else if (!grid && o->name == "A" && v == "inf")  // the grid's exact mode: the L tables are never exact
          CHECK_THROWS_WITH_AS(index->query(qs, p), doctest::Contains("A must be a positive finite number"), Error);
        else
          CHECK_NOTHROW(index->query(qs, p));
      }
    }
    for (const OptionInfo* o : method_info("blockhash").radius_options()) {
      if (o->name == "local-size" || o->name == "max-batch") continue;
      for (const std::string& v : bounds_of(*o).inside) {
        INFO(o->name << " = " << v);
        RadiusParams p;
        o->set_radius(&p, o->parse(v));
        RadiusResult r;
        if (grid && o->name == "probes" && v != "-1")
          CHECK_THROWS_WITH_AS(index->radius_search(qs.data(), 20, 0.1f, p, r), doctest::Contains("an option of the L tables"),
                               Error);
        else
          CHECK_NOTHROW(index->radius_search(qs.data(), 20, 0.1f, p, r));
      }
    }
  }
}

TEST_CASE("option tables: bhcl refuses every option beyond its bounds, naming it") {
  const std::string P = test::write_points("opt_p.f32", datasets::uniform(300, 7));
  const std::string base = "knn --points " + P + " --queries " + P + " --out-ids " + test::tmp_path("opt_i.i32") +
                           " --out-dist2 " + test::tmp_path("opt_d.f32") + " --quiet";
  for (const MethodInfo& m : methods())
    for (const OptionInfo& o : m.options) {
      const bool radius_only = !(o.scope & (OptionInfo::Build | OptionInfo::Search));
      const std::string extra = radius_only ? " --radius 0.1 --out-offsets " + test::tmp_path("opt_o.i64") : "";
      for (const std::string& v : bounds_of(o).outside) {
        INFO(m.name << " --" << o.name << " " << v);
        std::string out;
        CHECK(test::run_bhcl(base + extra + " --method " + m.name + " --" + o.name + " " + v, &out) == 2);
        CHECK(out.find("--" + o.name + " must be") != std::string::npos);
      }
    }
}

TEST_CASE("option tables: bhcl accepts block hashing's build options at their bounds") {
  const std::string P = test::write_points("optb_p.f32", datasets::uniform(300, 8));
  const std::string base = "knn --points " + P + " --queries " + P + " --out-ids " + test::tmp_path("optb_i.i32") +
                           " --out-dist2 " + test::tmp_path("optb_d.f32") + " --quiet --k 4 --method blockhash";
  for (const OptionInfo* o : method_info("blockhash").build_options()) {
    if (!o->set) continue;
    for (const std::string& v : bounds_of(*o).inside) {
      INFO("--" << o->name << " " << v);
      std::string out;
      std::string layout;
      std::istringstream needs(o->needs);  // the options this one needs, from the table
      for (std::string w; needs >> w;) layout += " --" + w.substr(0, w.find('=')) + " " + w.substr(w.find('=') + 1);
      CHECK_MESSAGE(test::run_bhcl(base + layout + " --" + o->name + " " + v, &out) == 0, out);
    }
  }
}

TEST_CASE("option tables: block hashing's retired layout option is refused with what replaced it") {
  // The option of the retired layout of blocks aligned to cells: an error naming the option, the
  // measurement that retired it and the layouts to use, never skipped as another method's option.
  const std::vector<float> pts = datasets::uniform(300, 9);
  for (const char* v : {"1", "0"}) {
    INFO("cell-aligned = " << v);
    CHECK_THROWS_WITH_AS(make_index("blockhash", test::runtime(), pts.data(), 300, MethodOptions().set("cell-aligned", v)),
                         doctest::Contains("the cell-aligned block layout was retired"), Error);
  }
}
