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
  //    Only the 6 distinct entries of the symmetric matrix are updated (a rotation in the
  //    (p, q) plane zeroes a_pq, moves a_pp, a_qq by -/+ t a_pq and mixes the third row r).
  const Mat3 A = F.transpose() * F;
  double d[3] = {A(0, 0), A(1, 1), A(2, 2)};
  double o[3] = {A(0, 1), A(0, 2), A(1, 2)};  // off-diagonal (0,1), (0,2), (1,2)
  V.setIdentity();
  const double scale = d[0] + d[1] + d[2];
  if (!(scale > 0) || !std::isfinite(scale)) return jacobi_svd(F, U, s, V);
  // pair k = (p, q) with the other index r; o_pr and o_qr are the off-diagonals it mixes
  static const int P[3] = {0, 0, 1}, Q[3] = {1, 2, 2};
  static const int OPR[3] = {1, 0, 0}, OQR[3] = {2, 2, 1};
  for (int sweep = 0; sweep < 12; ++sweep) {
    if (o[0] * o[0] + o[1] * o[1] + o[2] * o[2] <= 1e-34 * scale * scale) break;
    for (int k = 0; k < 3; ++k) {
      const double apq = o[k];
      if (std::abs(apq) <= 1e-300) continue;
      const int p = P[k], q = Q[k];
      // t = sign(theta) / (|theta| + sqrt(theta^2 + 1)), theta = (a_qq - a_pp) / (2 a_pq),
      // written without the division for theta (sign(+-0) = +1 as before).
      const double diff = d[q] - d[p];
      const double sgn = diff == 0.0 || (diff > 0) == (apq > 0) ? 1.0 : -1.0;
      const double t = sgn * 2.0 * std::abs(apq) / (std::abs(diff) + std::sqrt(diff * diff + 4.0 * apq * apq));
      const double c = 1.0 / std::sqrt(t * t + 1.0), sn = t * c;
      d[p] -= t * apq;
      d[q] += t * apq;
      o[k] = 0.0;
      const double arp = o[OPR[k]], arq = o[OQR[k]];
      o[OPR[k]] = c * arp - sn * arq;
      o[OQR[k]] = sn * arp + c * arq;
      for (int i = 0; i < 3; ++i) {
        const double vip = V(i, p), viq = V(i, q);
        V(i, p) = c * vip - sn * viq;
        V(i, q) = sn * vip + c * viq;
      }
    }
  }
  // 2. Order by decreasing eigenvalue (swapping two columns and negating one keeps det V = +1).
  Vec3 lam(d[0], d[1], d[2]);
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
