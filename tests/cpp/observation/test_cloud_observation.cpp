// Cloud observation: Gaussian weights, residual r_k = sum_n p_kn (c_n - s_k) / sigma^2 and its
// 3x3 Jacobian blocks (exact and weights-fixed) against central finite differences; targets;
// bad input throws InvalidInput.
#include <random>

#include "check.hpp"
#include "observation/cloud_observation.hpp"

using namespace matlearn;
namespace ob = matlearn::observation;

namespace {

struct Problem {
  MatX3 S, C;
  VecXi pk, pn;
  double sigma = 0.01;
};

/// Random surface points, cloud points scattered around them, and all pairs within 2.5 sigma
/// (below the truncation radius used, so finite differences never cross it).
Problem make_problem(unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-0.02, 0.02);
  std::normal_distribution<double> g(0.0, 0.006);
  Problem p;
  p.S.resize(10, 3);
  p.C.resize(50, 3);
  for (int i = 0; i < 10; ++i) p.S.row(i) << u(rng), u(rng), u(rng);
  for (int i = 0; i < 50; ++i) p.C.row(i) = p.S.row(i % 10) + Eigen::RowVector3d(g(rng), g(rng), g(rng));
  std::vector<int> k, n;
  for (int a = 0; a < 10; ++a)
    for (int b = 0; b < 50; ++b)
      if ((p.S.row(a) - p.C.row(b)).norm() < 2.5 * p.sigma) k.push_back(a), n.push_back(b);
  p.pk = Eigen::Map<VecXi>(k.data(), k.size());
  p.pn = Eigen::Map<VecXi>(n.data(), n.size());
  return p;
}

}  // namespace

TEST_CASE(residual_jacobian_blocks_match_finite_differences) {
  for (unsigned seed : {1u, 2u, 3u}) {
    Problem p = make_problem(seed);
    const double thr = std::exp(-0.5 * 9.0);  // truncation at 3 sigma: never reached
    const auto J = ob::cloud_residual_blocks(p.S, p.C, p.pk, p.pn, p.sigma, thr, true);
    const double eps = 1e-7;
    double scale = J.cwiseAbs().maxCoeff();
    for (int d = 0; d < 3; ++d) {
      MatX3 Sp = p.S, Sm = p.S;
      Sp.col(d).array() += eps;
      Sm.col(d).array() -= eps;
      const MatX3 fd = (ob::cloud_residual(Sp, p.C, p.pk, p.pn, p.sigma, thr) -
                        ob::cloud_residual(Sm, p.C, p.pk, p.pn, p.sigma, thr)) / (2 * eps);
      for (int k = 0; k < p.S.rows(); ++k)
        for (int r = 0; r < 3; ++r)
          CHECK_CLOSE(J(k, 3 * r + d) / scale, fd(k, r) / scale, 1e-5,
                      "seed " + std::to_string(seed) + " point " + std::to_string(k));
    }
    // Weights held fixed: -W_k / sigma^2 I.
    const auto Jf = ob::cloud_residual_blocks(p.S, p.C, p.pk, p.pn, p.sigma, thr, false);
    MatX3 mean;
    VecX W;
    ob::cloud_targets(p.S, p.C, p.pk, p.pn, p.sigma, thr, mean, W);
    for (int k = 0; k < p.S.rows(); ++k)
      for (int e = 0; e < 9; ++e)
        CHECK_CLOSE(Jf(k, e), (e % 4 == 0) ? -W[k] / (p.sigma * p.sigma) : 0.0, 1e-12, "fixed block");
  }
}

TEST_CASE(residual_equals_weighted_mean_offset) {
  Problem p = make_problem(7);
  const MatX3 R = ob::cloud_residual(p.S, p.C, p.pk, p.pn, p.sigma, 0.0);
  MatX3 mean;
  VecX W;
  ob::cloud_targets(p.S, p.C, p.pk, p.pn, p.sigma, 0.0, mean, W);
  for (int k = 0; k < p.S.rows(); ++k) {
    if (W[k] == 0) continue;
    for (int d = 0; d < 3; ++d)
      CHECK_CLOSE(R(k, d), W[k] * (mean(k, d) - p.S(k, d)) / (p.sigma * p.sigma), 1e-9, "r = W (m - s) / s^2");
  }
}

TEST_CASE(bad_input_throws) {
  Problem p = make_problem(1);
  VecXi short_pk = p.pk.head(p.pk.size() - 1);
  CHECK_THROWS(ob::cloud_weights(p.S, p.C, short_pk, p.pn, p.sigma, 0.0), InvalidInput);
  CHECK_THROWS(ob::cloud_weights(p.S, p.C, p.pk, p.pn, -1.0, 0.0), InvalidInput);
  VecXi bad = p.pk;
  bad[0] = 99;
  CHECK_THROWS(ob::cloud_residual(p.S, p.C, bad, p.pn, p.sigma, 0.0), InvalidInput);
}
