// The runtime layer: device choice, kernel sources, program building and its errors.
#include "test_util.hpp"

using namespace bhcl;

TEST_CASE("runtime: a device is found and PoCL is the default") {
  auto devs = list_devices();
  REQUIRE(!devs.empty());
  DeviceInfo d = select_device("default");
  bool any_pocl = std::any_of(devs.begin(), devs.end(), [](const DeviceInfo& x) { return x.is_pocl; });
  if (any_pocl) CHECK(d.is_pocl);
  CHECK(!d.summary().empty());
}

TEST_CASE("runtime: device specs by index, type and name") {
  auto devs = list_devices();
  REQUIRE(!devs.empty());
  const DeviceInfo& first = devs.front();
  DeviceInfo by_index = select_device(std::to_string(first.platform_index) + ":" +
                                      std::to_string(first.device_index));
  CHECK(by_index.device_name == first.device_name);
  DeviceInfo by_name = select_device(first.platform_name.substr(0, 4));
  CHECK(by_name.platform_index == first.platform_index);
  CHECK_THROWS_WITH_AS(select_device("no-such-vendor-xyz"),
                       doctest::Contains("no OpenCL device matches 'no-such-vendor-xyz'"), Error);
  CHECK_THROWS_WITH_AS(select_device("99:0"), doctest::Contains("no device 99:0"), Error);
  CHECK_THROWS_AS(select_device("pocl:x"), Error);
}

TEST_CASE("runtime: embedded kernel sources resolve their includes") {
  std::string src = kernel_source("bruteforce_knn.cl");
  CHECK(src.find("__kernel void bruteforce_knn") != std::string::npos);
  CHECK(src.find("bhcl_topk_push") != std::string::npos);     // from knn_common.h
  CHECK(src.find("BHCL_EMPTY_SLOT_ID") != std::string::npos);  // from bhcl_shared.h
  CHECK(src.find("#include \"") == std::string::npos);
  CHECK_THROWS_WITH_AS(kernel_source("missing.cl"), doctest::Contains("missing.cl"), Error);
}

TEST_CASE("runtime: a kernel that fails to build reports its log and options") {
  auto rt = test::runtime();
  const std::string bad = "__kernel void broken(__global float* x) { x[0] = undeclared_name; }\n";
  try {
    rt->build_source(bad, "-DSOME_DEFINE=3", "broken.cl");
    FAIL("the build should have failed");
  } catch (const BuildError& e) {
    CHECK(e.code() == CL_BUILD_PROGRAM_FAILURE);
    CHECK(e.call() == "clBuildProgram");
    CHECK(e.options().find("-cl-std=CL1.2") != std::string::npos);
    CHECK(e.options().find("-DSOME_DEFINE=3") != std::string::npos);
    CHECK(e.log().find("undeclared_name") != std::string::npos);
    std::string what = e.what();
    CHECK(what.find("broken.cl") != std::string::npos);
    CHECK(what.find("CL_BUILD_PROGRAM_FAILURE") != std::string::npos);
  }
}

TEST_CASE("runtime: programs are cached per device and options") {
  auto rt = test::runtime();
  cl::Program a = rt->program("bruteforce_knn.cl", "-DBHCL_KMAX=8");
  cl::Program b = rt->program("bruteforce_knn.cl", "-DBHCL_KMAX=8");
  cl::Program c = rt->program("bruteforce_knn.cl", "-DBHCL_KMAX=16");
  CHECK(a() == b());
  CHECK(a() != c());
}

TEST_CASE("runtime: OpenCL error names and ClError context") {
  CHECK(cl_error_name(CL_OUT_OF_RESOURCES) == "CL_OUT_OF_RESOURCES");
  CHECK(cl_error_name(-12345) == "CL_UNKNOWN_ERROR(-12345)");
  CHECK_THROWS_WITH_AS(check_cl(CL_INVALID_VALUE, "clFoo", "in bar"),
                       "clFoo failed: CL_INVALID_VALUE (in bar)", ClError);
  CHECK_NOTHROW(check_cl(CL_SUCCESS, "clFoo"));
}

TEST_CASE("runtime: BHCL_KERNEL_DIR loads kernels from disk") {
  std::string dir = test::tmp_path("kernels_override");
  std::system(("mkdir -p \"" + dir + "\"").c_str());
  {
    std::ofstream f(dir + "/only_on_disk.cl");
    f << "#include \"extra.h\"\n__kernel void k(__global int* x) { x[0] = EXTRA; }\n";
    std::ofstream h(dir + "/extra.h");
    h << "#define EXTRA 42\n";
  }
  setenv("BHCL_KERNEL_DIR", dir.c_str(), 1);
  std::string src = kernel_source("only_on_disk.cl");
  unsetenv("BHCL_KERNEL_DIR");
  CHECK(src.find("#define EXTRA 42") != std::string::npos);
  CHECK_THROWS_AS(kernel_source("only_on_disk.cl"), Error);  // not embedded
}
