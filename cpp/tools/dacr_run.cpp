// Runs an exported package on recorded inputs, for the tests (tests/test_cpp.py) and for checking a package by hand:
//
//   dacr_run info  PACKAGE [--module M] [--robot NAME] [--joints a,b,...]   the metadata, after the checks
//   dacr_run run   PACKAGE --batch B --out PREFIX IN0.bin [IN1.bin ...]
//       inputs: B rows each, raw in the package's dtype; writes PREFIX.<k>.bin (the batch call, the package's dtype)
//       and PREFIX.<k>.rows.bin (the plain-buffer call of the module's class, row by row, float64)
//   dacr_run loop  PACKAGE --steps K --out PREFIX IN0.bin [IN1.bin ...]
//       a closed loop at batch 1 through the module's class (ForwardKinematics, …, WholeBodyStep): an input named
//       like an output (the whole-body step's q, a hardware model's state) is fed back from it after every tick and
//       its file holds its start (one row); every other input's file holds K rows; float64 throughout; writes
//       PREFIX.<k>.bin (K rows of output k)
//   dacr_run rrc   JACOBIAN --steps K --out OUT.bin Q0.bin TARGETS.bin
//       the resolved-rate controller for K ticks from Q0 (float64, N) with TARGETS (float64, K × 6: target and
//       feedforward); writes the commands (K × N float64)
// Errors: one line on stderr, exit status 1.
#include <cstring>
#include <fstream>
#include <functional>
#include <memory>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/Parallel.h>

#include "dacr/controllers.h"

namespace {

std::vector<char> read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  if (!in) throw std::runtime_error(path + ": cannot read");
  std::vector<char> out(static_cast<size_t>(in.tellg()));
  in.seekg(0);
  in.read(out.data(), static_cast<std::streamsize>(out.size()));
  return out;
}

void write_file(const std::string& path, const void* data, size_t bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(static_cast<const char*>(data), static_cast<std::streamsize>(bytes));
  if (!out) throw std::runtime_error(path + ": cannot write");
}

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::string item;
  std::istringstream in(s);
  while (std::getline(in, item, ',')) out.push_back(item);
  return out;
}

std::vector<double> read_doubles(const std::string& path, size_t count) {
  auto raw = read_file(path);
  if (raw.size() != count * sizeof(double))
    throw std::runtime_error(path + ": " + std::to_string(raw.size()) + " bytes, expected " +
                             std::to_string(count) + " float64 values");
  std::vector<double> out(count);
  std::memcpy(out.data(), raw.data(), raw.size());
  return out;
}

// A package opened with the class of its kind (and so that class's load-time checks), called through it at batch 1.
struct Opened {
  std::shared_ptr<void> owner;
  dacr::Package* package = nullptr;
  std::function<void(const double* const*, double* const*)> call;
};

dacr::Package& package_of(dacr::Package& p) { return p; }
template <class M>
dacr::Package& package_of(M& m) { return m.package(); }

template <class M, class F>
Opened opened(std::shared_ptr<M> m, F f) {
  Opened o;
  o.package = &package_of(*m);
  o.call = [p = m.get(), f](const double* const* in, double* const* out) { f(*p, in, out); };
  o.owner = std::move(m);
  return o;
}

