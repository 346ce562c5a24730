#include "fem/svd.hpp"

#include <Eigen/SVD>
#include <cmath>

namespace matlearn::fem {

namespace {

// Eigen's two-sided JacobiSVD: robust reference, ~3x slower than the path below.
void jacobi_svd(const Mat3& F, Mat3& U, Vec3& s, Mat3& V) {
  Eigen::JacobiSVD<Mat3> svd(F, Eigen::ComputeFullU | Eigen::ComputeFullV);
  U = svd.matrixU();
  V = svd.matrixV();
  s = svd.singularValues();
  if (U.determinant() < 0) {
    U.col(2) *= -1;
    s[2] *= -1;
  }
  if (V.determinant() < 0) {
    V.col(2) *= -1;
    s[2] *= -1;
  }
}

// Givens rotation G acting on rows/cols (p, q) that zeroes b given (a, b), with r = hypot >= 0.
inline void givens(double a, double b, double& c, double& sn) {
  const double r = std::sqrt(a * a + b * b);  // no overflow risk at deformation-gradient scales
  if (r == 0.0) {
    c = 1.0;
    sn = 0.0;
  } else {
    c = a / r;
    sn = b / r;
  }
}

}  // namespace

void rotation_variant_svd(const Mat3& F, Mat3& U, Vec3& s, Mat3& V) {
  // 1. Symmetric eigen-decomposition of F^T F by cyclic Jacobi rotations: V (proper rotation).
  Mat3 A = F.transpose() * F;
  V.setIdentity();
  const double scale = A.diagonal().sum();
  if (!(scale > 0) || !std::isfinite(scale)) return jacobi_svd(F, U, s, V);
  for (int sweep = 0; sweep < 12; ++sweep) {
    const double off = A(0, 1) * A(0, 1) + A(0, 2) * A(0, 2) + A(1, 2) * A(1, 2);
    if (off <= 1e-34 * scale * scale) break;
    static const int pq[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    for (const auto& idx : pq) {
      const int p = idx[0], q = idx[1];
      const double apq = A(p, q);
      if (std::abs(apq) <= 1e-300) continue;
      const double theta = (A(q, q) - A(p, p)) / (2.0 * apq);
      const double t = (theta >= 0 ? 1.0 : -1.0) / (std::abs(theta) + std::sqrt(theta * theta + 1.0));
      const double c = 1.0 / std::sqrt(t * t + 1.0), sn = t * c;
      // A <- J^T A J, V <- V J with J the rotation in the (p, q) plane.
      for (int k = 0; k < 3; ++k) {
        const double akp = A(k, p), akq = A(k, q);
        A(k, p) = c * akp - sn * akq;
        A(k, q) = sn * akp + c * akq;
      }
      for (int k = 0; k < 3; ++k) {
        const double apk = A(p, k), aqk = A(q, k);
        A(p, k) = c * apk - sn * aqk;
        A(q, k) = sn * apk + c * aqk;
      }
      for (int k = 0; k < 3; ++k) {
        const double vkp = V(k, p), vkq = V(k, q);
        V(k, p) = c * vkp - sn * vkq;
        V(k, q) = sn * vkp + c * vkq;
      }
    }
  }
  // 2. Order by decreasing eigenvalue (swapping two columns and negating one keeps det V = +1).
  Vec3 lam = A.diagonal();
  auto swap_cols = [&](int i, int j) {
    std::swap(lam[i], lam[j]);
    V.col(i).swap(V.col(j));
    V.col(j) *= -1;
  };
  if (lam[0] < lam[1]) swap_cols(0, 1);
  if (lam[0] < lam[2]) swap_cols(0, 2);
  if (lam[1] < lam[2]) swap_cols(1, 2);
  // 3. QR of B = F V by Givens rotations: B = U R, U proper, R upper triangular whose diagonal
  //    holds the singular values (the last one negative for an inverted F).
  Mat3 R = F * V;
  U.setIdentity();
  auto rotate = [&](int p, int q, int col) {
    double c, sn;
    givens(R(p, col), R(q, col), c, sn);
    for (int k = 0; k < 3; ++k) {
      const double rp = R(p, k), rq = R(q, k);
      R(p, k) = c * rp + sn * rq;
      R(q, k) = -sn * rp + c * rq;
      const double up = U(k, p), uq = U(k, q);
      U(k, p) = c * up + sn * uq;
      U(k, q) = -sn * up + c * uq;
    }
  };
  rotate(0, 1, 0);
  rotate(0, 2, 0);
  rotate(1, 2, 1);
  s = R.diagonal();
  // 4. Accept only a clean factorisation: R diagonal to round-off and |s| ordered. Otherwise
  //    (clustered or tiny singular values in awkward positions) use the robust two-sided SVD.
  const double tol = 1e-14 * std::sqrt(scale);
  const double offR = std::abs(R(0, 1)) + std::abs(R(0, 2)) + std::abs(R(1, 2));
  if (!(offR <= tol) || s[0] < s[1] || s[1] < std::abs(s[2]) - tol || !s.allFinite())
    return jacobi_svd(F, U, s, V);
}

}  // namespace matlearn::fem
