// Sub-commands of bhcl register themselves here, one file each (cmd_*.cpp): each declares its
// options (with their meaning and default, for `bhcl CMD --help`) and runs on the parsed Args.
#pragma once

#include <string>
#include <vector>

namespace bhcl::cli {

class Args;

struct Command {
  std::string name;
  std::string summary;             // one line, shown by `bhcl --help`
  void (*declare)(Args& args);     // declares the options
  int (*run)(const Args& args);    // runs on the parsed options
};

std::vector<Command>& commands();

struct RegisterCommand {
  RegisterCommand(std::string name, std::string summary, void (*declare)(Args&), int (*run)(const Args&)) {
    commands().push_back({std::move(name), std::move(summary), declare, run});
  }
};

// Parses and runs `bhcl ARGV...` (argv[0] the sub-command) without printing: usage mistakes
// throw UsageError, other failures their own exception. The demo runs `render` through it.
int run_command(const std::vector<std::string>& argv);

}  // namespace bhcl::cli
