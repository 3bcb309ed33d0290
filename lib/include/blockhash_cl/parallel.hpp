// The one way to split host work over threads (builds, host references, FLANN's queries, several
// devices, the renderer): every worker is joined before return, and the first exception a worker
// throws is rethrown in the caller (none ends the process). A thread the OS cannot start (a
// cgroup's pids.max, ulimit -u or -v: std::thread throws std::system_error) never aborts: the work
// runs on the threads that did start and the caller (issue 38: the throw from emplace_back
// destroyed joinable threads, std::terminate). Three shapes:
//   parallel_for     contiguous ranges, one per thread;
//   parallel_chunks  fixed chunks handed out in turn (chunking independent of the thread count);
//   parallel_tasks   one thread per task (e.g. per device).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <exception>
#include <mutex>
#include <system_error>
#include <thread>
#include <vector>

#if defined(__linux__)
#include <sched.h>
#endif

namespace bhcl::detail {

// The CPUs this process may run on: its affinity mask (taskset, cgroup cpusets, a batch
// scheduler's binding) where the OS tells it, else the hardware threads. hardware_concurrency()
// counts every CPU of the machine, so a process confined to 2 of 64 cores would start 64
// threads and oversubscribe the 2 it has.
inline unsigned available_cpus() {
#if defined(__linux__) && defined(CPU_COUNT)
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof(set), &set) == 0) {
    const int c = CPU_COUNT(&set);
    if (c > 0) return static_cast<unsigned>(c);
  }
#endif
  return std::max(1u, std::thread::hardware_concurrency());
}

inline unsigned default_threads() { return available_cpus(); }

// Starts thread i = 0 .. count - 1 running make(i) into pool; stops at the first the OS refuses
// and returns how many started (the caller then does the rest itself).
template <typename Make>
std::size_t start_threads(std::vector<std::thread>& pool, std::size_t count, Make&& make) {
  pool.reserve(count);  // emplace_back then never reallocates (no bad_alloc after a start)
  for (std::size_t i = 0; i < count; ++i) {
    try {
      pool.emplace_back(make(i));
    } catch (const std::system_error&) {
      return i;
    }
  }
  return count;
}

// Calls fn(begin, end) on [0, n) cut into `threads` contiguous ranges (0: all hardware threads);
// small n runs inline.
template <typename Fn>
void parallel_for(std::size_t n, Fn&& fn, unsigned threads = 0, std::size_t min_per_thread = 4096) {
  if (threads == 0) threads = default_threads();
  std::size_t t = std::min<std::size_t>(threads, std::max<std::size_t>(1, n / std::max<std::size_t>(1, min_per_thread)));
  if (t <= 1) {
    if (n) fn(std::size_t(0), n);
    return;
  }
  std::vector<std::thread> pool;
  std::exception_ptr error;
  std::mutex m;
  const std::size_t per = (n + t - 1) / t, ranges = (n + per - 1) / per;
  auto range = [&](std::size_t i) {
    try {
      fn(i * per, std::min(n, i * per + per));
    } catch (...) {
      std::lock_guard<std::mutex> lock(m);
      if (!error) error = std::current_exception();
    }
  };
  // Range 0 is the caller's; those whose thread the OS refused run after it, on the caller too.
  const std::size_t started = start_threads(pool, ranges - 1, [&](std::size_t i) {
    return std::thread([&range, i] { range(i + 1); });
  });
  range(0);
  for (std::size_t i = started + 1; i < ranges; ++i) range(i);
  for (auto& th : pool) th.join();
  if (error) std::rethrow_exception(error);
}

// fn(chunk, begin, end) for chunks [c*chunk, min(n, (c+1)*chunk)) handed out in turn to `threads`
// threads (0: all hardware threads; the caller is one of them). After a throw no new chunk starts;
// the first exception is rethrown here.
template <typename Fn>
void parallel_chunks(std::size_t n, std::size_t chunk, unsigned threads, Fn&& fn) {
  if (n == 0) return;
  if (threads == 0) threads = default_threads();
  const std::size_t chunks = (n + chunk - 1) / chunk;
  std::atomic<std::size_t> next{0};
  std::exception_ptr error;
  std::mutex m;
  auto work = [&] {
    for (;;) {
      const std::size_t c = next.fetch_add(1);
      if (c >= chunks) return;
      try {
        fn(c, c * chunk, std::min(n, (c + 1) * chunk));
      } catch (...) {
        std::lock_guard<std::mutex> lock(m);
        if (!error) error = std::current_exception();
        next = chunks;
      }
    }
  };
  const std::size_t t = std::min<std::size_t>(threads, chunks);
  std::vector<std::thread> pool;
  start_threads(pool, t - 1, [&](std::size_t) { return std::thread(work); });  // the chunks go to those started
  work();
  for (auto& th : pool) th.join();
  if (error) std::rethrow_exception(error);
}

// fn(i) for i in [0, tasks), each on its own thread; all are joined, then the exception of the
// lowest failing i is rethrown.
template <typename Fn>
void parallel_tasks(std::size_t tasks, Fn&& fn) {
  std::vector<std::exception_ptr> errors(tasks);
  std::vector<std::thread> pool;
  auto task = [&](std::size_t i) {
    try {
      fn(i);
    } catch (...) {
      errors[i] = std::current_exception();
    }
  };
  // Tasks whose thread the OS refused run in the caller, one after another.
  const std::size_t started = start_threads(pool, tasks, [&](std::size_t i) { return std::thread([&task, i] { task(i); }); });
  for (std::size_t i = started; i < tasks; ++i) task(i);
  for (auto& th : pool) th.join();
  for (auto& e : errors)
    if (e) std::rethrow_exception(e);
}

}  // namespace bhcl::detail
