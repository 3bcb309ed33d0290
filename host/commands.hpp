// Sub-commands of bhcl register themselves here, one file each (cmd_*.cpp).
#pragma once

#include <string>
#include <vector>

namespace bhcl::cli {

struct Command {
  std::string name;
  std::string usage;  // the synopsis printed by `bhcl help`
  int (*run)(int argc, char** argv);  // argv[0] is the sub-command; options from argv[1]
};

std::vector<Command>& commands();

struct RegisterCommand {
  RegisterCommand(std::string name, std::string usage, int (*run)(int, char**)) {
    commands().push_back({std::move(name), std::move(usage), run});
  }
};

}  // namespace bhcl::cli
