#include "fem/material.hpp"

#include <Eigen/Eigenvalues>
#include <cmath>

namespace matlearn::fem {

MaterialModel material_model_from_string(const std::string& name) {
  if (name == "corotated") return MaterialModel::Corotated;
  if (name == "neo_hookean") return MaterialModel::NeoHookean;
  if (name == "stvk") return MaterialModel::StVK;
  if (name == "designed") return MaterialModel::Designed;
  throw InvalidInput("unknown material model '" + name +
                     "' (expected corotated, neo_hookean, stvk or designed)");
}

std::string to_string(MaterialModel m) {
  switch (m) {
    case MaterialModel::Corotated: return "corotated";
    case MaterialModel::NeoHookean: return "neo_hookean";
    case MaterialModel::StVK: return "stvk";
    case MaterialModel::Designed: return "designed";
  }
  return "?";
}

namespace {

// Continued logarithm L(J) and its first two derivatives.
void log_j(double J, double& L, double& dL, double& ddL) {
  const double J0 = kNeoHookeanJ0;
  if (J >= J0) {
    L = std::log(J);
    dL = 1.0 / J;
    ddL = -1.0 / (J * J);
  } else {
    const double d = J - J0;
    L = std::log(J0) + d / J0 - d * d / (2 * J0 * J0);
    dL = 1.0 / J0 - d / (J0 * J0);
    ddL = -1.0 / (J0 * J0);
  }
}

// Bump b(t) = (1-t^2)^2, its antiderivative and derivative.
double bump(double t) { return std::abs(t) < 1 ? (1 - t * t) * (1 - t * t) : 0.0; }
double bump_int(double t) {
  t = std::clamp(t, -1.0, 1.0);
  return t - 2.0 * t * t * t / 3.0 + t * t * t * t * t / 5.0;
}
double bump_d(double t) { return std::abs(t) < 1 ? -4.0 * t * (1 - t * t) : 0.0; }

}  // namespace

double principal_energy(MaterialModel m, const Vec3& s, double mu, double lam,
                        const std::vector<StretchEdit>& edits) {
  switch (m) {
    case MaterialModel::Corotated: {
      const Vec3 e = s.array() - 1.0;
      return mu * e.squaredNorm() + 0.5 * lam * e.sum() * e.sum();
    }
    case MaterialModel::StVK: {
      const Vec3 E = 0.5 * (s.array().square() - 1.0);
      return mu * E.squaredNorm() + 0.5 * lam * E.sum() * E.sum();
    }
    case MaterialModel::NeoHookean:
    case MaterialModel::Designed: {
      double L, dL, ddL;
      log_j(s.prod(), L, dL, ddL);
      double psi = 0.5 * mu * (s.squaredNorm() - 3.0) - mu * L + 0.5 * lam * L * L;
      if (m == MaterialModel::Designed)
        for (const auto& ed : edits)
          for (int i = 0; i < 3; ++i)
            // Integrated from the rest stretch 1, so the rest state has zero energy.
            psi += ed.amplitude * ed.half_width *
                   (bump_int((s[i] - ed.center) / ed.half_width) -
                    bump_int((1.0 - ed.center) / ed.half_width));
      return psi;
    }
  }
  return 0;
}

Vec3 principal_stress(MaterialModel m, const Vec3& s, double mu, double lam,
                      const std::vector<StretchEdit>& edits) {
  switch (m) {
    case MaterialModel::Corotated:
      return (2.0 * mu * (s.array() - 1.0) + lam * (s.array() - 1.0).sum()).matrix();
    case MaterialModel::StVK: {
      const Vec3 E = 0.5 * (s.array().square() - 1.0);
      return (s.array() * (2.0 * mu * E.array() + lam * E.sum())).matrix();
    }
    case MaterialModel::NeoHookean:
    case MaterialModel::Designed: {
      double L, dL, ddL;
      log_j(s.prod(), L, dL, ddL);
      const Vec3 dJ(s[1] * s[2], s[0] * s[2], s[0] * s[1]);
      Vec3 P = mu * s + (-mu + lam * L) * dL * dJ;
      if (m == MaterialModel::Designed)
        for (const auto& ed : edits)
          for (int i = 0; i < 3; ++i) P[i] += ed.amplitude * bump((s[i] - ed.center) / ed.half_width);
      return P;
    }
  }
  return Vec3::Zero();
}

Mat3 principal_stress_derivative(MaterialModel m, const Vec3& s, double mu, double lam,
                                 const std::vector<StretchEdit>& edits) {
  switch (m) {
    case MaterialModel::Corotated:
      return 2.0 * mu * Mat3::Identity() + lam * Mat3::Ones();
    case MaterialModel::StVK: {
      const Vec3 E = 0.5 * (s.array().square() - 1.0);
      Mat3 H = lam * s * s.transpose();
      for (int i = 0; i < 3; ++i) H(i, i) += 2.0 * mu * E[i] + lam * E.sum() + 2.0 * mu * s[i] * s[i];
      return H;
    }
    case MaterialModel::NeoHookean:
    case MaterialModel::Designed: {
      double L, dL, ddL;
      log_j(s.prod(), L, dL, ddL);
      const Vec3 dJ(s[1] * s[2], s[0] * s[2], s[0] * s[1]);
      const double c1 = -mu + lam * L;
      Mat3 H = mu * Mat3::Identity() + (lam * dL * dL + c1 * ddL) * dJ * dJ.transpose();
      // d^2 J / ds_i ds_j = s_k for i != j.
      Mat3 ddJ;
      ddJ << 0, s[2], s[1], s[2], 0, s[0], s[1], s[0], 0;
      H += c1 * dL * ddJ;
      if (m == MaterialModel::Designed)
        for (const auto& ed : edits)
          for (int i = 0; i < 3; ++i)
            H(i, i) += ed.amplitude / ed.half_width * bump_d((s[i] - ed.center) / ed.half_width);
      return H;
    }
  }
  return Mat3::Zero();
}

namespace {

/// Positive definite by its leading minors (the common case, where the projection clamps nothing).
bool positive_definite(const Mat3& sym) {
  const double m1 = sym(0, 0), m2 = sym(0, 0) * sym(1, 1) - sym(0, 1) * sym(0, 1);
  return m1 > 0 && m2 > 0 && sym.determinant() > 0;
}

}  // namespace

PrincipalTangent principal_tangent(const Vec3& s, const Vec3& Ph, const Mat3& dPh_in,
                                   bool project_psd) {
  PrincipalTangent T;
  // Unprojected: keep dPh as given (a learned correction need not have a symmetric Jacobian, and
  // the exact tangent is then non-symmetric). Projected: symmetrise, then clamp eigenvalues.
  T.diag = dPh_in;
  if (project_psd) {
    const Mat3 sym = 0.5 * (dPh_in + dPh_in.transpose());
    if (positive_definite(sym)) {
      T.diag = sym;
    } else {
      Eigen::SelfAdjointEigenSolver<Mat3> es(sym);
      T.diag = es.eigenvectors() * es.eigenvalues().cwiseMax(0.0).asDiagonal() *
               es.eigenvectors().transpose();
    }
  }
  static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
  for (int p = 0; p < 3; ++p) {
    const int i = pairs[p][0], j = pairs[p][1];
    const double ds = s[i] - s[j];
    // (Ph_i - Ph_j)/(s_i - s_j) -> dPh_ii - dPh_ij as s_i -> s_j (isotropy).
    const double A = std::abs(ds) > 1e-6 ? (Ph[i] - Ph[j]) / ds
                                         : 0.5 * (dPh_in(i, i) + dPh_in(j, j)) -
                                               0.5 * (dPh_in(i, j) + dPh_in(j, i));
    double ss = s[i] + s[j];
    if (std::abs(ss) < 1e-6) ss = ss < 0 ? -1e-6 : 1e-6;
    const double Bq = (Ph[i] + Ph[j]) / ss;
    double a = 0.5 * (A + Bq), b = 0.5 * (A - Bq);
    if (project_psd) {
      // eigenvalues of [[a b][b a]] are a+b (vector (1,1)) and a-b (vector (1,-1)).
      const double l1 = std::max(a + b, 0.0), l2 = std::max(a - b, 0.0);
      a = 0.5 * (l1 + l2);
      b = 0.5 * (l1 - l2);
    }
    T.a[p] = a;
    T.b[p] = b;
  }
  return T;
}

ProjectedTangentDerivative::ProjectedTangentDerivative(const Vec3& s, const Vec3& Ph, const Mat3& dPh)
    : s_(s) {
  const Mat3 sym = 0.5 * (dPh + dPh.transpose());
  clamped_ = !positive_definite(sym);
  if (clamped_) {
    Eigen::SelfAdjointEigenSolver<Mat3> es(sym);
    Q_ = es.eigenvectors();
    const Vec3 l = es.eigenvalues();
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        const double fi = std::max(l[i], 0.0), fj = std::max(l[j], 0.0);
        G_(i, j) = std::abs(l[i] - l[j]) > 1e-12 * (std::abs(l[i]) + std::abs(l[j]) + 1e-300)
                       ? (fi - fj) / (l[i] - l[j])
                       : (l[i] > 0 ? 1.0 : 0.0);
      }
  }
  const PrincipalTangent T = principal_tangent(s, Ph, dPh, false);
  keep_plus_ = ((T.a + T.b).array() > 0).cast<double>();
  keep_minus_ = ((T.a - T.b).array() > 0).cast<double>();
}

