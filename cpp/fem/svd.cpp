#include "fem/svd.hpp"

#include <Eigen/SVD>
#include <algorithm>
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

// Order V's columns by decreasing eigenvalue (swapping two columns and negating one keeps
// det V = +1).
inline void order_columns(double d0, double d1, double d2, Mat3& V) {
  double lam[3] = {d0, d1, d2};
  auto swap_cols = [&](int i, int j) {
    std::swap(lam[i], lam[j]);
    V.col(i).swap(V.col(j));
    V.col(j) *= -1;
  };
  if (lam[0] < lam[1]) swap_cols(0, 1);
  if (lam[0] < lam[2]) swap_cols(0, 2);
  if (lam[1] < lam[2]) swap_cols(1, 2);
}

// Whether the Givens QR left a clean factorisation: R diagonal to round-off (offR: the sum of
// |R_01|, |R_02|, |R_12|) and |s| ordered, for F^T F of trace `scale`.
inline bool clean(double offR, const Vec3& s, double scale) {
  const double tol = 1e-14 * std::sqrt(scale);
  return offR <= tol && !(s[0] < s[1]) && !(s[1] < std::abs(s[2]) - tol) && s.allFinite();
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
  // 2. Order by decreasing eigenvalue.
  order_columns(d[0], d[1], d[2], V);
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
  if (!clean(std::abs(R(0, 1)) + std::abs(R(0, 2)) + std::abs(R(1, 2)), s, scale))
    return jacobi_svd(F, U, s, V);
}

namespace {

using Lane = Eigen::Array<double, kSvdLanes, 1>;
using LaneMask = Eigen::Array<bool, kSvdLanes, 1>;

// One Jacobi rotation in the (p, q) plane of every lane that is `on` (not converged at the start
// of this sweep) and whose a_pq is not negligible (k: the pair's off-diagonal, kr / kq: the
// off-diagonals (p, r) and (q, r) it mixes), exactly as in rotation_variant_svd.
template <int p, int q, int k, int kr, int kq>
inline void jacobi_rotate(Lane* d, Lane* o, Lane (*v)[3], const LaneMask& on) {
  const Lane apq = o[k];
  const LaneMask active = on && (apq.abs() > 1e-300);
  const Lane diff = d[q] - d[p];
  const Lane sgn = ((diff == 0.0) || ((diff > 0.0) == (apq > 0.0))).select(Lane::Constant(1.0), Lane::Constant(-1.0));
  // (inactive lanes may divide 0 by 0 here; select discards them)
  const Lane t = sgn * 2.0 * apq.abs() / (diff.abs() + (diff * diff + 4.0 * apq * apq).sqrt());
  const Lane c = 1.0 / (t * t + 1.0).sqrt(), sn = t * c;
  d[p] = active.select(d[p] - t * apq, d[p]);
  d[q] = active.select(d[q] + t * apq, d[q]);
  o[k] = active.select(Lane::Zero(), o[k]);
  const Lane arp = o[kr], arq = o[kq];
  o[kr] = active.select(c * arp - sn * arq, arp);
  o[kq] = active.select(sn * arp + c * arq, arq);
  for (int i = 0; i < 3; ++i) {
    const Lane vip = v[i][p], viq = v[i][q];
    v[i][p] = active.select(c * vip - sn * viq, vip);
    v[i][q] = active.select(sn * vip + c * viq, viq);
  }
}

// The Givens rotation of `givens` + `rotate` in rotation_variant_svd, every lane.
inline void givens_rotate(Lane (*R)[3], Lane (*U)[3], int p, int q, int col) {
  const Lane a = R[p][col], b = R[q][col];
  const Lane r = (a * a + b * b).sqrt();
  const auto zero = r == 0.0;
  const Lane c = zero.select(Lane::Ones(), a / r), sn = zero.select(Lane::Zero(), b / r);
  for (int k = 0; k < 3; ++k) {
    const Lane rp = R[p][k], rq = R[q][k];
    R[p][k] = c * rp + sn * rq;
    R[q][k] = -sn * rp + c * rq;
    const Lane up = U[k][p], uq = U[k][q];
    U[k][p] = c * up + sn * uq;
    U[k][q] = -sn * up + c * uq;
  }
}

}  // namespace

// flatten: Eigen's lane expressions are inlined into one loop-free body (left to the inliner,
// GCC kept ~10 of them as out-of-line calls, and the lanes were no faster than the scalar path)
#if defined(__GNUC__)
__attribute__((flatten))
#endif
void rotation_variant_svd_lanes(const Mat3* F, Mat3* U, Vec3* s, Mat3* V, int count) {
  constexpr int L = kSvdLanes;
  Lane d[3], o[3], v[3][3];
  for (int l = 0; l < L; ++l) {
    const Mat3 A = l < count ? Mat3(F[l].transpose() * F[l]) : Mat3::Identity();  // (padding)
    d[0][l] = A(0, 0), d[1][l] = A(1, 1), d[2][l] = A(2, 2);
    o[0][l] = A(0, 1), o[1][l] = A(0, 2), o[2][l] = A(1, 2);
  }
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) v[i][j].setConstant(i == j ? 1.0 : 0.0);
  const Lane scale = d[0] + d[1] + d[2];
  const Lane lim = 1e-34 * scale * scale;
  for (int sweep = 0; sweep < 12; ++sweep) {
    // the scalar loop's convergence test, once per sweep (a NaN lane is never on: it is
    // redone by the scalar path below, which sends it to its fallback)
    const LaneMask on = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] > lim;
    if (!on.any()) break;
    jacobi_rotate<0, 1, 0, 1, 2>(d, o, v, on);
    jacobi_rotate<0, 2, 1, 0, 2>(d, o, v, on);
    jacobi_rotate<1, 2, 2, 0, 1>(d, o, v, on);
  }
  Lane R[3][3], Ul[3][3];
  for (int l = 0; l < L; ++l) {
    Mat3 Vm;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) Vm(i, j) = v[i][j][l];
    order_columns(d[0][l], d[1][l], d[2][l], Vm);
    const Mat3 B = l < count ? Mat3(F[l] * Vm) : Mat3::Identity();
    if (l < count) V[l] = Vm;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) R[i][j][l] = B(i, j);
  }
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) Ul[i][j].setConstant(i == j ? 1.0 : 0.0);
  givens_rotate(R, Ul, 0, 1, 0);
  givens_rotate(R, Ul, 0, 2, 0);
  givens_rotate(R, Ul, 1, 2, 1);
  for (int l = 0; l < count; ++l) {
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) U[l](i, j) = Ul[i][j][l];
    s[l] = Vec3(R[0][0][l], R[1][1][l], R[2][2][l]);
    const double sc = scale[l];
    const double offR = std::abs(R[0][1][l]) + std::abs(R[0][2][l]) + std::abs(R[1][2][l]);
    if (!(sc > 0) || !std::isfinite(sc) || !clean(offR, s[l], sc))
      rotation_variant_svd(F[l], U[l], s[l], V[l]);  // the scalar path and its robust fallback
  }
}

}  // namespace matlearn::fem
