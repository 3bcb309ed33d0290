// Device choice, kernel sources (embedded or from BHCL_KERNEL_DIR), program building and caching.
#include "blockhash_cl/runtime.hpp"

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <sstream>
#include <string_view>
#include <tuple>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/numbers.hpp"
#include "core/program_cache.hpp"

namespace bhcl {
namespace detail {
const std::map<std::string, std::string_view>& embedded_kernel_files();
}

namespace {

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  return s;
}

std::string trim_nul(std::string s) {
  while (!s.empty() && (s.back() == '\0' || std::isspace(static_cast<unsigned char>(s.back()))))
    s.pop_back();
  return s;
}

std::string devices_listing(const std::vector<DeviceInfo>& devs) {
  std::ostringstream os;
  if (devs.empty()) os << "  (no OpenCL device found: is pocl-opencl-icd installed?)\n";
  for (const auto& d : devs)
    os << "  " << d.platform_index << ":" << d.device_index << "  " << d.summary() << "\n";
  return os.str();
}

// Raw text of a kernels/ file: from BHCL_KERNEL_DIR when set, else the embedded copy.
std::string raw_kernel_file(const std::string& file) {
  if (const char* dir = std::getenv("BHCL_KERNEL_DIR"); dir && *dir) {
    std::string path = std::string(dir) + "/" + file;
    std::ifstream in(path, std::ios::binary);
    if (!in) throw Error("kernel file '" + path + "' not found (BHCL_KERNEL_DIR=" + dir + ")");
    std::ostringstream ss;
    ss << in.rdbuf();
    return ss.str();
  }
  const auto& files = detail::embedded_kernel_files();
  auto it = files.find(file);
  if (it == files.end()) throw Error("kernel file '" + file + "' is not embedded in the library");
  return std::string(it->second);
}

void resolve_includes(const std::string& file, std::vector<std::string>& stack, std::string& out) {
  if (std::find(stack.begin(), stack.end(), file) != stack.end()) return;  // include guard twin
  stack.push_back(file);
  std::istringstream in(raw_kernel_file(file));
  std::string line;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    std::string_view v(line);
    size_t p = v.find_first_not_of(" \t");
    if (p != std::string_view::npos && v.substr(p, 8) == "#include") {
      size_t a = v.find('"', p), b = a == std::string_view::npos ? a : v.find('"', a + 1);
      if (a != std::string_view::npos && b != std::string_view::npos) {
        std::string inc(v.substr(a + 1, b - a - 1));
        resolve_includes(inc, stack, out);
        out += "#line " + std::to_string(line_no + 1) + "\n";
        continue;
      }
    }
    out += line;
    out += '\n';
  }
}

struct ProgramKey {
  cl_context context;
  cl_device_id device;
  std::string file, options;
  bool operator<(const ProgramKey& o) const {
    return std::tie(context, device, file, options) < std::tie(o.context, o.device, o.file, o.options);
  }
};

// BHCL_DUMP_PROGRAMS=dir: each library program built (first build of a file at some options)
// is written to dir as NAME.cl (its source, includes resolved) and NAME.options (the full option
// string the build got), NAME = the file's stem and a hash of options and source. For tools that
// compile the kernels offline (bench/gpu_kernel_table.sh: registers and stack for sm_90).
void dump_program(const std::string& file, const std::string& source, const std::string& options) {
  const char* dir = std::getenv("BHCL_DUMP_PROGRAMS");
  if (!dir || !*dir) return;
  std::string stem = file.substr(0, file.rfind('.'));
  std::ostringstream name;
  name << dir << "/" << stem << "." << std::hex << (std::hash<std::string>{}(options + '\n' + source) & 0xffffffffu);
  std::ofstream src(name.str() + ".cl", std::ios::binary), opt(name.str() + ".options", std::ios::binary);
  src << source;
  opt << options << "\n";
  if (!src || !opt) throw Error("BHCL_DUMP_PROGRAMS: cannot write '" + name.str() + ".cl/.options'");
}