PrincipalTangent ProjectedTangentDerivative::operator()(const Vec3& dP, const Mat3& ddP) const {
  PrincipalTangent T = principal_tangent(s_, dP, 0.5 * (ddP + ddP.transpose()), false);
  if (clamped_) T.diag = Q_ * G_.cwiseProduct(Q_.transpose() * T.diag * Q_) * Q_.transpose();
  const Vec3 plus = (T.a + T.b).cwiseProduct(keep_plus_), minus = (T.a - T.b).cwiseProduct(keep_minus_);
  T.a = 0.5 * (plus + minus);
  T.b = 0.5 * (plus - minus);
  return T;
}

Eigen::Matrix<double, 9, 9> stress_derivative_from_principal(const Mat3& U, const Vec3& s,
                                                             const Mat3& V, const Vec3& Ph,
                                                             const Mat3& dPh, bool project_psd) {
  using Mat9 = Eigen::Matrix<double, 9, 9>;
  const PrincipalTangent T = principal_tangent(s, Ph, dPh, project_psd);
  // Column k of dP/dF is vec(U Hh(U^T E_k V) V^T) for the unit matrix E_k = unvec(e_k).
  Mat9 out;
  for (int k = 0; k < 9; ++k) {
    const int r = k % 3, c = k / 3;
    const Mat3 X = U.row(r).transpose() * V.row(c);  // U^T E_k V
    const Mat3 Y = U * T.apply(X) * V.transpose();
    out.col(k) = Eigen::Map<const Eigen::Matrix<double, 9, 1>>(Y.data());
  }
  return out;
}

}  // namespace matlearn::fem