Opened open(const std::string& path, const std::string& module, const dacr::Expectations& expect) {
  const auto info = dacr::PackageInfo::read(path);
  const std::string kind = module.empty() ? info.module : module;
  using In = const double* const*;
  using Out = double* const*;
  if (info.task == "fk" && kind == "fk")
    return opened(std::make_shared<dacr::ForwardKinematics>(path, expect),
                  [](dacr::ForwardKinematics& m, In in, Out out) { m.pose(in[0], out[0]); });
  if (info.task == "fk" && kind == "jacobian")
    return opened(std::make_shared<dacr::Jacobian>(path, expect),
                  [](dacr::Jacobian& m, In in, Out out) { m.evaluate(in[0], out[0], out[1], out[2]); });
  if (info.task == "ik")
    return opened(std::make_shared<dacr::InverseKinematics>(path, expect),
                  [](dacr::InverseKinematics& m, In in, Out out) { m.joints(in[0], out[0]); });
  if (info.task == "ik_refinement")
    return opened(std::make_shared<dacr::IKRefinement>(path, expect),
                  [](dacr::IKRefinement& m, In in, Out out) { m.refine(in[0], in[1], out[0], out[1], out[2]); });
  if (info.task == "hardware_fk")
    return opened(std::make_shared<dacr::HardwareModule>(path, kind, expect),
                  [](dacr::HardwareModule& m, In in, Out out) { m.call(in, out); });
  if (info.task == "whole_body_control")
    return opened(std::make_shared<dacr::WholeBodyStep>(path, expect),
                  [](dacr::WholeBodyStep& m, In in, Out out) { m.step(in[0], in[1], in[2], out[0]); });
  return opened(std::make_shared<dacr::Package>(path, module, "", expect),
                [](dacr::Package& m, In in, Out out) { m.call(in, out); });
}

}  // namespace

