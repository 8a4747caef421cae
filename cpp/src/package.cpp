// Loading and checking dacr_learn's AOTInductor packages (include/dacr/package.h).
#include "dacr/package.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <sstream>

#include <ATen/core/Tensor.h>
#include <ATen/ops/zeros.h>
#include <torch/csrc/inductor/aoti_package/model_package_loader.h>
#include <torch/csrc/inductor/aoti_runner/model_container_runner.h>
#include <torch/headeronly/version.h>

namespace dacr {
namespace {

constexpr const char* kPrefix = "dacr_learn.";

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> out;
  if (s.empty()) return out;
  std::string item;
  std::istringstream in(s);
  while (std::getline(in, item, sep)) out.push_back(item);
  if (s.back() == sep) out.emplace_back();
  return out;
}

std::string join(const std::vector<std::string>& items) {
  std::string out;
  for (size_t i = 0; i < items.size(); ++i) out += (i ? "," : "") + items[i];
  return out;
}

// the first line of libtorch's message (its later lines are a C++ stack)
std::string first_line(const std::exception& err) {
  const std::string what = err.what();
  return what.substr(0, std::min(what.find('\n'), size_t(160)));
}

std::string shape_str(const std::vector<int64_t>& shape) {
  std::string out = "(";
  for (size_t i = 0; i < shape.size(); ++i) out += (i ? ", " : "") + std::to_string(shape[i]);
  return out + (shape.size() == 1 ? ",)" : ")");
}

void expect_size(const std::string& path, const std::string& what, size_t got, size_t want) {
  if (got != want)
    throw PackageError(path + ": metadata " + what + " has " + std::to_string(got) + " entries, expected " +
                       std::to_string(want));
}

struct Reader {
  const std::unordered_map<std::string, std::string>& raw;
  const std::string& path;

  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    throw PackageError(path + ": metadata entry " + kPrefix + key + " " + what);
  }
  bool has(const std::string& key) const { return raw.count(key) != 0; }
  const std::string& text(const std::string& key) const {
    auto it = raw.find(key);
    if (it == raw.end()) fail(key, "is missing; re-export the module with this version of dacr_learn");
    return it->second;
  }
  std::vector<double> numbers(const std::string& key, bool required = false) const {
    std::vector<double> out;
    if (!has(key)) {
      if (required) text(key);
      return out;
    }
    for (const auto& item : split(text(key), ',')) {
      char* end = nullptr;
      double v = std::strtod(item.c_str(), &end);
      if (item.empty() || *end != '\0') fail(key, "is not a list of numbers: '" + item + "'");
      out.push_back(v);
    }
    return out;
  }
  // a required list of `n` numbers
  std::vector<double> sized(const std::string& key, size_t n) const {
    auto out = numbers(key, true);
    expect_size(path, key, out.size(), n);
    return out;
  }
  std::vector<TensorSpec> tensors(const std::string& key) const {
    std::vector<TensorSpec> out;
    for (const auto& item : split(text(key), ',')) {
      auto colon = item.find(':');
      if (colon == std::string::npos) fail(key, "expected name:shape entries, got '" + item + "'");
      TensorSpec spec{item.substr(0, colon), {}};
      for (const auto& d : split(item.substr(colon + 1), 'x')) {
        char* end = nullptr;
        long v = std::strtol(d.c_str(), &end, 10);
        if (d.empty() || *end != '\0' || v < 1) fail(key, "has a malformed shape in '" + item + "'");
        spec.shape.push_back(v);
      }
      out.push_back(std::move(spec));
    }
    return out;
  }
};

// Copy a tensor into `dst` in row-major order, whatever its strides (outputs of a package need not be contiguous,
// e.g. a transposed Jacobian): no temporary tensor.
template <class T>
void copy_out(const at::Tensor& t, const T* src, double* dst) {
  const int64_t dims = t.dim(), n = t.numel();
  if (t.is_contiguous()) {
    for (int64_t k = 0; k < n; ++k) dst[k] = src[k];
    return;
  }
  const auto sizes = t.sizes();
  const auto strides = t.strides();
  for (int64_t k = 0; k < n; ++k) {
    int64_t rest = k, offset = 0;
    for (int64_t d = dims - 1; d >= 0; --d) {
      offset += (rest % sizes[d]) * strides[d];
      rest /= sizes[d];
    }
    dst[k] = src[offset];
  }
}

}  // namespace

int64_t TensorSpec::numel() const {
  int64_t n = 1;
  for (auto d : shape) n *= d;
  return n;
}

