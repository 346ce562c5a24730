#pragma once
#include <string>
#include <vector>

#include "common/types.hpp"

namespace matlearn::fem {

/// Elastic laws, all written in principal stretches s (3) with per-element Lame parameters.
enum class MaterialModel { Corotated, NeoHookean, StVK, Designed };

MaterialModel material_model_from_string(const std::string& name);
std::string to_string(MaterialModel m);

/// A spline "edit" of the separable designed material: adds f'(s_i) = amplitude * b((s_i -
/// center) / half_width) to each principal stress, b(t) = (1 - t^2)^2 on |t| < 1 (a C1 bump).
/// Must not cover s = 1 so the rest state stays stress free.
struct StretchEdit {
  double amplitude;   ///< Pa
  double center;      ///< stretch
  double half_width;  ///< stretch
};

/// Neo-Hookean uses log J continued below J0 by its quadratic Taylor polynomial, which keeps
/// energy, stress and tangent finite (and consistent) for inverted elements.
constexpr double kNeoHookeanJ0 = 0.2;

double principal_energy(MaterialModel m, const Vec3& s, double mu, double lambda,
                        const std::vector<StretchEdit>& edits = {});
Vec3 principal_stress(MaterialModel m, const Vec3& s, double mu, double lambda,
                      const std::vector<StretchEdit>& edits = {});
Mat3 principal_stress_derivative(MaterialModel m, const Vec3& s, double mu, double lambda,
                                 const std::vector<StretchEdit>& edits = {});

/// The tangent of an isotropic law in the principal frame: with hat(X) = U^T X V,
/// hat(dP) = Hh hat(dF), where Hh couples the diagonal of hat(dF) through `diag` (3 x 3, the
/// principal tangent dPh/ds) and each off-diagonal pair (hat_ij, hat_ji), (i,j) in
/// {(0,1), (0,2), (1,2)}, through the symmetric 2 x 2 block [[a b] [b a]]. Hh has 21 non-zeros
/// of 81, which is what makes element tangents cheap (see apply()).
struct PrincipalTangent {
  Mat3 diag;
  Vec3 a, b;
  /// hat(dP) for hat(dF) = X.
  Mat3 apply(const Mat3& X) const {
    Mat3 Y;
    const Vec3 d = diag * X.diagonal();
    Y(0, 0) = d[0];
    Y(1, 1) = d[1];
    Y(2, 2) = d[2];
    Y(0, 1) = a[0] * X(0, 1) + b[0] * X(1, 0);
    Y(1, 0) = b[0] * X(0, 1) + a[0] * X(1, 0);
    Y(0, 2) = a[1] * X(0, 2) + b[1] * X(2, 0);
    Y(2, 0) = b[1] * X(0, 2) + a[1] * X(2, 0);
    Y(1, 2) = a[2] * X(1, 2) + b[2] * X(2, 1);
    Y(2, 1) = b[2] * X(1, 2) + a[2] * X(2, 1);
    return Y;
  }
};

/// Principal-frame tangent from principal stretches s, stresses Ph and dPh/ds, following Teran
/// et al. 2005 / Xu et al. 2015 with the repeated-stretch limits. Unprojected, dPh is used as
/// given (a learned correction need not have a symmetric Jacobian); if `project_psd`, dPh is
/// symmetrised and every block clamped to be PSD, so the world tangent is PSD.
PrincipalTangent principal_tangent(const Vec3& s, const Vec3& Ph, const Mat3& dPh,
                                   bool project_psd);

/// Derivative of the projected tangent principal_tangent(s, Ph, dPh, true) at a total (Ph, dPh),
/// as a linear map of a direction (dP, ddP): the pair blocks [[a b][b a]] keep the change of each
/// eigenvalue a +- b that is positive at the total (a clamped one stays 0); the principal block,
/// where principal_tangent clamps it, changes by the Daleckii-Krein formula Q (G o Q^T dS Q) Q^T,
/// G_ij the divided differences of max(lambda, 0). Used to linearise damping on a projected
/// corrected tangent (learning/fit_normal_equations.cpp).
class ProjectedTangentDerivative {
 public:
  ProjectedTangentDerivative(const Vec3& s, const Vec3& Ph, const Mat3& dPh);
  /// The projected tangent's change in the direction (dP, ddP) (ddP symmetrised here).
  PrincipalTangent operator()(const Vec3& dP, const Mat3& ddP) const;

 private:
  Vec3 s_;
  bool clamped_ = false;  ///< principal_tangent clamps the principal block at the total
  Mat3 Q_ = Mat3::Identity(), G_ = Mat3::Ones();
  Vec3 keep_plus_, keep_minus_;  ///< 1 where a + b (a - b) of a pair is positive at the total
};

/// dP/dF (9 x 9, acting on column-major vec(F)) of an isotropic law from its principal data,
/// following Teran et al. 2005 / Xu et al. 2015 with the repeated-stretch limits.
/// `dPh` is dPh/ds (3x3); if `project_psd`, each principal block is clamped to be PSD.
Eigen::Matrix<double, 9, 9> stress_derivative_from_principal(const Mat3& U, const Vec3& s,
                                                             const Mat3& V, const Vec3& Ph,
                                                             const Mat3& dPh, bool project_psd);

/// Lame parameters from Young's modulus (Pa) and Poisson ratio.
inline double lame_mu(double E, double nu) { return E / (2.0 * (1.0 + nu)); }
inline double lame_lambda(double E, double nu) { return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)); }

}  // namespace matlearn::fem
