// kernel_dump: builds every OpenCL program the library uses, at the options it passes, so that
// BHCL_DUMP_PROGRAMS=dir (lib/src/core/runtime.cpp) writes each one's source and options to dir.
// Every method of the registry (each choice of a "preset" option), each compiled k variant
// (kKmaxVariants: k <= 8, 16, 32, 64, 128, 256) for kNN, and the radius kernel, plus scale.cl; a
// method added to the registry, or a preset added to its choices, is covered without a change here.
// bench/gpu_kernel_table.sh runs it (with BHCL_QUIRKS_AS=nvidia, so the defines are a GPU's) and
// compiles the dump for sm_90.
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "blockhash_cl/blockhash_cl.hpp"
#include "blockhash_cl/datasets.hpp"
#include "bench_cli.hpp"

using namespace bhcl;

int main(int argc, char** argv) {
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
#endif
  std::size_t N = 1000000;
  std::string data = "cornell", device;
  std::vector<std::string> only;
  bench::BenchCli cli("kernel_dump",
                      "Build every method's OpenCL kernels (every k variant, kNN and radius); with "
                      "BHCL_DUMP_PROGRAMS=dir each program's source and options are written to dir");
  cli.integer("N", N, "points of the set the indexes are built on (the defines follow the data: "
              "kd-tree stack depth, paper's L)", 1, 2147483646.0);
  cli.text("data", data, "generated set: uniform, clustered, duplicates, cornell", "NAME")
      ->check(CLI::IsMember({"uniform", "clustered", "duplicates", "cornell"}));
  cli.methods(only);
  cli.device(device);
  cli.parse(argc, argv);
  if (!std::getenv("BHCL_DUMP_PROGRAMS"))
    std::fprintf(stderr, "kernel_dump: BHCL_DUMP_PROGRAMS is not set: building only, nothing written\n");
  try {
    auto rt = std::make_shared<Runtime>(device);
    std::vector<float> pts = datasets::by_name(data, N, 1);
    std::vector<float> qs = datasets::queries_by_name(data, 64, 2);
    int programs = 0;
    for (const MethodInfo& m : methods()) {
      if (!m.on_device) continue;
      if (!only.empty() && std::find(only.begin(), only.end(), m.name) == only.end()) continue;
      std::vector<std::string> presets = {""};
      for (const OptionInfo* o : m.build_options())
        if (o->name == "preset" && o->kind == OptionInfo::Kind::Choice) presets = o->choices;
      for (const std::string& preset : presets) {
        MethodOptions mo;
        if (!preset.empty()) mo.set("preset", preset);
        std::fprintf(stderr, "kernel_dump: %s%s%s: building on %zu %s points\n", m.name.c_str(),
                     preset.empty() ? "" : " ", preset.c_str(), N, data.c_str());
        auto index = m.make(rt, pts.data(), N, mo);
        for (int kv : kKmaxVariants) {
          SearchParams p;
          p.k = kv;
          index->warm_up(p);
          ++programs;
        }
        RadiusParams rp;
        RadiusResult rr;
        index->radius_search(qs.data(), qs.size() / 3, 1e-3f, rp, rr);
        ++programs;
      }
    }
    // The coordinate-scaling kernels that buffer-level queries run at extreme scales
    // (Index::enqueue_query), built with no extra options there.
    rt->program("scale.cl");
    ++programs;
    std::fprintf(stderr, "kernel_dump: %d kernel variants built (%.1f s of program builds)\n",
                 programs, rt->build_seconds());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "kernel_dump: %s\n", e.what());
    return 1;
  }
  return 0;
}