PackageInfo PackageInfo::parse(const std::unordered_map<std::string, std::string>& metadata, const std::string& path) {
  PackageInfo info;
  info.path = path;
  for (const auto& [k, v] : metadata)
    if (k.rfind(kPrefix, 0) == 0) info.raw[k.substr(std::string(kPrefix).size())] = v;
  if (info.raw.empty())
    throw PackageError(path + ": no dacr_learn metadata in the package (written by an older dacr_learn, or not by "
                       "dacr_learn); re-export it with `python -m dacr_learn.export` or `python -m "
                       "dacr_learn.ik.exported`");
  Reader r{info.raw, path};
  info.format = r.text("format");
  if (info.format != kFormat)
    throw PackageError(path + ": package format '" + info.format + "', this library reads '" + kFormat +
                       "'; re-export the module");
  info.module = r.text("module");
  info.task = r.text("task");
  info.dtype = r.text("dtype");
  info.robot = r.text("robot");
  info.torch_version = r.text("torch_version");
  info.inputs = r.tensors("inputs");
  info.outputs = r.tensors("outputs");
  info.joint_names = split(r.text("joint_names"), ',');
  info.joint_units = split(r.text("joint_units"), ',');
  expect_size(path, "joint_units", info.joint_units.size(), info.joint_names.size());
  if (info.task == "whole_body_control") {
    info.arm_joints = std::atoi(r.text("arm_joints").c_str());
    if (info.arm_joints < 1 || size_t(info.arm_joints) >= info.joint_names.size())
      r.fail("arm_joints", "must count 1 … " + std::to_string(info.joint_names.size() - 1) + " of the joints");
    const size_t a = size_t(info.arm_joints);
    info.arm_lower = r.sized("arm_lower", a);
    info.arm_upper = r.sized("arm_upper", a);
    info.arm_velocity = r.sized("arm_velocity", a);
    info.mount = r.sized("mount", 16);
    for (size_t i = 0; i < a; ++i)
      if (!(info.arm_lower[i] < info.arm_upper[i]) || !(info.arm_velocity[i] > 0))
        r.fail("arm_lower", "of joint " + info.joint_names[i] + ": expected lower < upper and a velocity > 0");
    info.port_centre = r.numbers("port_centre");
    if (!info.port_centre.empty()) {
      expect_size(path, "port_centre", info.port_centre.size(), 3);
      info.port_radius = r.sized("port_radius", 1)[0];
    }
    auto dt = r.numbers("dt");
    info.dt = dt.empty() ? 0.0 : dt[0];
  }
  if (info.task != "hardware_fk") {
    info.feature_names = split(r.text("feature_names"), ',');
    // the robot's joints: the whole of q, or what follows the arm's
    const size_t d = info.feature_names.size(), n = info.joint_names.size() - size_t(info.arm_joints);
    info.feature_lower = r.sized("feature_lower", d);
    info.feature_upper = r.sized("feature_upper", d);
    info.feature_scale = r.sized("feature_scale", d);
    info.feature_disk_radius = r.numbers("feature_disk_radius", true);
    for (const auto& pair : split(r.text("feature_disks"), ',')) {
      std::istringstream in(pair);
      std::array<int, 2> ij{-1, -1};
      in >> ij[0] >> ij[1];
      if (in.fail() || ij[0] < 0 || ij[1] < 0 || size_t(ij[0]) >= d || size_t(ij[1]) >= d)
        r.fail("feature_disks", "has a malformed pair '" + pair + "'");
      info.feature_disks.push_back(ij);
    }
    expect_size(path, "feature_disk_radius", info.feature_disk_radius.size(), info.feature_disks.size());
    info.robot_length = r.sized("robot_length", 1)[0];
    info.decoder_matrix = r.numbers("decoder_matrix");
    info.decoder_offset = r.numbers("decoder_offset");
    info.encoder_matrix = r.numbers("encoder_matrix");
    info.encoder_offset = r.numbers("encoder_offset");
    if (!info.decoder_matrix.empty()) {
      expect_size(path, "decoder_matrix", info.decoder_matrix.size(), n * d);
      expect_size(path, "decoder_offset", info.decoder_offset.size(), n);
      expect_size(path, "encoder_matrix", info.encoder_matrix.size(), d * n);
      expect_size(path, "encoder_offset", info.encoder_offset.size(), d);
    }
  }
  if (info.task == "ik_refinement") {
    info.iterations = std::atoi(r.text("iterations").c_str());
    info.position_only = r.text("position_only") == "true";
  }
  return info;
}