std::mutex& cache_mutex() {
  static std::mutex m;
  return m;
}
std::map<ProgramKey, cl::Program>& program_cache() {
  static std::map<ProgramKey, cl::Program> cache;
  return cache;
}
// Per program: its binary cache file and the size of the binary last stored or loaded there (a
// later launch that compiled more work-group functions grows the binary: stored again).
struct StoredBinary {
  detail::ProgramBinaryCache file;
  std::size_t bytes = 0;
  bool fresh = false;  // built from source in this process: its first launches grow the binary
};
std::map<ProgramKey, StoredBinary>& stored_binaries() {
  static std::map<ProgramKey, StoredBinary> m;
  return m;
}

// The binary of a built program for its one device (empty when the driver gives none).
std::vector<unsigned char> program_binary(const cl::Program& p) {
  std::vector<std::size_t> sizes;
  if (p.getInfo(CL_PROGRAM_BINARY_SIZES, &sizes) != CL_SUCCESS || sizes.size() != 1 || sizes[0] == 0) return {};
  std::vector<unsigned char> bin(sizes[0]);
  unsigned char* ptr = bin.data();
  if (clGetProgramInfo(p(), CL_PROGRAM_BINARIES, sizeof ptr, &ptr, nullptr) != CL_SUCCESS) return {};
  return bin;
}

}  // namespace

std::string DeviceInfo::type_name() const {
  if (type & CL_DEVICE_TYPE_GPU) return "GPU";
  if (type & CL_DEVICE_TYPE_CPU) return "CPU";
  if (type & CL_DEVICE_TYPE_ACCELERATOR) return "accelerator";
  return "other";
}

std::string DeviceInfo::summary() const {
  std::ostringstream os;
  os << platform_name << " / " << device_name << " (" << type_name() << ", " << compute_units
     << " CU, " << (global_mem_bytes >> 20) << " MiB, " << device_version << ")";
  return os.str();
}

std::vector<DeviceInfo> list_devices() {
  std::vector<DeviceInfo> out;
  // PoCL reads its cache folder at its first call: a folder it cannot make must be replaced now.
  detail::ensure_pocl_cache_usable();
  std::vector<cl::Platform> platforms;
  if (cl::Platform::get(&platforms) != CL_SUCCESS) return out;  // no ICD: no devices
  for (size_t pi = 0; pi < platforms.size(); ++pi) {
    std::vector<cl::Device> devices;
    if (platforms[pi].getDevices(CL_DEVICE_TYPE_ALL, &devices) != CL_SUCCESS) continue;
    for (size_t di = 0; di < devices.size(); ++di) {
      const cl::Device& d = devices[di];
      DeviceInfo info;
      info.platform_index = pi;
      info.device_index = di;
      info.platform_name = trim_nul(platforms[pi].getInfo<CL_PLATFORM_NAME>());
      info.platform_vendor = trim_nul(platforms[pi].getInfo<CL_PLATFORM_VENDOR>());
      info.platform_version = trim_nul(platforms[pi].getInfo<CL_PLATFORM_VERSION>());
      info.device_name = trim_nul(d.getInfo<CL_DEVICE_NAME>());
      info.device_vendor = trim_nul(d.getInfo<CL_DEVICE_VENDOR>());
      info.device_version = trim_nul(d.getInfo<CL_DEVICE_VERSION>());
      info.driver_version = trim_nul(d.getInfo<CL_DRIVER_VERSION>());
      info.type = d.getInfo<CL_DEVICE_TYPE>();
      info.compute_units = d.getInfo<CL_DEVICE_MAX_COMPUTE_UNITS>();
      info.global_mem_bytes = d.getInfo<CL_DEVICE_GLOBAL_MEM_SIZE>();
      info.max_alloc_bytes = d.getInfo<CL_DEVICE_MAX_MEM_ALLOC_SIZE>();
      info.max_work_group_size = d.getInfo<CL_DEVICE_MAX_WORK_GROUP_SIZE>();
      std::string all = lower(info.platform_name + " " + info.platform_vendor);
      info.is_pocl = all.find("portable computing language") != std::string::npos ||
                     all.find("pocl") != std::string::npos;
      info.is_nvidia = all.find("nvidia") != std::string::npos;
      out.push_back(std::move(info));
    }
  }
  return out;
}

