// Real-time helpers (include/dacr/realtime.h).
#include "dacr/realtime.h"

#include <pthread.h>
#include <sched.h>
#include <sys/prctl.h>
#include <sys/mman.h>
#include <unistd.h>
#include <time.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstring>

#include <c10/core/CPUAllocator.h>

namespace dacr {

RealtimeSetup prepare_realtime_thread(int cpu, int priority) {
  RealtimeSetup out;
  cpu_set_t set;
  CPU_ZERO(&set);
  CPU_SET(cpu, &set);
  int err = pthread_setaffinity_np(pthread_self(), sizeof(set), &set);
  out.pinned = err == 0;
  out.pinning = err == 0 ? "pinned to CPU " + std::to_string(cpu) : std::string("not pinned: ") + std::strerror(err);
  sched_param param{};
  param.sched_priority = priority;
  err = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param);
  out.fifo = err == 0;
  out.scheduler = err == 0 ? "SCHED_FIFO priority " + std::to_string(priority)
                           : std::string("SCHED_OTHER (SCHED_FIFO refused: ") + std::strerror(err) + ")";
  prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);   // only matters for SCHED_OTHER (real-time threads have none)
  out.locked = mlockall(MCL_CURRENT | MCL_FUTURE) == 0;
  out.memory = out.locked ? "mlockall" : std::string("not locked (mlockall: ") + std::strerror(errno) + ")";
  out.malloc = malloc_setting();
  return out;
}

void reexec_with_malloc_tunables(char** argv) {
  const char* now = std::getenv("GLIBC_TUNABLES");
  const std::string have = now ? now : "";
  if (have.find("glibc.malloc.tcache_count=") != std::string::npos) return;   // set (by us, or by the caller)
  const std::string want = have.empty() ? kMallocTunables : have + ":" + kMallocTunables;
  if (setenv("GLIBC_TUNABLES", want.c_str(), 1) != 0) return;
  execv("/proc/self/exe", argv);   // returns only on failure: carry on with glibc's defaults
  if (now) setenv("GLIBC_TUNABLES", now, 1); else unsetenv("GLIBC_TUNABLES");
}

std::string malloc_setting() {
  const char* now = std::getenv("GLIBC_TUNABLES");
  return now && *now ? std::string("GLIBC_TUNABLES=") + now : "glibc defaults";
}

int64_t now_ns() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return int64_t(ts.tv_sec) * 1000000000 + ts.tv_nsec;
}

void sleep_until_ns(int64_t t_ns, int64_t spin_ns) {
  const int64_t wake = t_ns - std::max<int64_t>(spin_ns, 0);
  timespec ts{static_cast<time_t>(wake / 1000000000), static_cast<long>(wake % 1000000000)};
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
  while (spin_ns > 0 && now_ns() < t_ns) {
  }
}

LatencySummary summarize(std::vector<int64_t> s) {
  LatencySummary out;
  out.count = static_cast<int64_t>(s.size());
  if (s.empty()) return out;
  std::sort(s.begin(), s.end());
  auto at = [&](double q) {  // linear interpolation between order statistics, as numpy.percentile
    const double pos = q * double(s.size() - 1);
    const size_t lo = static_cast<size_t>(std::floor(pos)), hi = std::min(lo + 1, s.size() - 1);
    return (double(s[lo]) + (pos - double(lo)) * double(s[hi] - s[lo])) / 1e3;
  };
  double sum = 0;
  for (auto v : s) sum += double(v);
  out.p50_us = at(0.5);
  out.p99_us = at(0.99);
  out.max_us = double(s.back()) / 1e3;
  out.mean_us = sum / double(s.size()) / 1e3;
  return out;
}

namespace {
std::atomic<int64_t> g_tensor_allocations{0};

struct CountingAllocator final : c10::Allocator {
  c10::Allocator* base;
  explicit CountingAllocator(c10::Allocator* b) : base(b) {}
  c10::DataPtr allocate(size_t n) override {
    g_tensor_allocations.fetch_add(1, std::memory_order_relaxed);
    return base->allocate(n);
  }
  c10::DeleterFnPtr raw_deleter() const override { return base->raw_deleter(); }
  void copy_data(void* dest, const void* src, std::size_t count) const override {
    default_copy_data(dest, src, count);
  }
};
}  // namespace

void install_counting_allocator() {
  static CountingAllocator allocator(c10::GetCPUAllocator());
  c10::SetCPUAllocator(&allocator, /*priority=*/100);
}

int64_t tensor_allocations() { return g_tensor_allocations.load(std::memory_order_relaxed); }

}  // namespace dacr
