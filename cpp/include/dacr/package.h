// dacr_learn's exported modules in C++: AOTInductor packages written by `python -m dacr_learn.export`,
// `python -m dacr_learn.ik.exported` and `python -m dacr_learn.arm.exported`, loaded with libtorch, their embedded metadata read and checked.
//
// Two ways to call a module (docs/cpp.md, "API"):
//  - plain buffers at batch 1 (`Package::call`, and the typed classes below): double arrays in, double arrays
//    out, in the shapes of the metadata (row major). What a controller has (ros2_control state and command
//    interfaces are doubles); no torch type in the controller's code; the inputs are copied into tensors made
//    once at load, so nothing is allocated for them per call.
//  - at::Tensor (`Package::run`): any batch (1 … 65536), the package's dtype, contiguous; for batch work.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

#include <ATen/Tensor.h>

namespace torch::inductor {
class AOTIModelPackageLoader;
class AOTIModelContainerRunner;
}  // namespace torch::inductor

namespace dacr {

// The package format this library reads (dacr_learn.deploy.export.FORMAT).
inline constexpr const char* kFormat = "dacr_learn.export/1";

// A problem with a package or with a call: the message names the file and what was expected.
struct PackageError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// One input or output: its name and the shape of one batch row (empty for a scalar per row).
struct TensorSpec {
  std::string name;
  std::vector<int64_t> shape;
  int64_t numel() const;  // elements per batch row
};

// The metadata a package carries (dacr_learn/deploy/package_metadata.py; `dacr_learn.` keys).
struct PackageInfo {
  std::string path, format, module, task, dtype, robot, torch_version;
  std::vector<TensorSpec> inputs, outputs;
  // columns of the joint vector (robot models: s<k>.q<j> [m], s<k>.alpha [rad]) or the servo command
  // (hardware models: servo<id> [mm])
  std::vector<std::string> joint_names, joint_units;
  // robot models: actuated Clarke features (the columns of J_f) and their limits: a box (lower/upper, ±inf on the
  // rho columns) and disks (feature index pairs with ‖(f_i, f_j)‖ ≤ radius), a typical range per feature
  std::vector<std::string> feature_names;
  std::vector<double> feature_lower, feature_upper, feature_disk_radius, feature_scale;
  std::vector<std::array<int, 2>> feature_disks;
  double robot_length = 0.0;  // [m], sum of the nominal segment lengths (robot models)
  // robot models without twisting segments: q = A·f + c (A: N × D) and f = E·q + e (E: D × N), row major;
  // empty otherwise
  std::vector<double> decoder_matrix, decoder_offset, encoder_matrix, encoder_offset;
  int iterations = 0;          // IK refinement
  bool position_only = false;  // IK refinement
  // whole-body control step (task whole_body_control): joint_names are the arm's `arm_joints` joints (URDF names,
  // chain order) then the robot's; the feature entries above describe the robot (its joints: the rest of q)
  int arm_joints = 0;
  std::vector<double> arm_lower, arm_upper;  // URDF joint limits [rad, m]
  std::vector<double> arm_velocity;          // URDF velocity limits [rad/s, m/s]
  std::vector<double> mount;                 // arm tip link → robot base, 4 × 4 row major [m]
  std::vector<double> port_centre;           // (3) [m] in the arm's base frame; empty: no port
  double port_radius = 0.0;                  // [m]
  double dt = 0.0;                           // the control period the step limits the arm's velocity for [s]; 0: none
  std::unordered_map<std::string, std::string> raw;  // every `dacr_learn.` entry, prefix removed

  // Parse the package's metadata map; PackageError naming `path` when an entry is missing or malformed.
  static PackageInfo parse(const std::unordered_map<std::string, std::string>& metadata, const std::string& path);
  // Read and parse the metadata of the package at `path` without loading its code (which class to open it with).
  static PackageInfo read(const std::string& path);
};

// What the caller expects of a package; an empty field is not checked. A mismatch is a PackageError.
struct Expectations {
  std::string robot;                     // the robot's name
  std::vector<std::string> joint_names;  // the controller's joint (or servo) order
};

// One loaded AOTInductor package of dacr_learn (any module kind).
class Package {
 public:
  // Loads `path` (a .aoti.pt2 file) and checks: dacr_learn metadata present, format, module name and task (when
  // `module` / `task` are not empty), torch version of the package = this libtorch's, dtype, consistent shapes,
  // `expect`; then runs it once on zeros and checks the number and shapes of the outputs.
  Package(const std::string& path, const std::string& module = "", const std::string& task = "",
          const Expectations& expect = {});
  ~Package();
  Package(const Package&) = delete;
  Package& operator=(const Package&) = delete;

  const PackageInfo& info() const { return info_; }
  at::ScalarType dtype() const { return dtype_; }

