// The kernels' define table (lib/src/core/kernel_defines.cpp) against the kernel sources, and a
// caller's kernel_defines refused where no kernel being built reads them.
#include <doctest/doctest.h>

#include <map>
#include <regex>
#include <set>
#include <string>
#include <string_view>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#include "blockhash_cl/runtime.hpp"
#include "core/kernel_defines.hpp"
#include "test_util.hpp"

namespace bhcl::detail {
const std::map<std::string, std::string_view>& embedded_kernel_files();
}

using namespace bhcl;

namespace {

// Per kernel file (.cl), the defines its source (includes expanded) gives a default with
// `#ifndef NAME` / `#define NAME value`: name -> the value as written. Include guards (*_H) are not defines.
std::map<std::string, std::string> defaults_in(const std::string& source) {
  std::map<std::string, std::string> out;
  static const std::regex guard(R"(#ifndef\s+(BHCL_[A-Z0-9_]+)[^\n]*\n\s*#define\s+\1\s+([^\n]*))");
  for (auto it = std::sregex_iterator(source.begin(), source.end(), guard); it != std::sregex_iterator(); ++it) {
    const std::string name = (*it)[1], value = std::regex_replace(std::string((*it)[2]), std::regex(R"(\s*(/\*.*)?$)"), "");
    if (name.size() > 2 && name.compare(name.size() - 2, 2, "_H") == 0) continue;
    out.emplace(name, value);
  }
  return out;
}

}  // namespace

TEST_CASE("kernel defines: the table lists exactly the defines each kernel reads, with the source's defaults") {
  std::set<std::string> kernels;
  for (const auto& [file, text] : detail::embedded_kernel_files())
    if (file.size() > 3 && file.compare(file.size() - 3, 3, ".cl") == 0) kernels.insert(file);
  REQUIRE(kernels.size() >= 10);
  for (const std::string& file : kernels) {
    CAPTURE(file);
    const std::map<std::string, std::string> in_source = defaults_in(kernel_source(file));
    for (const auto& [name, value] : in_source) {
      CAPTURE(name);
      const detail::KernelDefine* d = detail::find_kernel_define(name);
      REQUIRE_MESSAGE(d != nullptr, "a define the table lacks");
      const detail::KernelDefine::Reader* r = nullptr;
      for (const auto& x : d->readers)
        if (file == x.kernel) r = &x;
      REQUIRE_MESSAGE(r != nullptr, "the table does not say this kernel reads it");
      CHECK(value == std::string(r->fallback));
    }
    for (const detail::KernelDefine& d : detail::kernel_define_table())
      if (d.read_by(file)) CHECK_MESSAGE(in_source.count(d.name) == 1, d.name << ": listed, but the kernel does not read it");
  }
  for (const detail::KernelDefine& d : detail::kernel_define_table()) {
    CAPTURE(d.name);
    CHECK(d.lo <= d.hi);
    for (const auto& r : d.readers) CHECK(kernels.count(r.kernel) == 1);
  }
}

TEST_CASE("kernel defines: a caller's define is refused unless the kernel being built reads it and may be set") {
  const test::PointSet set = test::exact_point_sets().front();  // uniform
  const std::vector<float>& pts = set.points;
  const std::vector<float>& qs = set.queries;
  auto grid = make_index("blockhash", test::runtime(), pts.data(), pts.size() / 3);
  auto kd = make_index("kdtree", test::runtime(), pts.data(), pts.size() / 3);
  auto bf = make_index("bruteforce", test::runtime(), pts.data(), pts.size() / 3);
  SearchParams p = test::knn_params(8);
  KnnResult out;
  auto refused = [&](const Index& ix, const std::string& defines) {
    SearchParams q = p;
    q.kernel_defines = defines;
    return test::error_of([&] { ix.query(qs.data(), qs.size() / 3, q, out); });
  };
  // A name no kernel reads (a retired one, a misspelling): refused before anything is built.
  CHECK(refused(*grid, "-DBHCL_VEC_SCAN=0").find("no kernel reads BHCL_VEC_SCAN") != std::string::npos);
  CHECK(refused(*bf, "-DBHCL_GRID_PREFETCH_HOME=1").find("no kernel reads") != std::string::npos);
  // The library's own: the host's arrays depend on them.
  CHECK(refused(*grid, "-DBHCL_KMAX=8").find("set by the library") != std::string::npos);
  CHECK(refused(*kd, "-DBHCL_KD_STACK=8").find("set by the library") != std::string::npos);
  // Out of range, or not an integer.
  CHECK(refused(*grid, "-DBHCL_GRID_VTOPK=7").find("not an integer in [0, 1]") != std::string::npos);
  CHECK(refused(*grid, "-DBHCL_GRID_ROWCAP=x").find("not an integer") != std::string::npos);
  CHECK(refused(*grid, "BHCL_GRID_VTOPK=0").find("not a -DNAME[=VALUE] define") != std::string::npos);
  // Another kernel's define: named with the kernels that do read it.
  const std::string other = refused(*kd, "-DBHCL_GRID_VTOPK=0");
  CHECK(other.find("is not read by kdtree_knn.cl") != std::string::npos);
  CHECK(other.find("blockhash_grid_knn.cl") != std::string::npos);
  {
    RadiusParams rp;
    rp.kernel_defines = "-DBHCL_GRID_VTOPK=0";  // the kNN kernel's, not the radius kernel's
    RadiusResult rr;
    const std::string e = test::error_of([&] { grid->radius_search(qs.data(), qs.size() / 3, 0.1f, rp, rr); });
    CHECK(e.find("is not read by blockhash_grid_radius.cl") != std::string::npos);
  }
  // Accepted: the grid's tuning defines change no row of its exact answer.
  KnnResult plain, scalar;
  grid->query(qs.data(), qs.size() / 3, p, plain);
  SearchParams ps = p;
  ps.kernel_defines = "-DBHCL_GRID_VTOPK=0 -DBHCL_GRID_PREFETCH=0 -DBHCL_GRID_FINE_RINGS=0xffffffff";
  grid->query(qs.data(), qs.size() / 3, ps, scalar);
  test::require_identical(scalar, plain, "tuning defines");
}

TEST_CASE("kernel defines: a caller's define replaces the library's value, one -D of each name") {
  // Two -D of one name build as the last, but clang warns of the redefinition on PoCL's stderr.
  const std::string o = detail::kernel_build_options(
      "blockhash_grid_knn.cl", {{"BHCL_GRID_PREFETCH", 2}, {"BHCL_GRID_ROWCAP", 32}}, "-DBHCL_GRID_PREFETCH=0");
  CHECK(o == "-DBHCL_GRID_ROWCAP=32 -DBHCL_GRID_PREFETCH=0");
  CHECK(detail::kernel_build_options("blockhash_grid_knn.cl", {{"BHCL_GRID_PREFETCH", 2}}, "") == "-DBHCL_GRID_PREFETCH=2");
}
