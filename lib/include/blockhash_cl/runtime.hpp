// The OpenCL runtime layer: device choice, program building and caching, kernel sources.
//
// Device choice (VexCL-style): a spec string, or the environment variable BHCL_DEVICE when the
// spec is empty. Grammar, case-insensitive:
//   ""/"default"   PoCL if present, else the first device found
//   "P:D"          platform index P, device index D (as `bhcl devices` lists them)
//   "cpu" / "gpu"  the first device of that type
//   "NAME[:D]"     the D-th device (default 0) whose platform name, vendor or device name contains
//                  NAME, e.g. "pocl", "nvidia", "nvidia:1"
// An NVIDIA GPU is reached through NVIDIA's OpenCL driver: point OCL_ICD_VENDORS at a directory
// holding a `nvidia.icd` file whose content is `libnvidia-opencl.so.1` (see README).
#pragma once

#include <CL/opencl.hpp>

#include <cstddef>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "blockhash_cl/quirks.hpp"

namespace bhcl {

struct DeviceInfo {
  std::size_t platform_index = 0;
  std::size_t device_index = 0;
  std::string platform_name, platform_vendor, platform_version;
  std::string device_name, device_vendor, device_version, driver_version;
  cl_device_type type = 0;
  unsigned compute_units = 0;
  unsigned long long global_mem_bytes = 0;
  unsigned long long max_alloc_bytes = 0;
  std::size_t max_work_group_size = 0;
  bool is_pocl = false;
  bool is_nvidia = false;

  std::string type_name() const;                // "CPU", "GPU", ...
  std::string summary() const;                  // "PoCL / pthread-haswell-AMD EPYC (CPU, 2 CU)"
};

// Every device of every platform the ICD loader sees. Empty (no throw) when there is none.
std::vector<DeviceInfo> list_devices();

// Picks a device by spec (see top of file). Throws bhcl::Error naming the spec and listing the
// devices when none matches.
DeviceInfo select_device(const std::string& spec);

// The source of a file under kernels/, with `#include "x"` lines replaced by the file x. Comes from
// the sources embedded at build time, or from the directory BHCL_KERNEL_DIR when it is set.
std::string kernel_source(const std::string& file);

class Runtime {
 public:
  // Opens the device picked by spec (empty: BHCL_DEVICE, then the default), with an in-order
  // queue that has profiling enabled.
  explicit Runtime(const std::string& spec = {});
  // Uses the caller's objects. The queue must be in order (an out-of-order queue is refused: the
  // host-array calls read results back after their kernels on it); without
  // CL_QUEUE_PROFILING_ENABLE queries answer with zero timings (QueryStats' event times).
  Runtime(cl::Context context, cl::Device device, cl::CommandQueue queue);

  const cl::Context& context() const { return context_; }
  const cl::Device& device() const { return device_; }
  const cl::CommandQueue& queue() const { return queue_; }
  // The library's own queue for one-off warm-up launches, so that a warm-up never waits behind
  // the caller's commands on queue() (e.g. ones gated by a user event).
  const cl::CommandQueue& warm_queue() const { return warm_queue_; }
  const DeviceInfo& info() const { return info_; }
  const Quirks& quirks() const { return quirks_; }

  // Builds (or returns the cached) program of a kernels/ file with the given extra options.
  // "-cl-std=CL1.2" and the quirks' options are always added. Cached per context, device, file
  // and options, in the process and across processes (the library's program binary cache: a
  // warm process builds from the stored binary in about a millisecond; see program_cache.hpp).
  // Throws BuildError with the log on failure.
  cl::Program program(const std::string& file, const std::string& options = {}) const;

  // After first launches: the binaries of the programs this process built from source, which now
  // hold the machine code compiled for those launches, replace the stored ones when they grew
  // (the library's program cache, lib/src/core/program_cache.hpp), so that the next process
  // loads them instead of compiling.
  void keep_program_binaries() const;

  // Builds a program from source text (not cached); for tests and user kernels.
  cl::Program build_source(const std::string& source, const std::string& options,
                           const std::string& name = "<source>") const;

  // A new kernel object of a cached program (kernel objects are not shared: setArg is stateful).
  cl::Kernel kernel(const std::string& file, const std::string& kernel_name,
                    const std::string& options = {}) const;

  // The full option string a build gets.
  std::string build_options(const std::string& extra) const;

  // Total seconds spent in clBuildProgram by this runtime (first builds only; cache hits are 0).
  double build_seconds() const;

 private:
  void init_from(const DeviceInfo& info);
  void make_warm_queue();
  std::string binary_key(const std::string& full_options, const std::string& source) const;
  // A program from a stored binary, built; an empty one when the driver refuses the binary.
  cl::Program build_binary(const std::vector<unsigned char>& binary, const std::string& name) const;

  cl::Context context_;
  cl::Device device_;
  cl::CommandQueue queue_, warm_queue_;
  DeviceInfo info_;
  Quirks quirks_;
  mutable std::mutex mutex_;
  mutable double build_seconds_ = 0.0;
};

// A runtime shared by everything in a process that does not pass its own (created on first use
// from BHCL_DEVICE).
std::shared_ptr<Runtime> default_runtime();

// Seconds between a profiled event's START and END (0 when its queue has no profiling).
double event_seconds(const cl::Event& e);

}  // namespace bhcl