DeviceInfo select_device(const std::string& spec_in) {
  std::string spec = spec_in;
  if (spec.empty()) {
    if (const char* env = std::getenv("BHCL_DEVICE")) spec = env;
  }
  spec = lower(spec);
  auto devs = list_devices();
  auto fail = [&](const std::string& why) -> DeviceInfo {
    throw Error("no OpenCL device matches '" + spec + "' (" + why + "); devices:\n" +
                devices_listing(devs));
  };
  if (devs.empty()) fail("no OpenCL platform or device found");
  if (spec.empty() || spec == "default") {
    for (const auto& d : devs)
      if (d.is_pocl) return d;
    return devs.front();
  }
  // "P:D" numeric
  size_t colon = spec.find(':');
  std::string head = spec.substr(0, colon);
  std::string tail = colon == std::string::npos ? "" : spec.substr(colon + 1);
  auto is_number = [](const std::string& s) {
    return !s.empty() && std::all_of(s.begin(), s.end(), [](unsigned char c) { return std::isdigit(c); });
  };
  // Digits past the integer range name no device either (issue 38: std::stoul threw "stoul").
  auto index_of = [](const std::string& s) {
    unsigned long long v = 0;
    return detail::parse_integer(s, v) == detail::NumberParse::Ok ? v : ~0ull;
  };
  if (is_number(head) && is_number(tail)) {
    const unsigned long long p = index_of(head), d = index_of(tail);
    for (const auto& dev : devs)
      if (dev.platform_index == p && dev.device_index == d) return dev;
    return fail("no device " + head + ":" + tail);
  }
  if (!tail.empty() && !is_number(tail)) return fail("expected NAME[:INDEX] or P:D");
  const unsigned long long want = tail.empty() ? 0 : index_of(tail);
  std::vector<DeviceInfo> matches;
  for (const auto& d : devs) {
    bool match;
    if (head == "cpu") match = d.type & CL_DEVICE_TYPE_CPU;
    else if (head == "gpu") match = d.type & CL_DEVICE_TYPE_GPU;
    else
      match = lower(d.platform_name + " " + d.platform_vendor + " " + d.device_name + " " +
                    d.device_vendor)
                  .find(head) != std::string::npos;
    if (match) matches.push_back(d);
  }
  if (want >= matches.size())
    return fail(std::to_string(matches.size()) + " device(s) match '" + head + "'");
  return matches[want];
}

std::string kernel_source(const std::string& file) {
  std::vector<std::string> stack;
  std::string out;
  resolve_includes(file, stack, out);
  return out;
}

Runtime::Runtime(const std::string& spec) { init_from(select_device(spec)); }

Runtime::Runtime(cl::Context context, cl::Device device, cl::CommandQueue queue)
    : context_(std::move(context)), device_(std::move(device)), queue_(std::move(queue)) {
  // Describe the caller's device the way list_devices() does.
  cl_platform_id pid = device_.getInfo<CL_DEVICE_PLATFORM>();
  for (const auto& d : list_devices()) {
    std::vector<cl::Platform> platforms;
    cl::Platform::get(&platforms);
    std::vector<cl::Device> devices;
    platforms[d.platform_index].getDevices(CL_DEVICE_TYPE_ALL, &devices);
    if (platforms[d.platform_index]() == pid && devices[d.device_index]() == device_()) {
      info_ = d;
      break;
    }
  }
  quirks_ = quirks_for(info_);
  // Host-array queries read results back after the kernels on this queue: an out-of-order queue
  // would let a read overtake its kernel. Refused rather than silently wrong.
  cl_command_queue_properties props = 0;
  check_cl(queue_.getInfo(CL_QUEUE_PROPERTIES, &props), "clGetCommandQueueInfo", "the caller's queue");
  if (props & CL_QUEUE_OUT_OF_ORDER_EXEC_MODE_ENABLE)
    throw Error("Runtime: the caller's queue is out of order (CL_QUEUE_OUT_OF_ORDER_EXEC_MODE_ENABLE); "
                "pass an in-order queue (enqueue_query accepts out-of-order queues)");
  make_warm_queue();
}

