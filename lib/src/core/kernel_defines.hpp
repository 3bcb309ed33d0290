// The one table of the -D defines the kernels read (CLBlast keeps its tuning parameters so): per
// define its kind, the range a caller may give, its default in the kernel source and the kernels
// that read it. The host renders its own defines through it (a misspelt name is an error, not a
// silent default) and checks a caller's SearchParams::kernel_defines against it: a name no kernel
// reads, one the kernel being built does not read, one the library sets from the index's build
// (structural), or a value out of range is refused with a message. tests/kernel_defines_tests.cpp
// checks the table against the kernel sources (names, defaults, which kernel reads what).
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

namespace bhcl::detail {

struct KernelDefine {
  enum Kind {
    Structural,  // must match the host's arrays or the build: set by the library only
    Tuning,      // trades speed only, results unchanged (or as documented beside it)
    Experiment,  // a measured alternative kept in the source: a caller may try it
  };
  struct Reader {
    const char* kernel;    // a kernel file (kernels/*.cl) that reads it, includes expanded
    const char* fallback;  // its source's default, as written there
  };
  const char* name;  // BHCL_...
  Kind kind;
  long long lo, hi;  // the values a caller may give
  const char* help;
  std::vector<Reader> readers;
  bool read_by(const std::string& kernel) const;
};

const std::vector<KernelDefine>& kernel_define_table();
// The entry of `name` (BHCL_...), nullptr when no kernel reads it.
const KernelDefine* find_kernel_define(const std::string& name);

// One define of a caller's kernel_defines: its entry, the value as written and as read.
struct CallerDefine {
  const KernelDefine* define;
  std::string text;  // "1" for a -DNAME without a value
  long long value;
};
// A caller's kernel_defines, in order. Throws bhcl::Error for a token that is not
// -DNAME[=VALUE], or a name no kernel reads (listing the table), or a structural one, or a value
// that is not an integer in the entry's range.
std::vector<CallerDefine> parse_kernel_defines(const std::string& defines);

// The build options of kernel `file`: the library's own defines (each must be in the table and
// read by `file`: an internal error otherwise) but those the caller sets, then the caller's, each
// of which `file` must read (bhcl::Error naming the define, the kernel and the kernels that do
// read it): a caller's define replaces the library's value of it.
using DefineValues = std::vector<std::pair<const char*, long long>>;
std::string kernel_build_options(const std::string& file, const DefineValues& library,
                                 const std::string& caller_defines);

// The value the kernel sees for `name` under the caller's defines (the last one wins, as in the
// OpenCL compiler; decimal, 0x hex or 0 octal, as C reads a literal), `fallback` when unset.
std::uint32_t caller_define_value(const std::string& caller_defines, const std::string& name,
                                  std::uint32_t fallback);

}  // namespace bhcl::detail
