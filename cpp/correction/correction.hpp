#pragma once
#include <cmath>
#include <memory>
#include <vector>

#include "common/types.hpp"
#include "correction/isotropy.hpp"

namespace matlearn::correction {

/// Batched output of a stress correction N(Fh, Fhdot) for m elements.
struct CorrectionOutput {
  MatX3 dPh;                  ///< (m x 3) principal stress correction (Pa)
  std::vector<Mat3> d_dFh;    ///< m Jacobians dN/dFh
  std::vector<Mat3> d_dFhdot; ///< m Jacobians dN/dFhdot (s)
  VecX dalpha;                ///< (m) additive change of the element's stiffness-damping alpha_K (s)
};

/// A learned correction to the nominal principal stress, evaluated for all elements at once.
class Correction {
 public:
  virtual ~Correction() = default;
  /// Fh, Fhdot: (m x 3). Fills `out` for all m rows.
  virtual void evaluate(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const = 0;
  /// Values only: fills out.dPh and out.dalpha (bitwise those of evaluate) and leaves the
  /// Jacobians d_dFh, d_dFhdot empty, for callers that need forces but no tangent (the
  /// force-only Model evaluation of residuals and chord steps). Default: the full evaluate.
  virtual void evaluate_values(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const {
    evaluate(Fh, Fhdot, out);
  }
  /// True when evaluate() may run on several threads (false for Python callbacks).
  virtual bool thread_safe() const { return true; }

  /// Tangent damping. When on, the Model's stiffness-proportional Rayleigh damping acts on the
  /// *corrected* tangent: D_K = (alpha_K + dalpha) K_psd(nominal + correction) instead of
  /// (alpha_K + dalpha) K_psd(nominal), so a material whose stiffness the correction changes
  /// also changes its damping, as Rayleigh damping on the true material's tangent does. Off by
  /// default (models learned before it existed keep their meaning). Both are passive: the
  /// tangent is projected to PSD per element and alpha_K + dalpha is clamped at 0.
  bool tangent_damping() const { return tangent_damping_; }
  void set_tangent_damping(bool on) { tangent_damping_ = on; }

 private:
  bool tangent_damping_ = false;
};

/// RBF correction over principal stretches (method.md section 6):
///   dPh(Fh) = A (Fh - 1) + b + sum_k w_k phi(|Fh - c_k|),   phi(r) = sqrt(r^2 + eps^2)
///   dalpha(Fh) = a0 + sum_k wa_k phi(|Fh - c_k|)
/// centers (c x 3), weights (c x 3), linear A (3 x 3), bias b (3), alpha_weights (c), alpha_bias.
/// Optional box [lower, upper] (3 each, or both empty; the hull of the training stretches):
/// outside it each elastic kernel continues linearly with its slope at the nearest box point sc,
///   g_k(s) = phi(|sc - c_k|) + (sc - c_k).(s - sc) / phi(|sc - c_k|),
/// so the correction extrapolates to first order from the edge of the data (continuous, growth
/// at most linear, slope = the edge slope); the damping kernels are evaluated at sc (constant
/// beyond the box).
/// A fitted RBF is not exactly isotropic either (dPh_i != dPh_j at s_i = s_j: measured 800-1700
/// Pa on a learned compression sphere, whose replay then stalls); `isotropic_width` > 0 (stretch
/// units) passes dPh through isotropic_blend() as MlpCorrection does; < 0: 0.1 x the mean per-axis
/// std of the centres (k-means of the fitted stretches: a tenth of their spread); 0 (default):
/// off, the raw RBF. dalpha is a scalar per element, isotropic already.
class RbfCorrection final : public Correction {
 public:
  RbfCorrection(MatX3 centers, MatX3 weights, Mat3 linear, Vec3 bias, VecX alpha_weights,
                double alpha_bias, double epsilon, VecX lower = VecX(), VecX upper = VecX(),
                double isotropic_width = 0.0);
  double isotropic_width() const { return width_; }
  void evaluate(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const override;
  /// No kernel gradients; inside the box each kernel is phi alone (the extension term is an
  /// exact +0 there), so the values are bitwise those of evaluate().
  void evaluate_values(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const override;

 private:
  /// One element: dPh `p` and dalpha `da` at stretches s, and with J != nullptr dPh's Jacobian.
  void element(const Vec3& s, Vec3& p, double& da, Mat3* J) const;

  /// centres and weights column-major: per-axis contiguous columns for the vectorised kernel loop
  Eigen::Matrix<double, Eigen::Dynamic, 3> c_, w_;
  Mat3 A_;
  Vec3 b_;
  VecX wa_;
  double a0_, eps_;
  VecX lo_, hi_;
  double width_;  ///< isotropic blend width (0: off)
};

/// Elastic kernel g(s) of RbfCorrection (box extension above) and its gradient dg/ds.
/// sc: s clamped to the box (= s without one); also returns phi(|sc - c|) for the damping part.
inline double extended_kernel(const Vec3& s, const Vec3& sc, const Vec3& c, double eps,
                              Vec3* grad, double* phi_clamped) {
  const Vec3 d = sc - c, delta = s - sc;
  const double phi = std::sqrt(d.squaredNorm() + eps * eps);
  const double dd = d.dot(delta);
  if (phi_clamped) *phi_clamped = phi;
  if (grad)
    for (int i = 0; i < 3; ++i)
      (*grad)[i] = delta[i] != 0.0 ? d[i] / phi : d[i] / phi * (1.0 - dd / (phi * phi));
  return phi + dd / phi;
}

/// Dense layer of an MLP: y = W x + b (W is out x in); batch norm folded in at export.
struct DenseLayer {
  MatX W;
  VecX b;
};

/// MLP correction N(Fh, Fhdot) with ELU between layers (none after the last), inputs
/// normalised (x - in_mean) / in_std and outputs de-normalised y * out_std + out_mean.
/// The last layer has 3 outputs (dPh) or 4: (dPh, dalpha), dalpha being the additive change of
/// the element's stiffness-damping alpha_K exactly as RbfCorrection's damping part (the Model
/// clamps alpha_K + dalpha at 0, so this damping is passive by construction). Networks whose
/// first-layer Fhdot columns are zero are rate-independent: d_dFhdot is then exactly 0.
///
/// Coincident stretches. A stress correction must be an isotropic function of F: dPh_i = dPh_j
/// wherever s_i = s_j, or U diag(Ph) V^T depends on the arbitrary principal frame there and the
/// force jumps (Newton then cycles between the two sides: measured on a distilled StVK bar, 68 of
/// 300 steps hit the factorisation limit, the net's dPh_1 - dPh_2 being ~40 Pa at s_1 = s_2). A
/// trained network is not exactly isotropic, so its stress outputs pass through
/// isotropic_blend() with the width `isotropic_width` (stretch units; < 0: 0.1 x the mean input
/// std of the stretches, i.e. a tenth of the training spread; 0: off): exact at coincidence,
/// the raw network wherever all gaps |s_i - s_j| >= width, C1 in between.
class MlpCorrection final : public Correction {
 public:
  MlpCorrection(std::vector<DenseLayer> layers, VecX in_mean, VecX in_std, VecX out_mean,
                VecX out_std, double isotropic_width = -1.0);
  double isotropic_width() const { return width_; }
  void evaluate(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const override;
  /// No input Jacobians (the forward pass alone): bitwise the values of evaluate().
  void evaluate_values(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const override;

 private:
  void run(const MatX3& Fh, const MatX3& Fhdot, bool jacobians, CorrectionOutput& out) const;
  std::vector<DenseLayer> layers_;
  VecX in_mean_, in_std_, out_mean_, out_std_;
  int outputs_;  ///< 3 (dPh) or 4 (dPh, dalpha)
  double width_;  ///< isotropic blend width (0: off)
};

}  // namespace matlearn::correction
