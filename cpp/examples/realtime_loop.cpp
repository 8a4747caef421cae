// Real-time loops on dacr_learn's exported modules (docs/cpp.md):
//
//   dacr_rt rrc   --jacobian J.aoti.pt2 [--seconds 10 --rate 1000 --cpu 1 --radius 0.005 --lap 2 --spin-us 50
//                 --warmup 200]
//       resolved-rate control of the robot (the plant: its commanded joints) along a circle of `radius` [m]
//       around the start tip, one lap per `lap` seconds
//   dacr_rt ik    --refine R.aoti.pt2 --targets T.bin [--seconds 10 --rate 1000 --cpu 1 --spin-us 50 --warmup 200]
//       warm-started IK refinement tracking a moving target; T.bin: float64, the start joints (N), then poses
//       (T × 16, row major), one per tick (cycled)
//   dacr_rt bench [--fk F] [--jacobian J] [--refine R --targets T.bin] [--calls 2000 --rounds 5 --cpu 1]
//       back-to-back batch-1 calls of each module, interleaved round by round (no sleeping)
//
// Each prints one JSON object: per-tick latency p50 / p99 / max [µs] (the controller's update: module call and
// control maths), wake-up lateness, overruns (a tick that ends after its period), allocations per tick (operator
// new, and libtorch tensor storages), and how the thread was set up (pinning, scheduler, memory locking).
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <algorithm>
#include <fstream>
#include <functional>
#include <memory>
#include <iostream>
#include <map>
#include <new>
#include <string>
#include <vector>

#include <ATen/Parallel.h>

#include "dacr/controllers.h"
#include "dacr/realtime.h"

// Every operator new of the process counted (the loop's own code allocates nothing; the module call does).
static std::atomic<long long> g_news{0};
void* operator new(std::size_t n) {
  g_news.fetch_add(1, std::memory_order_relaxed);
  if (void* p = std::malloc(n ? n : 1)) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n) { return operator new(n); }
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }

