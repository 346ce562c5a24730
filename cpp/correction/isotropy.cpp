#include "correction/isotropy.hpp"

#include <cmath>

namespace matlearn::correction {

bool isotropic_blend(const Vec3& s, double w, Vec3& p, Mat3* J, Mat3* Jdot) {
  static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
  constexpr double kCap = 1e8;
  double k[3], dk[3], sg[3];
  bool any = false;
  for (int q = 0; q < 3; ++q) {
    const double diff = s[pairs[q][0]] - s[pairs[q][1]], d = std::abs(diff);
    sg[q] = diff < 0 ? -1.0 : 1.0;
    k[q] = dk[q] = 0.0;
    if (!(d < w)) continue;
    any = true;
    const double r = d > 0 ? (w / d) * (w / d) - 1.0 : 0.0;
    if (d == 0 || r * r >= kCap) {
      k[q] = kCap;  // (the dropped derivative term is ~ p-gap * d^3 / w^4: negligible here)
    } else {
      k[q] = r * r;
      dk[q] = -4.0 * r * w * w / (d * d * d);
    }
  }
  if (!any) return false;
  Mat3 A = Mat3::Identity();
  Vec3 l[3];
  for (int q = 0; q < 3; ++q) {
    l[q] = Vec3::Zero();
    l[q][pairs[q][0]] = 1.0;
    l[q][pairs[q][1]] = -1.0;
    A += k[q] * l[q] * l[q].transpose();
  }
  const Mat3 S = A.inverse();  // symmetric positive definite, eigenvalues in [1, 1 + 3 kCap]
  // S keeps constants (L 1 = 0), so only the deviation from the mean changes; the projector Z
  // onto zero-mean vectors removes what round-off in S (condition up to ~3e8) leaks into the mean.
  const Mat3 Z = Mat3::Identity() - Mat3::Constant(1.0 / 3.0);
  const Mat3 M = Mat3::Constant(1.0 / 3.0);
  const double mean = p.mean();
  p = Vec3::Constant(mean) + Z * (S * (p - Vec3::Constant(mean)));
  if (J) {
    Mat3 Jn = S * *J;
    for (int q = 0; q < 3; ++q)
      if (dk[q] != 0.0) Jn -= (dk[q] * sg[q] * l[q].dot(p)) * (S * l[q]) * l[q].transpose();
    *J = M * *J + Z * Jn;
  }
  if (Jdot) *Jdot = M * *Jdot + Z * (S * *Jdot);
  return true;
}

}  // namespace matlearn::correction