int main(int argc, char** argv) {
  try {
    if (argc < 3) throw std::runtime_error("usage: dacr_run info|run|loop|rrc PACKAGE ... (see tools/dacr_run.cpp)");
    const std::string mode = argv[1], path = argv[2];
    std::string module, out;
    long batch = 1, steps = 0;
    dacr::Expectations expect;
    std::vector<std::string> files;
    for (int i = 3; i < argc; ++i) {
      const std::string a = argv[i];
      auto value = [&]() -> std::string {
        if (i + 1 >= argc) throw std::runtime_error(a + " needs a value");
        return argv[++i];
      };
      if (a == "--module") module = value();
      else if (a == "--robot") expect.robot = value();
      else if (a == "--joints") expect.joint_names = split(value());
      else if (a == "--batch") batch = std::stol(value());
      else if (a == "--steps") steps = std::stol(value());
      else if (a == "--out") out = value();
      else files.push_back(a);
    }
    at::set_num_threads(1);
    if (mode == "info") {
      dacr::Package p(path, module, "", expect);
      std::cout << "module " << p.info().module << "\ntask " << p.info().task << "\n";
      for (const auto& [k, v] : p.info().raw) std::cout << k << " " << v << "\n";
      return 0;
    }
    if (mode == "run") {
      auto m = open(path, module, expect);
      dacr::Package& p = *m.package;
      const auto& info = p.info();
      if (files.size() != info.inputs.size())
        throw std::runtime_error("expected " + std::to_string(info.inputs.size()) + " input files");
      std::vector<at::Tensor> inputs;
      std::vector<std::vector<char>> raw;
      for (size_t i = 0; i < files.size(); ++i) {
        raw.push_back(read_file(files[i]));
        std::vector<int64_t> shape{batch};
        shape.insert(shape.end(), info.inputs[i].shape.begin(), info.inputs[i].shape.end());
        auto t = at::empty(shape, at::TensorOptions().dtype(p.dtype()));
        if (raw.back().size() != size_t(t.nbytes()))
          throw std::runtime_error(files[i] + ": " + std::to_string(raw.back().size()) + " bytes, expected " +
                                   std::to_string(t.nbytes()));
        std::memcpy(t.data_ptr(), raw.back().data(), t.nbytes());
        inputs.push_back(t);
      }
      auto outs = p.run(inputs);
      for (size_t k = 0; k < outs.size(); ++k)
        write_file(out + "." + std::to_string(k) + ".bin", outs[k].contiguous().const_data_ptr(), outs[k].nbytes());
      // the plain-buffer API, row by row
      std::vector<std::vector<double>> in64, out64(outs.size());
      for (auto& t : inputs) {
        auto d = t.to(at::kDouble).contiguous();
        in64.emplace_back(d.const_data_ptr<double>(), d.const_data_ptr<double>() + d.numel());
      }
      for (size_t k = 0; k < outs.size(); ++k) out64[k].resize(size_t(batch * info.outputs[k].numel()));
      std::vector<const double*> ip(inputs.size());
      std::vector<double*> op(outs.size());
      for (long b = 0; b < batch; ++b) {
        for (size_t i = 0; i < inputs.size(); ++i) ip[i] = in64[i].data() + b * info.inputs[i].numel();
        for (size_t k = 0; k < outs.size(); ++k) op[k] = out64[k].data() + b * info.outputs[k].numel();
        m.call(ip.data(), op.data());
      }
      for (size_t k = 0; k < outs.size(); ++k)
        write_file(out + "." + std::to_string(k) + ".rows.bin", out64[k].data(), out64[k].size() * sizeof(double));
      return 0;
    }
    if (mode == "loop") {
      auto m = open(path, module, expect);
      const auto& info = m.package->info();
      if (files.size() != info.inputs.size())
        throw std::runtime_error("expected " + std::to_string(info.inputs.size()) + " input files");
      const size_t ni = info.inputs.size(), no = info.outputs.size(), k_steps = size_t(steps);
      std::vector<int> fed(ni, -1);
      std::vector<std::vector<double>> ins(ni), outs(no);
      for (size_t i = 0; i < ni; ++i) {
        for (size_t j = 0; j < no; ++j)
          if (info.outputs[j].name == info.inputs[i].name) fed[i] = int(j);
        ins[i] = read_doubles(files[i], size_t(info.inputs[i].numel()) * (fed[i] >= 0 ? 1 : k_steps));
      }
      for (size_t j = 0; j < no; ++j) outs[j].resize(k_steps * size_t(info.outputs[j].numel()));
      std::vector<const double*> ip(ni);
      std::vector<double*> op(no);
      for (size_t k = 0; k < k_steps; ++k) {
        for (size_t i = 0; i < ni; ++i) ip[i] = fed[i] >= 0 ? ins[i].data() : ins[i].data() + k * info.inputs[i].numel();
        for (size_t j = 0; j < no; ++j) op[j] = outs[j].data() + k * info.outputs[j].numel();
        m.call(ip.data(), op.data());
        for (size_t i = 0; i < ni; ++i)
          if (fed[i] >= 0) std::memcpy(ins[i].data(), op[fed[i]], ins[i].size() * sizeof(double));
      }
      for (size_t j = 0; j < no; ++j)
        write_file(out + "." + std::to_string(j) + ".bin", outs[j].data(), outs[j].size() * sizeof(double));
      return 0;
    }
    if (mode == "rrc") {
      dacr::Jacobian jac(path, expect);
      dacr::ResolvedRateController ctrl(jac);
      if (files.size() != 2) throw std::runtime_error("rrc: expected Q0.bin and TARGETS.bin");
      auto q0 = read_file(files[0]), targets = read_file(files[1]);
      if (q0.size() != ctrl.state.size() * sizeof(double) || targets.size() != size_t(steps) * 6 * sizeof(double))
        throw std::runtime_error("rrc: Q0 must hold N doubles and TARGETS steps × 6 doubles");
      std::memcpy(ctrl.state.data(), q0.data(), q0.size());
      ctrl.on_activate();
      std::vector<double> commands;
      for (long k = 0; k < steps; ++k) {
        std::memcpy(ctrl.reference.data(), targets.data() + k * 6 * sizeof(double), 6 * sizeof(double));
        if (ctrl.update(0.001 * double(k), 0.001) != dacr::ReturnType::OK)
          throw std::runtime_error("rrc: update failed at tick " + std::to_string(k));
        commands.insert(commands.end(), ctrl.command.begin(), ctrl.command.end());
        ctrl.state = ctrl.command;
      }
      write_file(out, commands.data(), commands.size() * sizeof(double));
      return 0;
    }
    throw std::runtime_error("unknown mode " + mode + " (info, run, loop, rrc)");
  } catch (const std::exception& err) {
    std::cerr << "error: " << err.what() << "\n";
    return 1;
  }
}