namespace {

using Args = std::map<std::string, std::string>;

std::string arg(const Args& a, const std::string& key, const std::string& fallback = "") {
  auto it = a.find(key);
  if (it != a.end()) return it->second;
  if (fallback.empty()) throw std::runtime_error("missing --" + key);
  return fallback;
}

std::string json_summary(const char* name, const dacr::LatencySummary& s) {
  char buf[256];
  std::snprintf(buf, sizeof buf, "\"%s\": {\"p50_us\": %.2f, \"p99_us\": %.2f, \"max_us\": %.2f, \"mean_us\": %.2f, "
                "\"count\": %lld}", name, s.p50_us, s.p99_us, s.max_us, s.mean_us, (long long)s.count);
  return buf;
}

std::string json_setup(const dacr::RealtimeSetup& r) {
  return "\"pinning\": \"" + r.pinning + "\", \"scheduler\": \"" + r.scheduler + "\", \"memory\": \"" + r.memory +
         "\", \"malloc\": \"" + r.malloc + "\"";
}

std::vector<double> read_doubles(const std::string& path) {
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  if (!in) throw std::runtime_error(path + ": cannot read the targets file");
  const auto bytes = static_cast<size_t>(in.tellg());
  std::vector<double> out(bytes / sizeof(double));
  in.seekg(0);
  in.read(reinterpret_cast<char*>(out.data()), static_cast<std::streamsize>(out.size() * sizeof(double)));
  return out;
}

// Loop timing: ticks are released at absolute deadlines (clock_nanosleep, TIMER_ABSTIME), the last `spin_us` before
// each by spinning on the clock; the first `warmup` ticks run the same way and are not counted (caches, the
// allocator's free lists and the branch predictors settle).
struct Timing {
  double seconds = 10, rate = 1000, spin_us = 50;
  long warmup = 200;
};

Timing timing(const Args& a) {
  return {std::stod(arg(a, "seconds", "10")), std::stod(arg(a, "rate", "1000")), std::stod(arg(a, "spin-us", "50")),
          std::stol(arg(a, "warmup", "200"))};
}

// The periodic loop: `tick(k, t, dt)` at `rate` Hz, `warmup` ticks then `seconds` of counted ones; returns its JSON
// fields.
template <class Tick>
std::string periodic(const Timing& tm, Tick&& tick) {
  const int64_t period = static_cast<int64_t>(std::llround(1e9 / tm.rate));
  const int64_t spin = static_cast<int64_t>(std::llround(tm.spin_us * 1e3));
  const long ticks = std::lround(tm.seconds * tm.rate), warmup = std::max(0L, tm.warmup);
  std::vector<int64_t> busy, late;
  busy.reserve(ticks);
  late.reserve(ticks);
  long overruns = 0, failed = 0;
  long long news0 = 0;
  int64_t tensors0 = 0;
  int64_t next = dacr::now_ns() + period;
  const int64_t start = next;
  for (long k = 0; k < warmup + ticks; ++k) {
    if (k == warmup) {
      news0 = g_news.load();
      tensors0 = dacr::tensor_allocations();
    }
    dacr::sleep_until_ns(next, spin);
    const int64_t t0 = dacr::now_ns();
    const bool ok = tick(k, double(next - start) * 1e-9, double(period) * 1e-9);
    const int64_t t1 = dacr::now_ns();
    if (k >= warmup) {
      failed += !ok;
      busy.push_back(t1 - t0);
      late.push_back(t0 - next);
      if (t1 > next + period) ++overruns;
    }
    next += period;
    while (next < t1) next += period;  // skip the periods an overrun ate
  }
  const double news = double(g_news.load() - news0) / double(ticks);
  const double tensors = double(dacr::tensor_allocations() - tensors0) / double(ticks);
  char buf[320];
  std::snprintf(buf, sizeof buf, "\"ticks\": %ld, \"overruns\": %ld, \"overrun_fraction\": %.6f, \"failed_ticks\": %ld, "
                "\"new_per_tick\": %.2f, \"tensor_allocations_per_tick\": %.2f, \"warmup_ticks\": %ld, \"spin_us\": %.0f, ",
                ticks, overruns, double(overruns) / double(ticks), failed, news, tensors, warmup, tm.spin_us);
  return std::string(buf) + json_summary("tick", dacr::summarize(busy)) + ", " +
         json_summary("wakeup_late", dacr::summarize(late));
}

int run_rrc(const Args& a, const dacr::RealtimeSetup& setup) {
  dacr::Jacobian jac(arg(a, "jacobian"));
  dacr::ResolvedRateController ctrl(jac);
  const auto& info = jac.package().info();
  // start: the straight robot (the decoder's value at f = the middle of each box, ρ = 0)
  std::vector<double> f(jac.num_features(), 0.0), q(jac.num_joints());
  for (int k = 0; k < jac.num_features(); ++k)
    if (std::isfinite(info.feature_lower[k])) f[k] = 0.5 * (info.feature_lower[k] + info.feature_upper[k]);
  for (int j = 0; j < jac.num_joints(); ++j) {
    q[j] = info.decoder_offset[j];
    for (int k = 0; k < jac.num_features(); ++k) q[j] += info.decoder_matrix[j * jac.num_features() + k] * f[k];
  }
  std::vector<double> pose(16);
  jac.evaluate(q.data(), pose.data(), nullptr, nullptr);
  const double c[3] = {pose[3], pose[7], pose[11]};
  const double radius = std::stod(arg(a, "radius", "0.005")), lap = std::stod(arg(a, "lap", "2"));
  ctrl.state = q;
  ctrl.on_activate();
  std::vector<double> err;
  err.reserve(100000);
  auto target = [&](double t, double* p) {  // a circle in the base x-y plane through the start tip
    const double w = 2 * M_PI / lap, s = std::sin(w * t), co = std::cos(w * t);
    p[0] = c[0] + radius * (co - 1);
    p[1] = c[1] + radius * s;
    p[2] = c[2];
  };
  const Timing tm = timing(a);
  std::string loop = periodic(tm, [&](long, double t, double dt) {
    double p[3], pn[3];
    target(t, p);
    target(t + dt, pn);
    for (int i = 0; i < 3; ++i) {
      ctrl.reference[i] = p[i];
      ctrl.reference[3 + i] = pn[i] - p[i];
    }
    const bool ok = ctrl.update(t, dt) == dacr::ReturnType::OK;
    ctrl.state = ctrl.command;  // the plant: the commanded joints are reached within the tick
    if (err.size() < err.capacity()) err.push_back(ctrl.position_error());
    return ok;
  });
  double rms = 0, mx = 0;
  const size_t skip = std::min(err.size(), size_t(tm.rate * 0.5));  // settling: the first 0.5 s
  for (size_t i = skip; i < err.size(); ++i) {
    rms += err[i] * err[i];
    mx = std::max(mx, err[i]);
  }
  rms = std::sqrt(rms / double(std::max<size_t>(1, err.size() - skip)));
  std::printf("{\"mode\": \"rrc\", \"package\": \"%s\", %s, %s, \"tracking_rms_m\": %.3e, \"tracking_max_m\": %.3e}\n",
              info.path.c_str(), loop.c_str(), json_setup(setup).c_str(), rms, mx);
  return 0;
}

int run_ik(const Args& a, const dacr::RealtimeSetup& setup) {
  dacr::IKRefinement refine(arg(a, "refine"));
  dacr::IKTrackingController ctrl(refine);
  const auto data = read_doubles(arg(a, "targets"));
  const size_t n = refine.num_joints(), width = ctrl.reference.size();
  if (data.size() < n + width || (data.size() - n) % width)
    throw std::runtime_error("targets file: expected N start joints and then whole targets");
  const size_t count = (data.size() - n) / width;
  ctrl.state.assign(data.begin(), data.begin() + long(n));
  ctrl.on_activate();
  std::vector<double> perr, rerr;
  perr.reserve(100000);
  rerr.reserve(100000);
  std::string loop = periodic(timing(a), [&](long k, double t, double dt) {
    const double* target = data.data() + n + (size_t(k) % count) * width;
    for (size_t i = 0; i < width; ++i) ctrl.reference[i] = target[i];
    const bool ok = ctrl.update(t, dt) == dacr::ReturnType::OK;
    if (perr.size() < perr.capacity()) {
      perr.push_back(ctrl.position_error());
      rerr.push_back(ctrl.rotation_error());
    }
    return ok;
  });
  std::sort(perr.begin(), perr.end());
  std::sort(rerr.begin(), rerr.end());
  std::printf("{\"mode\": \"ik\", \"package\": \"%s\", %s, %s, \"pos_err_median_m\": %.3e, \"pos_err_max_m\": %.3e, "
              "\"rot_err_max_rad\": %.3e}\n", refine.package().info().path.c_str(), loop.c_str(),
              json_setup(setup).c_str(), perr[perr.size() / 2], perr.back(), rerr.back());
  return 0;
}

int run_bench(const Args& a, const dacr::RealtimeSetup& setup) {
  const int calls = std::stoi(arg(a, "calls", "2000")), rounds = std::stoi(arg(a, "rounds", "5"));
  struct Row {
    std::string name;
    std::function<void()> fn;
    std::vector<int64_t> ns;
    long long news = 0;  // operator new during the timed calls
  };
  std::vector<Row> rows;
  std::unique_ptr<dacr::ForwardKinematics> fk;
  std::unique_ptr<dacr::Jacobian> jac;
  std::unique_ptr<dacr::IKRefinement> refine;
  std::vector<double> q, pose(16), jf, jq, target, q0, qo(64);
  double pe, re;
  if (a.count("fk")) {
    fk = std::make_unique<dacr::ForwardKinematics>(a.at("fk"));
    q.assign(fk->num_joints(), 0.01);
    rows.push_back({"fk", [&] { fk->pose(q.data(), pose.data()); }, {}});
  }
  if (a.count("jacobian")) {
    jac = std::make_unique<dacr::Jacobian>(a.at("jacobian"));
    q.assign(jac->num_joints(), 0.01);
    jf.assign(6 * jac->num_features(), 0);
    jq.assign(6 * jac->num_joints(), 0);
    rows.push_back({"jacobian", [&] { jac->evaluate(q.data(), pose.data(), jf.data(), jq.data()); }, {}});
  }
  if (a.count("refine")) {
    refine = std::make_unique<dacr::IKRefinement>(a.at("refine"));
    const auto data = read_doubles(arg(a, "targets"));
    const size_t n = refine->num_joints();
    q0.assign(data.begin(), data.begin() + long(n));
    target.assign(data.begin() + long(n), data.begin() + long(n) + 16);
    rows.push_back({"refine", [&] { refine->refine(target.data(), q0.data(), qo.data(), &pe, &re); }, {}});
  }
  for (auto& r : rows) {
    r.ns.reserve(size_t(calls) * rounds);
    for (int i = 0; i < 50; ++i) r.fn();
  }
  for (int round = 0; round < rounds; ++round)
    for (size_t i = 0; i < rows.size(); ++i) {
      auto& r = rows[round % 2 ? rows.size() - 1 - i : i];
      const long long news = g_news.load();
      for (int c = 0; c < calls; ++c) {
        const int64_t t0 = dacr::now_ns();
        r.fn();
        r.ns.push_back(dacr::now_ns() - t0);
      }
      r.news += g_news.load() - news;
    }
  std::string out = "{\"mode\": \"bench\", ", news = "\"new_per_call\": {";
  for (auto& r : rows) {
    out += json_summary(r.name.c_str(), dacr::summarize(r.ns)) + ", ";
    news += (news.size() > 17 ? ", \"" : "\"") + r.name + "\": " + std::to_string(r.news / (double(calls) * rounds));
  }
  out += news + "}, ";
  std::printf("%s%s}\n", out.c_str(), json_setup(setup).c_str());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  dacr::reexec_with_malloc_tunables(argv);  // a controller's environment (docs/cpp.md, "Real-time loop")
  if (argc < 2) {
    std::cerr << "usage: dacr_rt rrc|ik|bench --key value ... (see the top of cpp/examples/realtime_loop.cpp)\n";
    return 2;
  }
  Args a;
  for (int i = 2; i + 1 < argc; i += 2) {
    std::string key = argv[i];
    if (key.rfind("--", 0) != 0) {
      std::cerr << "expected --key value pairs, got " << key << "\n";
      return 2;
    }
    a[key.substr(2)] = argv[i + 1];
  }
  try {
    at::set_num_threads(1);  // batch-1 calls: intra-op threads only add contention
    dacr::install_counting_allocator();
    const auto setup = dacr::prepare_realtime_thread(std::stoi(arg(a, "cpu", "1")), std::stoi(arg(a, "priority", "80")));
    const std::string mode = argv[1];
    if (mode == "rrc") return run_rrc(a, setup);
    if (mode == "ik") return run_ik(a, setup);
    if (mode == "bench") return run_bench(a, setup);
    std::cerr << "unknown mode " << mode << " (rrc, ik, bench)\n";
    return 2;
  } catch (const std::exception& err) {
    std::cerr << "error: " << err.what() << "\n";
    return 1;
  }
}