PackageInfo PackageInfo::read(const std::string& path) {
  if (!std::filesystem::is_regular_file(path))
    throw PackageError(path + ": no such package file (an exported <name>.aoti.pt2)");
  std::unordered_map<std::string, std::string> metadata;
  try {
    metadata = torch::inductor::AOTIModelPackageLoader::load_metadata_from_package(path, "model");
  } catch (const std::exception& err) {
    throw PackageError(path + ": not an AOTInductor package (" + first_line(err) + ")");
  }
  return parse(metadata, path);
}

Package::Package(const std::string& path, const std::string& module, const std::string& task,
                 const Expectations& expect) {
  info_ = PackageInfo::read(path);
  const std::string here = TORCH_VERSION;
  if (info_.torch_version.substr(0, info_.torch_version.find('+')) != here)
    throw PackageError(path + ": built with torch " + info_.torch_version + ", this libtorch is " + here +
                       "; re-export with the torch this program links");
  if (!module.empty() && info_.module != module)
    throw PackageError(path + ": module '" + info_.module + "', expected '" + module + "'");
  if (!task.empty() && info_.task != task)
    throw PackageError(path + ": task '" + info_.task + "', expected '" + task + "'");
  if (info_.dtype == "float32") dtype_ = at::kFloat;
  else if (info_.dtype == "float64") dtype_ = at::kDouble;
  else throw PackageError(path + ": dtype '" + info_.dtype + "', expected float32 or float64");
  if (!expect.robot.empty() && info_.robot != expect.robot)
    throw PackageError(path + ": exported for robot '" + info_.robot + "', expected '" + expect.robot + "'");
  if (!expect.joint_names.empty() && info_.joint_names != expect.joint_names)
    throw PackageError(path + ": joint order [" + join(info_.joint_names) + "], expected [" +
                       join(expect.joint_names) + "]");
  loader_ = std::make_unique<torch::inductor::AOTIModelPackageLoader>(path, "model", /*run_single_threaded=*/true);
  runner_ = loader_->get_runner();
  for (const auto& spec : info_.inputs) {
    std::vector<int64_t> shape{1};
    shape.insert(shape.end(), spec.shape.begin(), spec.shape.end());
    batch1_.push_back(at::zeros(shape, at::TensorOptions().dtype(dtype_)));
  }
  std::vector<at::Tensor> outs;  // warm-up, and the outputs checked against the metadata
  try {
    outs = runner_->run(batch1_);
  } catch (const std::exception& err) {
    throw PackageError(path + ": the package does not run on inputs of its metadata's shapes (" + first_line(err) +
                       ")");
  }
  if (outs.size() != info_.outputs.size())
    throw PackageError(path + ": the package returns " + std::to_string(outs.size()) + " outputs, its metadata lists " +
                       std::to_string(info_.outputs.size()));
  for (size_t j = 0; j < outs.size(); ++j) {
    std::vector<int64_t> want{1};
    want.insert(want.end(), info_.outputs[j].shape.begin(), info_.outputs[j].shape.end());
    if (outs[j].sizes().vec() != want)
      throw PackageError(path + ": output " + info_.outputs[j].name + " has shape " + shape_str(outs[j].sizes().vec()) +
                         ", its metadata says " + shape_str(want));
  }
}

Package::~Package() = default;

std::vector<at::Tensor> Package::run(const std::vector<at::Tensor>& inputs) {
  if (inputs.size() != info_.inputs.size())
    throw PackageError(info_.path + ": expected " + std::to_string(info_.inputs.size()) + " inputs, got " +
                       std::to_string(inputs.size()));
  const int64_t batch = inputs.empty() ? 1 : (inputs[0].dim() ? inputs[0].size(0) : 0);
  for (size_t i = 0; i < inputs.size(); ++i) {
    const auto& x = inputs[i];
    std::vector<int64_t> want{batch};
    want.insert(want.end(), info_.inputs[i].shape.begin(), info_.inputs[i].shape.end());
    if (x.sizes().vec() != want || batch < 1 || batch > (1 << 16))
      throw PackageError(info_.path + ": input " + info_.inputs[i].name + " has shape " + shape_str(x.sizes().vec()) +
                         ", expected " + shape_str(want) + " with a batch of 1 … 65536 shared by all inputs");
    if (x.scalar_type() != dtype_ || !x.is_contiguous() || !x.device().is_cpu())
      throw PackageError(info_.path + ": input " + info_.inputs[i].name + " must be a contiguous CPU " + info_.dtype +
                         " tensor");
  }
  return runner_->run(inputs);
}

