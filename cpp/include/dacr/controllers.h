// Controllers on the exported modules, with the life cycle of a ros2_control controller in plain C++
// (on_configure → on_activate → update(time, period) every tick → on_deactivate); docs/cpp.md says how to wrap
// one in a ROS 2 controller. Interfaces are plain double vectors, as ros2_control's state, command and reference
// interfaces are: the owner writes `state` (and `reference`) before `update`, reads `command` after it.
// Nothing is allocated in `update` by these classes (the module call's own allocations: docs/cpp.md, "Limits").
#pragma once

#include <vector>

#include "dacr/package.h"

namespace dacr {

enum class ReturnType { OK, ERROR };

// Resolved-rate position control in Clarke features, as dacr_learn.deploy.control.ResolvedRateController:
// per tick (pose, J_f) = jacobian(q); Δx = feedforward + gain·(p* − p); Δz = J̃ᵀ(J̃J̃ᵀ + λ²I)⁻¹Δx with
// J̃ = J_v·diag(s), ‖Δz‖ ≤ max_step; f' = sat(enc(q) + s·Δz) (disks radially, boxes clamped); q' = dec(f').
// Needs a package with the affine Clarke maps in its metadata (robots without twisting segments).
class ResolvedRateController {
 public:
  struct Config {
    double gain = 0.5;       // fraction of the position error corrected per tick, (0, 1]
    double damping = -1.0;   // λ [m]; < 0: 1 % of the robot length
    double max_step = 0.05;  // largest scaled feature step per tick
  };
  ResolvedRateController(Jacobian& jacobian, Config config);
  ResolvedRateController(Jacobian& jacobian) : ResolvedRateController(jacobian, Config{}) {}

  std::vector<double> state;      // (N) measured joints [m, rad]
  std::vector<double> reference;  // (6) target tip position p* [m], then its displacement over this tick [m]
  std::vector<double> command;    // (N) joint command [m, rad] on the displacement constraint

  ReturnType on_activate();  // the command starts at the measured joints
  ReturnType update(double time, double period);
  const double* tip() const { return pose_.data() + 0; }  // the last tick's pose (4 × 4, row major) [m]
  double position_error() const { return error_; }          // ‖p* − p‖ [m] at the last tick, before its step

 private:
  Jacobian& jacobian_;
  Config config_;
  const PackageInfo& info_;
  int n_, d_;
  double damping_;
  std::vector<double> pose_, jf_, f_, jt_;
  double error_ = 0.0;
};

// Warm-started IK tracking: per tick q = refine(target, previous q) (a fixed number of LM iterations).
class IKTrackingController {
 public:
  explicit IKTrackingController(IKRefinement& refinement);

  std::vector<double> state;      // (N) measured joints
  std::vector<double> reference;  // target pose (16, row major) [m] (or position (3) for a position-only module)
  std::vector<double> command;    // (N) joint command

  ReturnType on_activate();  // warm start at the measured joints
  ReturnType update(double time, double period);
  double position_error() const { return pos_err_; }  // [m] of the command
  double rotation_error() const { return rot_err_; }  // [rad]

 private:
  IKRefinement& refinement_;
  std::vector<double> warm_;
  double pos_err_ = 0.0, rot_err_ = 0.0;
};

}  // namespace dacr