void Runtime::make_warm_queue() {
  cl_int err = CL_SUCCESS;
  warm_queue_ = cl::CommandQueue(context_, device_, 0, &err);
  check_cl(err, "clCreateCommandQueue", "the warm-up queue of " + info_.summary());
}

void Runtime::init_from(const DeviceInfo& info) {
  info_ = info;
  std::vector<cl::Platform> platforms;
  check_cl(cl::Platform::get(&platforms), "clGetPlatformIDs");
  std::vector<cl::Device> devices;
  check_cl(platforms.at(info.platform_index).getDevices(CL_DEVICE_TYPE_ALL, &devices),
           "clGetDeviceIDs", info.platform_name);
  device_ = devices.at(info.device_index);
  cl_int err = CL_SUCCESS;
  context_ = cl::Context(device_, nullptr, nullptr, nullptr, &err);
  check_cl(err, "clCreateContext", info.summary());
  queue_ = cl::CommandQueue(context_, device_, CL_QUEUE_PROFILING_ENABLE, &err);
  check_cl(err, "clCreateCommandQueue", info.summary());
  quirks_ = quirks_for(info_);
  make_warm_queue();
}

std::string Runtime::build_options(const std::string& extra) const {
  std::string opts = "-cl-std=CL1.2";
  if (!extra.empty()) opts += " " + extra;
  return opts;
}

cl::Program Runtime::build_source(const std::string& source, const std::string& options,
                                  const std::string& name) const {
  cl_int err = CL_SUCCESS;
  cl::Program program(context_, source, false, &err);
  check_cl(err, "clCreateProgramWithSource", name);
  std::string opts = build_options(options);
  auto t0 = std::chrono::steady_clock::now();
  err = program.build(std::vector<cl::Device>{device_}, opts.c_str());
  double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  {
    std::lock_guard<std::mutex> lock(mutex_);
    build_seconds_ += s;
  }
  if (err != CL_SUCCESS) {
    std::string log;
    program.getBuildInfo(device_, CL_PROGRAM_BUILD_LOG, &log);
    throw BuildError(err, name, opts, trim_nul(log));
  }
  return program;
}

cl::Program Runtime::program(const std::string& file, const std::string& options) const {
  ProgramKey key{context_(), device_(), file, options};
  {
    std::lock_guard<std::mutex> lock(cache_mutex());
    auto it = program_cache().find(key);
    if (it != program_cache().end()) return it->second;
  }
  std::string source = kernel_source(file);
  const std::string opts = build_options(options);
  dump_program(file, source, opts);
  detail::ProgramBinaryCache stored(file, binary_key(opts, source));
  std::size_t stored_bytes = 0;
  bool fresh = false;
  cl::Program p;
  if (auto bin = stored.load()) {
    stored_bytes = bin->size();
    p = build_binary(*bin, file);
  }
  if (!p()) {
    // PoCL re-reads its own cache on a build from source: its damaged files are removed first.
    if (info_.is_pocl) detail::check_pocl_cache_once();
    p = build_source(source, options, file);
    const std::vector<unsigned char> bin = stored.enabled() ? program_binary(p) : std::vector<unsigned char>();
    stored.store(bin);
    stored_bytes = bin.size();
    fresh = stored.enabled();
  }
  std::lock_guard<std::mutex> lock(cache_mutex());
  stored_binaries().insert_or_assign(key, StoredBinary{stored, stored_bytes, fresh});
  return program_cache().emplace(key, p).first->second;
}