void Package::call(const double* const* inputs, double* const* outputs) {
  for (size_t i = 0; i < batch1_.size(); ++i) {
    auto& t = batch1_[i];
    const int64_t n = t.numel();
    if (dtype_ == at::kFloat) {
      float* dst = t.data_ptr<float>();
      for (int64_t k = 0; k < n; ++k) dst[k] = static_cast<float>(inputs[i][k]);
    } else {
      double* dst = t.data_ptr<double>();
      for (int64_t k = 0; k < n; ++k) dst[k] = inputs[i][k];
    }
  }
  auto outs = runner_->run(batch1_);
  for (size_t j = 0; j < outs.size(); ++j) {
    if (outputs[j] == nullptr) continue;
    if (dtype_ == at::kFloat) copy_out(outs[j], outs[j].const_data_ptr<float>(), outputs[j]);
    else copy_out(outs[j], outs[j].const_data_ptr<double>(), outputs[j]);
  }
}

void Package::call(std::initializer_list<const double*> inputs, std::initializer_list<double*> outputs) {
  if (inputs.size() != info_.inputs.size() || outputs.size() != info_.outputs.size())
    throw PackageError(info_.path + ": call with " + std::to_string(inputs.size()) + " inputs and " +
                       std::to_string(outputs.size()) + " outputs, the module has " +
                       std::to_string(info_.inputs.size()) + " and " + std::to_string(info_.outputs.size()));
  for (const double* p : inputs)
    if (p == nullptr) throw PackageError(info_.path + ": an input buffer is nullptr");
  call(inputs.begin(), outputs.begin());
}

namespace {
int trailing(const Package& p, bool input, size_t index, size_t axis) {
  const auto& specs = input ? p.info().inputs : p.info().outputs;
  if (index >= specs.size() || axis >= specs[index].shape.size())
    throw PackageError(p.info().path + ": module " + p.info().module + " lacks the expected " +
                       (input ? "input" : "output") + " #" + std::to_string(index));
  return static_cast<int>(specs[index].shape[axis]);
}
}  // namespace

ForwardKinematics::ForwardKinematics(const std::string& path, const Expectations& expect)
    : package_(path, "fk", "fk", expect), n_(trailing(package_, true, 0, 0)) {}

Jacobian::Jacobian(const std::string& path, const Expectations& expect)
    : package_(path, "jacobian", "fk", expect), n_(trailing(package_, true, 0, 0)),
      d_(trailing(package_, false, 1, 1)) {}

InverseKinematics::InverseKinematics(const std::string& path, const Expectations& expect)
    : package_(path, "ik", "ik", expect), n_(trailing(package_, false, 0, 0)) {}

IKRefinement::IKRefinement(const std::string& path, const Expectations& expect)
    : package_(path, "refine", "ik_refinement", expect), n_(trailing(package_, true, 1, 0)) {}

namespace {
int whole_body_joints(const Package& p) {
  const auto& info = p.info();
  const int64_t n = int64_t(info.joint_names.size());
  const auto shape = [](const std::vector<TensorSpec>& specs, size_t i) {
    return i < specs.size() ? specs[i].shape : std::vector<int64_t>{};
  };
  if (info.inputs.size() != 3 || info.outputs.size() != 1 || shape(info.inputs, 0) != std::vector<int64_t>{n} ||
      shape(info.inputs, 1) != std::vector<int64_t>{4, 4} || shape(info.inputs, 2) != std::vector<int64_t>{6} ||
      shape(info.outputs, 0) != std::vector<int64_t>{n})
    throw PackageError(info.path + ": the whole-body step's signature is (q:" + std::to_string(n) +
                       ", target:4x4, feedforward:6) -> (q:" + std::to_string(n) + ") for its " + std::to_string(n) +
                       " joints; the package says (" + info.raw.at("inputs") + ") -> (" + info.raw.at("outputs") + ")");
  return static_cast<int>(n);
}
}  // namespace

WholeBodyStep::WholeBodyStep(const std::string& path, const Expectations& expect)
    : package_(path, "step", "whole_body_control", expect), n_(whole_body_joints(package_)) {}

HardwareModule::HardwareModule(const std::string& path, const std::string& module, const Expectations& expect)
    : package_(path, module, "hardware_fk", expect), s_(trailing(package_, true, 0, 0)) {}

}  // namespace dacr