  // Batch call: one tensor per input, shape (B, *shape), the package's dtype, contiguous CPU; returns the outputs
  // (B, *shape), not necessarily contiguous (a Jacobian may come transposed in memory). PackageError on a wrong
  // count, shape, dtype or device.
  std::vector<at::Tensor> run(const std::vector<at::Tensor>& inputs);

  // Batch-1 call on plain buffers: `inputs[i]` points at inputs()[i].numel() doubles, `outputs[j]` at
  // outputs()[j].numel() doubles (nullptr: not wanted). Inputs are converted into tensors made at load; the runtime
  // returns freshly allocated output tensors (AOTInductor's outputs own their memory), copied out here.
  void call(const double* const* inputs, double* const* outputs);
  void call(std::initializer_list<const double*> inputs, std::initializer_list<double*> outputs);

 private:
  PackageInfo info_;
  at::ScalarType dtype_;
  std::unique_ptr<torch::inductor::AOTIModelPackageLoader> loader_;
  torch::inductor::AOTIModelContainerRunner* runner_ = nullptr;
  std::vector<at::Tensor> batch1_;  // the batch-1 input tensors of `call`
};

// fk of an FK export: joint vector q (N) [m, rad] → tip pose (4 × 4) [m].
class ForwardKinematics {
 public:
  explicit ForwardKinematics(const std::string& path, const Expectations& expect = {});
  void pose(const double* q, double* pose) { package_.call({q}, {pose}); }
  int num_joints() const { return n_; }
  Package& package() { return package_; }

 private:
  Package package_;
  int n_;
};

// jacobian of an FK export: q (N) → pose (4 × 4), J_f (6 × D), J_q (6 × N): rows v_x, v_y, v_z [m], ω [rad] of the
// tip in the base frame, w.r.t. the actuated Clarke features (J_f) and the joints (J_q). Any pointer but q may be
// nullptr.
class Jacobian {
 public:
  explicit Jacobian(const std::string& path, const Expectations& expect = {});
  void evaluate(const double* q, double* pose, double* J_f, double* J_q) { package_.call({q}, {pose, J_f, J_q}); }
  int num_joints() const { return n_; }
  int num_features() const { return d_; }
  Package& package() { return package_; }

 private:
  Package package_;
  int n_, d_;
};

// ik of an IK export: tip pose (4 × 4) [m] → joint vector q (N) on the displacement constraint.
class InverseKinematics {
 public:
  explicit InverseKinematics(const std::string& path, const Expectations& expect = {});
  void joints(const double* pose, double* q) { package_.call({pose}, {q}); }
  int num_joints() const { return n_; }
  Package& package() { return package_; }

 private:
  Package package_;
  int n_;
};

// refine of `python -m dacr_learn.ik.exported`: target pose (4 × 4) [m] (or position (3) with position_only),
// warm start q0 (N) → q (N), position error [m], rotation error [rad], after a fixed number of LM iterations.
class IKRefinement {
 public:
  explicit IKRefinement(const std::string& path, const Expectations& expect = {});
  void refine(const double* target, const double* q0, double* q, double* pos_err, double* rot_err) {
    package_.call({target, q0}, {q, pos_err, rot_err});
  }
  int num_joints() const { return n_; }
  Package& package() { return package_; }

 private:
  Package package_;
  int n_;
};

// Any module of a saved hardware model's export (task hardware_fk): fk (servo [, state] → tip, tip_std [, state]),
// jacobian (→ tip, J [, state]), initial_state; `info().inputs` / `outputs` name the buffers of `call`.
class HardwareModule {
 public:
  HardwareModule(const std::string& path, const std::string& module, const Expectations& expect = {});
  void call(std::initializer_list<const double*> inputs, std::initializer_list<double*> outputs) {
    package_.call(inputs, outputs);
  }
  void call(const double* const* inputs, double* const* outputs) { package_.call(inputs, outputs); }
  int num_servos() const { return s_; }
  Package& package() { return package_; }

 private:
  Package package_;
  int s_;
};

// step of `python -m dacr_learn.arm.exported` (task whole_body_control): one whole-body resolved-rate step of an arm
// carrying a continuum robot, float64: joints q (N) [the arm's joints in chain order, rad / m, then the robot's
// joint vector], target pose (4 × 4) [m, arm base frame], feedforward (6) (Δp [m], Δφ [rad] of the target over
// the step) → next joints (N). Gains, port and period are fixed in the package (`info()`, `info().raw`). Checked
// at load: the signature (q: N = joint_names, target 4 × 4, feedforward 6 → q: N) and the arm's limits.
class WholeBodyStep {
 public:
  explicit WholeBodyStep(const std::string& path, const Expectations& expect = {});
  void step(const double* q, const double* target, const double* feedforward, double* q_next) {
    package_.call({q, target, feedforward}, {q_next});
  }
  int num_joints() const { return n_; }
  int num_arm_joints() const { return package_.info().arm_joints; }
  Package& package() { return package_; }

 private:
  Package package_;
  int n_;
};

}  // namespace dacr
