// bhcl: the blockhash_cl command-line tool. Each sub-command's options are parsed by CLI11
// (`bhcl CMD --help` lists them). Errors are one line on stderr: exit 2 for a usage mistake,
// 1 for anything else (bad input, OpenCL failure).
#include <filesystem>
#include <limits.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <string>
#include <vector>

#include "blockhash_cl/atomic_file.hpp"
#include "blockhash_cl/config.hpp"
#include "blockhash_cl/error.hpp"
#include "cli.hpp"
#include "commands.hpp"

namespace bhcl::cli {

std::vector<Command>& commands() {
  static std::vector<Command> all;
  return all;
}

namespace {

const Command* find_command(const std::string& name) {
  for (const auto& c : commands())
    if (c.name == name) return &c;
  return nullptr;
}

// CLI11's messages in the words bhcl uses everywhere.
std::string usage_message(const CLI::ParseError& e) {
  std::string m = e.what();
  const std::string required = " is required";
  if (m.rfind("--", 0) == 0 && m.size() > required.size() &&
      m.compare(m.size() - required.size(), required.size(), required) == 0)
    return "missing required option " + m.substr(0, m.size() - required.size());
  if (e.get_name() == "ArgumentMismatch" && m.rfind("--", 0) == 0)
    return "option " + m.substr(0, m.find(':')) + " needs a value";
  return m;
}

}  // namespace

int run_command(const std::vector<std::string>& argv) {
  if (argv.empty()) throw UsageError("no command");
  const Command* c = find_command(argv[0]);
  if (!c) throw UsageError("unknown command '" + argv[0] + "'");
  CLI::App app(c->summary, "bhcl " + c->name);
  app.allow_extras();
  app.get_formatter()->column_width(34);
  Args args(&app, c->name);
  c->declare(args);
  std::vector<std::string> rest(argv.rbegin(), argv.rend() - 1);  // CLI11 takes them reversed
  try {
    app.parse(rest);
  } catch (const CLI::CallForHelp&) {
    std::fputs(app.help().c_str(), stdout);
    return 0;
  } catch (const CLI::ParseError& e) {
    throw UsageError(usage_message(e));
  }
  args.check_extras();
  return c->run(args);
}

}  // namespace bhcl::cli

namespace {

// mkdir -p; false when a component cannot be made.
bool make_dirs(const std::string& path) {
  for (std::size_t i = 1; i <= path.size(); ++i) {
    if (i < path.size() && path[i] != '/') continue;
    const std::string part = path.substr(0, i);
    if (mkdir(part.c_str(), 0755) != 0 && errno != EEXIST) return false;
  }
  return true;
}

#ifdef BHCL_BUILD_TREE
// True when this executable lies inside the build tree it was built in.
bool run_from_build_tree() {
  char exe[PATH_MAX], tree[PATH_MAX];
  if (!realpath("/proc/self/exe", exe) || !realpath(BHCL_BUILD_TREE, tree)) return false;
  const std::string e = exe, t = std::string(tree) + "/";
  return e.compare(0, t.size(), t) == 0;
}
#endif

// PoCL's kernel cache: where the user put it (POCL_CACHE_DIR), else the build tree's for a bhcl
// run from its build tree, else the user's cache directory ($XDG_CACHE_HOME/blockhash_cl/pocl or
// ~/.cache/blockhash_cl/pocl). `bhcl devices` shows which. A folder that cannot be made is left to
// the library, which falls back to a private temporary one and says so (program_cache.hpp).
// The library's program binaries go beside PoCL's cache when run from the build tree (its
// build-tree/program-cache, unless BHCL_CACHE_DIR is set), so that a build tree keeps its own.
void choose_pocl_cache() {
#ifdef BHCL_BUILD_TREE
  const bool in_tree = run_from_build_tree();
  if (const char* mine = std::getenv("BHCL_CACHE_DIR"); in_tree && !(mine && *mine)) {
    const std::string dir = (std::filesystem::path(BHCL_BUILD_TREE_POCL_CACHE).parent_path() / "program-cache").string();
    setenv("BHCL_CACHE_DIR", dir.c_str(), 1);
  }
#endif
  if (const char* set = std::getenv("POCL_CACHE_DIR"); set && *set) return;
#ifdef BHCL_BUILD_TREE
  if (in_tree) {
    setenv("POCL_CACHE_DIR", BHCL_BUILD_TREE_POCL_CACHE, 1);
    return;
  }
#endif
  std::string base;
  if (const char* xdg = std::getenv("XDG_CACHE_HOME"); xdg && xdg[0] == '/') base = xdg;
  else if (const char* home = std::getenv("HOME"); home && home[0] == '/') base = std::string(home) + "/.cache";
  else return;  // PoCL's own default
  const std::string dir = base + "/blockhash_cl/pocl";
  if (make_dirs(dir)) setenv("POCL_CACHE_DIR", dir.c_str(), 1);
}

void print_help(std::FILE* to) {
  auto cmds = bhcl::cli::commands();
  std::sort(cmds.begin(), cmds.end(), [](const auto& a, const auto& b) { return a.name < b.name; });
  std::fprintf(to, "bhcl %s: batched approximate kNN on 3D points with OpenCL (blockhash_cl)\n\n",
               BHCL_VERSION_STRING);
  std::fprintf(to, "usage: bhcl COMMAND [OPTIONS]   (bhcl COMMAND --help lists its options)\n\n");
  for (const auto& c : cmds) std::fprintf(to, "  %-9s %s\n", c.name.c_str(), c.summary.c_str());
  std::fprintf(to,
               "\n  --version  print the version and exit\n"
               "\nEnvironment: BHCL_DEVICE picks the OpenCL device (see `bhcl devices`),\n"
               "BHCL_KERNEL_DIR loads kernels/*.cl from disk instead of the embedded copies.\n");
}

}  // namespace

int main(int argc, char** argv) {
  choose_pocl_cache();
  // Ctrl-C, SIGTERM or SIGHUP mid-write leaves no temporary beside an output (issue 38).
  bhcl::install_temporary_cleanup();
  if (argc < 2) {
    print_help(stderr);
    return 2;
  }
  const std::string first = argv[1];
  if (first == "help" || first == "--help" || first == "-h") {
    print_help(stdout);
    return 0;
  }
  if (first == "--version") {
    std::printf("bhcl %s\n", BHCL_VERSION_STRING);
    return 0;
  }
  if (!bhcl::cli::find_command(first)) {
    std::fprintf(stderr, "bhcl: unknown command '%s' (try `bhcl --help`)\n", first.c_str());
    return 2;
  }
  try {
    return bhcl::cli::run_command(std::vector<std::string>(argv + 1, argv + argc));
  } catch (const bhcl::cli::UsageError& e) {
    std::fprintf(stderr, "bhcl %s: usage error: %s (see `bhcl %s --help`)\n", argv[1], e.what(), argv[1]);
    return 2;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bhcl %s: error: %s\n", argv[1], e.what());
    return 1;
  }
}
