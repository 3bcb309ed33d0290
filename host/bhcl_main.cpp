// bhcl: the blockhash_cl command-line tool. Errors are one line on stderr: exit 2 for a usage
// mistake, 1 for anything else (bad input, OpenCL failure).
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>

#include "blockhash_cl/error.hpp"
#include "cli.hpp"
#include "commands.hpp"

namespace bhcl::cli {
std::vector<Command>& commands() {
  static std::vector<Command> all;
  return all;
}
}  // namespace bhcl::cli

namespace {

void print_help() {
  auto cmds = bhcl::cli::commands();
  std::sort(cmds.begin(), cmds.end(), [](const auto& a, const auto& b) { return a.name < b.name; });
  std::printf("bhcl: batched approximate kNN on 3D points with OpenCL (blockhash_cl)\n\n");
  for (const auto& c : cmds) std::printf("  bhcl %s\n", c.usage.c_str());
  std::printf(
      "\nEnvironment: BHCL_DEVICE picks the OpenCL device (see `bhcl devices`),\n"
      "BHCL_KERNEL_DIR loads kernels/*.cl from disk instead of the embedded copies.\n");
}

}  // namespace

int main(int argc, char** argv) {
#ifdef BHCL_BUILD_TREE_POCL_CACHE
  // Run from the build tree: PoCL's kernel cache goes there too, unless the user chose one.
  setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 0);
#endif
  if (argc < 2 || !std::strcmp(argv[1], "help") || !std::strcmp(argv[1], "--help") ||
      !std::strcmp(argv[1], "-h")) {
    print_help();
    return argc < 2 ? 2 : 0;
  }
  for (const auto& c : bhcl::cli::commands()) {
    if (c.name != argv[1]) continue;
    try {
      return c.run(argc - 1, argv + 1);
    } catch (const bhcl::cli::UsageError& e) {
      std::fprintf(stderr, "bhcl %s: usage error: %s\nusage: bhcl %s\n", argv[1], e.what(),
                   c.usage.c_str());
      return 2;
    } catch (const std::exception& e) {
      std::fprintf(stderr, "bhcl %s: error: %s\n", argv[1], e.what());
      return 1;
    }
  }
  std::fprintf(stderr, "bhcl: unknown command '%s' (try `bhcl help`)\n", argv[1]);
  return 2;
}
