// What a real-time loop needs around the controllers: pinning, the scheduler, a periodic clock, latency figures,
// and counting the allocations of the loop (docs/cpp.md, "Real-time loop").
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace dacr {

// Outcome of preparing the calling thread for real-time work; each field says what happened in words.
struct RealtimeSetup {
  bool pinned = false, fifo = false, locked = false;
  std::string pinning, scheduler, memory, malloc;
};

// glibc's malloc keeps at most 7 freed blocks of each size in its per-thread cache (tcache, the fast path); a
// package call allocates and frees hundreds of tensor handles of the same few sizes, so the rest went through the
// slower bins (with consolidations) on every call. kMallocTunables raises the cache to 64 blocks per size (measured
// on a loaded 2-core machine: the IK refinement's p50 −10 to −15 %, the Jacobian's within the spread of the machine;
// 512 or 4096 blocks doubled the Jacobian's p99, docs/history/cpp.md). glibc
// reads it only from the environment at process start: set GLIBC_TUNABLES in the controller's environment, or call
// this at the top of main(): it re-executes the program with it added (returns if it is set, or exec failed).
constexpr const char* kMallocTunables = "glibc.malloc.tcache_count=64";
void reexec_with_malloc_tunables(char** argv);
// GLIBC_TUNABLES as this process has it, in words ("glibc defaults" when unset).
std::string malloc_setting();

// Pin the calling thread to `cpu` (pthread affinity), ask for SCHED_FIFO at `priority` (needs CAP_SYS_NICE or an
// rtprio limit; else it stays SCHED_OTHER and says so), set its timer slack to 1 ns (SCHED_OTHER threads get 50 µs
// by default) and lock the process memory (mlockall, if permitted).
RealtimeSetup prepare_realtime_thread(int cpu, int priority);

// Monotonic clock [ns].
int64_t now_ns();
// Sleep until the absolute monotonic time `t_ns` (clock_nanosleep, TIMER_ABSTIME); with `spin_ns` > 0, sleep until
// `spin_ns` before it and spin on the clock for the rest (the wake-up's latency is paid before the deadline, not
// after it; the thread keeps its CPU for `spin_ns` per tick).
void sleep_until_ns(int64_t t_ns, int64_t spin_ns = 0);

// p50 / p99 / max / mean of samples [ns], reported in µs.
struct LatencySummary {
  double p50_us = 0, p99_us = 0, max_us = 0, mean_us = 0;
  int64_t count = 0;
};
LatencySummary summarize(std::vector<int64_t> samples_ns);

// Counts of tensor storages allocated through libtorch's CPU allocator since `install_counting_allocator()`
// (a wrapper around the default allocator, c10::SetCPUAllocator).
void install_counting_allocator();
int64_t tensor_allocations();

}  // namespace dacr
