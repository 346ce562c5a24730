#include "observation/cloud_observation.hpp"

#include <cmath>
#include <limits>
#include <string>

namespace matlearn::observation {

namespace {

void check(const MatX3& S, const MatX3& C, const VecXi& pk, const VecXi& pn, double sigma,
           double threshold) {
  if (pk.size() != pn.size())
    throw InvalidInput("pair_point and pair_cloud must have the same length (" +
                       std::to_string(pk.size()) + " vs " + std::to_string(pn.size()) + ")");
  if (!(sigma > 0)) throw InvalidInput("sigma must be > 0, got " + std::to_string(sigma));
  if (!(threshold >= 0 && threshold < 1))
    throw InvalidInput("threshold must lie in [0, 1), got " + std::to_string(threshold));
  for (Eigen::Index p = 0; p < pk.size(); ++p) {
    if (pk[p] < 0 || pk[p] >= S.rows())
      throw InvalidInput("pair_point[" + std::to_string(p) + "] = " + std::to_string(pk[p]) +
                         " out of range [0, " + std::to_string(S.rows()) + ")");
    if (pn[p] < 0 || pn[p] >= C.rows())
      throw InvalidInput("pair_cloud[" + std::to_string(p) + "] = " + std::to_string(pn[p]) +
                         " out of range [0, " + std::to_string(C.rows()) + ")");
  }
}

/// Weight of one pair and its offset d = c_n - s_k.
inline double pair_weight(const MatX3& S, const MatX3& C, int k, int n, double inv2s2,
                          double threshold, Vec3& d) {
  d = (C.row(n) - S.row(k)).transpose();
  const double p = std::exp(-d.squaredNorm() * inv2s2);
  return p < threshold ? 0.0 : p;
}

}  // namespace

VecX cloud_weights(const MatX3& S, const MatX3& C, const VecXi& pk, const VecXi& pn, double sigma,
                   double threshold) {
  check(S, C, pk, pn, sigma, threshold);
  const double inv2s2 = 0.5 / (sigma * sigma);
  VecX p(pk.size());
  Vec3 d;
  for (Eigen::Index i = 0; i < pk.size(); ++i) p[i] = pair_weight(S, C, pk[i], pn[i], inv2s2, threshold, d);
  return p;
}

MatX3 cloud_weight_gradients(const MatX3& S, const MatX3& C, const VecXi& pk, const VecXi& pn,
                             double sigma, double threshold) {
  check(S, C, pk, pn, sigma, threshold);
  const double inv2s2 = 0.5 / (sigma * sigma), invs2 = 1.0 / (sigma * sigma);
  MatX3 G(pk.size(), 3);
  Vec3 d;
  for (Eigen::Index i = 0; i < pk.size(); ++i) {
    const double p = pair_weight(S, C, pk[i], pn[i], inv2s2, threshold, d);
    G.row(i) = (p * invs2) * d.transpose();
  }
  return G;
}

MatX3 cloud_residual(const MatX3& S, const MatX3& C, const VecXi& pk, const VecXi& pn, double sigma,
                     double threshold) {
  check(S, C, pk, pn, sigma, threshold);
  const double inv2s2 = 0.5 / (sigma * sigma), invs2 = 1.0 / (sigma * sigma);
  MatX3 R = MatX3::Zero(S.rows(), 3);
  Vec3 d;
  // Serial scatter: pairs of one surface point may be spread over the list.
  for (Eigen::Index i = 0; i < pk.size(); ++i) {
    const double p = pair_weight(S, C, pk[i], pn[i], inv2s2, threshold, d);
    if (p > 0) R.row(pk[i]) += (p * invs2) * d.transpose();
  }
  return R;
}

Eigen::Matrix<double, Eigen::Dynamic, 9, Eigen::RowMajor> cloud_residual_blocks(
    const MatX3& S, const MatX3& C, const VecXi& pk, const VecXi& pn, double sigma, double threshold,
    bool full) {
  check(S, C, pk, pn, sigma, threshold);
  const double inv2s2 = 0.5 / (sigma * sigma), invs2 = 1.0 / (sigma * sigma);
  Eigen::Matrix<double, Eigen::Dynamic, 9, Eigen::RowMajor> J =
      Eigen::Matrix<double, Eigen::Dynamic, 9, Eigen::RowMajor>::Zero(S.rows(), 9);
  Vec3 d;
  for (Eigen::Index i = 0; i < pk.size(); ++i) {
    const double p = pair_weight(S, C, pk[i], pn[i], inv2s2, threshold, d);
    if (p == 0) continue;
    Mat3 b = -p * invs2 * Mat3::Identity();
    if (full) b += (p * invs2 * invs2) * d * d.transpose();
    Eigen::Map<Eigen::Matrix<double, 1, 9>>(J.row(pk[i]).data()) +=
        Eigen::Map<const Eigen::Matrix<double, 1, 9>>(Eigen::Matrix<double, 3, 3, Eigen::RowMajor>(b).data());
  }
  return J;
}

void cloud_targets(const MatX3& S, const MatX3& C, const VecXi& pk, const VecXi& pn, double sigma,
                   double threshold, MatX3& mean, VecX& W) {
  check(S, C, pk, pn, sigma, threshold);
  const double inv2s2 = 0.5 / (sigma * sigma);
  mean = MatX3::Zero(S.rows(), 3);
  W = VecX::Zero(S.rows());
  Vec3 d;
  for (Eigen::Index i = 0; i < pk.size(); ++i) {
    const double p = pair_weight(S, C, pk[i], pn[i], inv2s2, threshold, d);
    if (p == 0) continue;
    mean.row(pk[i]) += p * C.row(pn[i]);
    W[pk[i]] += p;
  }
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (Eigen::Index k = 0; k < S.rows(); ++k) {
    if (W[k] > 0)
      mean.row(k) /= W[k];
    else
      mean.row(k).setConstant(nan);
  }
}

}  // namespace matlearn::observation
