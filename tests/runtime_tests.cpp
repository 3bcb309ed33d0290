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

TEST_CASE("runtime: a caller's queue: out of order refused, without profiling answered without timings") {
  auto base = test::runtime();
  const cl::Context& ctx = base->context();
  const cl::Device& dev = base->device();
  cl_int err = CL_SUCCESS;
  cl::CommandQueue ooo(ctx, dev, CL_QUEUE_OUT_OF_ORDER_EXEC_MODE_ENABLE, &err);
  if (err == CL_SUCCESS)
    CHECK_THROWS_WITH_AS(Runtime(ctx, dev, ooo), doctest::Contains("out of order"), Error);
  else
    MESSAGE("this device has no out-of-order queues: the refusal is not reachable here");
  cl::CommandQueue plain(ctx, dev, 0, &err);
  REQUIRE(err == CL_SUCCESS);
  auto rt = std::make_shared<Runtime>(ctx, dev, plain);
  auto pts = datasets::uniform(2000, 91), qs = datasets::uniform(300, 92);
  for (const auto& method : method_names()) {
    CAPTURE(method);
    auto index = make_index(method, rt, pts.data(), 2000);
    SearchParams p = test::knn_params(7);
    QueryStats st;
    KnnResult r;
    REQUIRE_NOTHROW(r = index->query(qs, p, &st));
    CHECK(r.ids == make_index(method, base, pts.data(), 2000)->query(qs, p).ids);
    if (method_info(method).on_device) CHECK(st.query_s == 0.0);  // no profiling: no event times
  }
}

TEST_CASE("runtime: enqueue_query behind a user event on the runtime's own queue never blocks a device method") {
  // A single-threaded pipeline: the queries' upload waits for a user event on the runtime's queue,
  // then the query is enqueued behind it, then the event is completed. A warm-up launch on that
  // same queue would wait behind the gated upload forever.
  auto pts = datasets::clustered(3000, 93, 5, 0.02f), qs = datasets::uniform(400, 94);
  for (const auto& method : method_names()) {
    if (!method_info(method).on_device) continue;  // host methods block on `wait` (knn.hpp)
    CAPTURE(method);
    auto rt = std::make_shared<Runtime>();  // its own queue, cold kernels
    std::shared_ptr<Index> index = make_index(method, rt, pts.data(), 3000);
    SearchParams p = test::knn_params(6);
    p.max_batch = 50;  // 8 batches: the returned event must cover them all
    cl::UserEvent gate(rt->context());
    std::vector<cl::Event> gated{gate};
    cl::Buffer qb(rt->context(), CL_MEM_READ_ONLY, qs.size() * 4);
    cl::Event up;
    rt->queue().enqueueWriteBuffer(qb, CL_FALSE, 0, qs.size() * 4, qs.data(), &gated, &up);
    std::vector<cl::Event> wait{up};
    ResultBuffers out{cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 400 * 6 * 4),
                      cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 400 * 6 * 4),
                      cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 400 * 4)};
    // On a detached thread with a deadline: a blocked call fails the test instead of hanging it
    // (the gate is opened either way, so the thread can finish).
    auto result = std::make_shared<std::promise<cl::Event>>();
    std::future<cl::Event> call = result->get_future();
    std::thread([=] {  // copies only: the thread may outlive this scope if it is stuck
      try { result->set_value(index->enqueue_query(rt->queue(), qb, 400, out, p, &wait)); }
      catch (...) { result->set_exception(std::current_exception()); }
    }).detach();
    const bool returned = call.wait_for(std::chrono::seconds(60)) == std::future_status::ready;
    gate.setStatus(CL_COMPLETE);
    REQUIRE(returned);
    std::vector<cl::Event> after{call.get()};
    std::vector<int> ids(400 * 6);
    rt->queue().enqueueReadBuffer(out.ids, CL_TRUE, 0, ids.size() * 4, ids.data(), &after);
    CHECK(ids == index->query(qs, p).ids);
  }
}

TEST_CASE("runtime: enqueue_query on an out-of-order queue: every batch after the wait list, one event for all") {
  auto rt = test::runtime();
  cl_int err = CL_SUCCESS;
  cl::CommandQueue ooo(rt->context(), rt->device(), CL_QUEUE_OUT_OF_ORDER_EXEC_MODE_ENABLE, &err);
  if (err != CL_SUCCESS) {
    MESSAGE("this device has no out-of-order queues");
    return;
  }
  auto pts = datasets::clustered(3000, 95, 5, 0.02f), qs = datasets::uniform(400, 96);
  for (const auto& method : method_names()) {
    if (!method_info(method).on_device) continue;
    CAPTURE(method);
    auto index = make_index(method, rt, pts.data(), 3000);
    SearchParams p = test::knn_params(6);
    p.max_batch = 50;
    index->warm_up(p);
    // The queries arrive after a user event: batches not ordered after it would read garbage.
    cl::UserEvent gate(rt->context());
    std::vector<cl::Event> gated{gate};
    cl::Buffer qb(rt->context(), CL_MEM_READ_ONLY, qs.size() * 4);
    cl::Event up;
    ooo.enqueueWriteBuffer(qb, CL_FALSE, 0, qs.size() * 4, qs.data(), &gated, &up);
    std::vector<cl::Event> wait{up};
    ResultBuffers out{cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 400 * 6 * 4),
                      cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 400 * 6 * 4),
                      cl::Buffer(rt->context(), CL_MEM_READ_WRITE, 400 * 4)};
    cl::Event done = index->enqueue_query(ooo, qb, 400, out, p, &wait);
    gate.setStatus(CL_COMPLETE);
    std::vector<cl::Event> after{done};
    std::vector<int> ids(400 * 6);
    ooo.enqueueReadBuffer(out.ids, CL_TRUE, 0, ids.size() * 4, ids.data(), &after);
    CHECK(ids == index->query(qs, p).ids);
  }
}
