// Controllers on the exported modules (include/dacr/controllers.h).
#include "dacr/controllers.h"

#include <algorithm>
#include <cmath>

namespace dacr {

ResolvedRateController::ResolvedRateController(Jacobian& jacobian, Config config)
    : jacobian_(jacobian), config_(config), info_(jacobian.package().info()), n_(jacobian.num_joints()),
      d_(jacobian.num_features()) {
  if (info_.decoder_matrix.empty())
    throw PackageError(info_.path + ": no affine Clarke maps in the metadata (a robot with twisting segments); the "
                       "resolved-rate controller needs them");
  if (!(config.gain > 0 && config.gain <= 1) || !(config.max_step > 0))
    throw PackageError("ResolvedRateController: expected gain in (0, 1] and max_step > 0");
  damping_ = config.damping < 0 ? 0.01 * info_.robot_length : config.damping;
  state.assign(n_, 0.0);
  reference.assign(6, 0.0);
  command.assign(n_, 0.0);
  pose_.assign(16, 0.0);
  jf_.assign(6 * d_, 0.0);
  f_.assign(d_, 0.0);
  jt_.assign(3 * d_, 0.0);
}

ReturnType ResolvedRateController::on_activate() {
  command = state;
  return ReturnType::OK;
}

ReturnType ResolvedRateController::update(double /*time*/, double /*period*/) {
  const auto& s = info_.feature_scale;
  jacobian_.evaluate(command.data(), pose_.data(), jf_.data(), nullptr);
  double dx[3], e2 = 0.0;
  for (int i = 0; i < 3; ++i) {
    const double e = reference[i] - pose_[4 * i + 3];
    e2 += e * e;
    dx[i] = config_.gain * e + reference[3 + i];
  }
  error_ = std::sqrt(e2);
  // J̃ = J_v·diag(s), A = J̃J̃ᵀ + λ²I (3 × 3, symmetric positive definite), solved by Cholesky
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < d_; ++k) jt_[i * d_ + k] = jf_[i * d_ + k] * s[k];
  double a[3][3];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      double sum = i == j ? damping_ * damping_ : 0.0;
      for (int k = 0; k < d_; ++k) sum += jt_[i * d_ + k] * jt_[j * d_ + k];
      a[i][j] = sum;
    }
  double l[3][3] = {};
  for (int j = 0; j < 3; ++j) {
    double diag = a[j][j];
    for (int k = 0; k < j; ++k) diag -= l[j][k] * l[j][k];
    if (!(diag > 0)) return ReturnType::ERROR;
    l[j][j] = std::sqrt(diag);
    for (int i = j + 1; i < 3; ++i) {
      double v = a[i][j];
      for (int k = 0; k < j; ++k) v -= l[i][k] * l[j][k];
      l[i][j] = v / l[j][j];
    }
  }
  double y[3], w[3];
  for (int i = 0; i < 3; ++i) {
    double v = dx[i];
    for (int k = 0; k < i; ++k) v -= l[i][k] * y[k];
    y[i] = v / l[i][i];
  }
  for (int i = 2; i >= 0; --i) {
    double v = y[i];
    for (int k = i + 1; k < 3; ++k) v -= l[k][i] * w[k];
    w[i] = v / l[i][i];
  }
  // Δz = J̃ᵀw, shortened to max_step; f = enc(q) + s·Δz
  double norm2 = 0.0;
  for (int k = 0; k < d_; ++k) {
    const double dz = jt_[k] * w[0] + jt_[d_ + k] * w[1] + jt_[2 * d_ + k] * w[2];
    f_[k] = dz;
    norm2 += dz * dz;
  }
  const double norm = std::sqrt(norm2), shrink = norm > config_.max_step ? config_.max_step / norm : 1.0;
  for (int k = 0; k < d_; ++k) {
    double enc = info_.encoder_offset[k];
    for (int j = 0; j < n_; ++j) enc += info_.encoder_matrix[k * n_ + j] * command[j];
    f_[k] = enc + f_[k] * shrink * s[k];
  }
  // saturation: ρ radially into its disk, β and α into their ranges
  for (size_t p = 0; p < info_.feature_disks.size(); ++p) {
    const int i = info_.feature_disks[p][0], j = info_.feature_disks[p][1];
    const double r = std::hypot(f_[i], f_[j]), rmax = info_.feature_disk_radius[p];
    if (r > rmax) {
      f_[i] *= rmax / r;
      f_[j] *= rmax / r;
    }
  }
  for (int k = 0; k < d_; ++k) f_[k] = std::min(std::max(f_[k], info_.feature_lower[k]), info_.feature_upper[k]);
  for (int j = 0; j < n_; ++j) {
    double q = info_.decoder_offset[j];
    for (int k = 0; k < d_; ++k) q += info_.decoder_matrix[j * d_ + k] * f_[k];
    command[j] = q;
  }
  return ReturnType::OK;
}

IKTrackingController::IKTrackingController(IKRefinement& refinement) : refinement_(refinement) {
  const int n = refinement.num_joints();
  state.assign(n, 0.0);
  command.assign(n, 0.0);
  warm_.assign(n, 0.0);
  reference.assign(refinement.package().info().position_only ? 3 : 16, 0.0);
}

ReturnType IKTrackingController::on_activate() {
  warm_ = state;
  return ReturnType::OK;
}

ReturnType IKTrackingController::update(double /*time*/, double /*period*/) {
  refinement_.refine(reference.data(), warm_.data(), command.data(), &pos_err_, &rot_err_);
  std::copy(command.begin(), command.end(), warm_.begin());
  return std::isfinite(pos_err_) ? ReturnType::OK : ReturnType::ERROR;
}

}  // namespace dacr