std::string Runtime::binary_key(const std::string& full_options, const std::string& source) const {
  // Everything the compiled program depends on; the driver version carries PoCL's version.
  return "blockhash_cl program 1\n" + info_.platform_name + "\n" + info_.platform_version + "\n" +
         info_.device_name + "\n" + info_.device_vendor + "\n" + info_.driver_version + "\n" +
         full_options + "\n" + source;
}

cl::Program Runtime::build_binary(const std::vector<unsigned char>& bin, const std::string& name) const {
  // The program's folder in PoCL's cache is checked first: PoCL loads what it finds there.
  if (info_.is_pocl) detail::check_pocl_program_folder(bin);
  auto t0 = std::chrono::steady_clock::now();
  cl_int err = CL_SUCCESS, status = CL_SUCCESS;
  const unsigned char* ptr = bin.data();
  const std::size_t size = bin.size();
  cl_device_id dev = device_();
  cl_program raw = clCreateProgramWithBinary(context_(), 1, &dev, &size, &ptr, &status, &err);
  cl::Program p;
  if (err == CL_SUCCESS && status == CL_SUCCESS) {
    p = cl::Program(raw);
    err = p.build(std::vector<cl::Device>{device_}, build_options("").c_str());
  } else if (raw) {
    clReleaseProgram(raw);
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    build_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
  if (err == CL_SUCCESS && status == CL_SUCCESS) return p;
  // A binary the driver no longer takes (another build of it with the same version string):
  // compiled again from source, and said once.
  detail::note_once("program-binary-refused", "the driver refused the cached program binary of " + name +
                                                  " (OpenCL error " + std::to_string(err != CL_SUCCESS ? err : status) +
                                                  "); compiled from source");
  return cl::Program();
}

void Runtime::keep_program_binaries() const {
  // Programs loaded from a stored binary are left as they are: re-reading a binary costs PoCL a
  // walk of its cache folder, which a warm process should not pay.
  std::vector<std::pair<ProgramKey, cl::Program>> fresh;
  {
    std::lock_guard<std::mutex> lock(cache_mutex());
    for (auto& [key, st] : stored_binaries())
      if (st.fresh && key.context == context_() && key.device == device_()) {
        st.fresh = false;
        fresh.emplace_back(key, program_cache().at(key));
      }
  }
  for (const auto& [key, p] : fresh) {
    const std::vector<unsigned char> bin = program_binary(p);
    std::lock_guard<std::mutex> lock(cache_mutex());
    StoredBinary& st = stored_binaries().at(key);
    if (bin.size() == st.bytes) continue;
    st.file.store(bin);
    st.bytes = bin.size();
  }
}

cl::Kernel Runtime::kernel(const std::string& file, const std::string& kernel_name,
                           const std::string& options) const {
  cl_int err = CL_SUCCESS;
  cl::Kernel k(program(file, options), kernel_name.c_str(), &err);
  check_cl(err, "clCreateKernel", kernel_name + " in " + file);
  return k;
}

double Runtime::build_seconds() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return build_seconds_;
}

std::shared_ptr<Runtime> default_runtime() {
  static std::mutex m;
  static std::shared_ptr<Runtime> rt;
  std::lock_guard<std::mutex> lock(m);
  if (!rt) rt = std::make_shared<Runtime>();
  return rt;
}

double event_seconds(const cl::Event& e) {
  cl_ulong start = 0, end = 0;
  // A queue without CL_QUEUE_PROFILING_ENABLE (a caller's) has no timings: 0, not an error.
  cl_int err = e.getProfilingInfo(CL_PROFILING_COMMAND_START, &start);
  if (err == CL_PROFILING_INFO_NOT_AVAILABLE) return 0.0;
  check_cl(err, "clGetEventProfilingInfo");
  check_cl(e.getProfilingInfo(CL_PROFILING_COMMAND_END, &end), "clGetEventProfilingInfo");
  return end > start ? (end - start) * 1e-9 : 0.0;
}

}  // namespace bhcl
