// Normal equations of the correction fit (cpp/learning/fit_normal_equations.*): forces generated
// by a known RbfCorrection (clamped box, elastic + damping parts) are reproduced exactly by the
// true parameter vector, i.e. the least-squares residual |y - D theta_true|^2 computed from
// (N, rhs, y^T y) vanishes; the same holds with the correction passed as the current model and
// zero control forces, and with a basis instead of the free-DOF selection. N is symmetric.
#include <random>

#include "check.hpp"
#include "correction/correction.hpp"
#include "fem/model.hpp"
#include "fixtures.hpp"
#include "learning/fit_normal_equations.hpp"

using namespace matlearn;
using namespace matlearn::fem;

namespace {

const double kL = 0.2, kW = 0.04;

std::shared_ptr<Model> make_model() {
  auto mesh = mltest::grid_mesh(4, 2, 2, kL, kW, kW);
  const int nt = mesh->num_tets();
  DampingParams d;
  d.alpha_stiffness = 0.05;
  return std::make_shared<Model>(mesh, MaterialModel::Corotated, VecX::Constant(nt, 4e4),
                                 VecX::Constant(nt, 1e5), VecX::Constant(nt, 1000.0),
                                 std::vector<StretchEdit>{}, d);
}

double kernel(const Vec3& s, const Vec3& c, double eps) { return std::sqrt((s - c).squaredNorm() + eps * eps); }

}  // namespace

TEST_CASE(true_parameters_have_zero_residual) {
  auto nominal = make_model();
  const int n = nominal->mesh().num_vertices(), c = 6;
  std::mt19937 rng(3);
  std::normal_distribution<double> g(0, 1);
  learning::RbfFeatures rbf;
  rbf.centers.resize(c, 3);
  for (int i = 0; i < rbf.centers.size(); ++i) rbf.centers.data()[i] = 1.0 + 0.04 * g(rng);
  rbf.epsilon = 0.05;
  rbf.lower = Vec3::Constant(0.97);  // tighter than the motion: clamping is exercised
  rbf.upper = Vec3::Constant(1.03);
  MatX3 W(c, 3);
  for (int i = 0; i < W.size(); ++i) W.data()[i] = 2e4 * g(rng);
  Mat3 A;
  for (int i = 0; i < 9; ++i) A.data()[i] = 5e4 * g(rng);
  VecX wa(c);
  for (int i = 0; i < c; ++i) wa[i] = 0.02 * g(rng);
  const double a0 = 0.004;
  // Bias tied to the weights: zero correction at rest (the fit's parametrisation).
  Vec3 b = Vec3::Zero();
  const Vec3 one = Vec3::Ones().cwiseMax(rbf.lower).cwiseMin(rbf.upper);
  for (int k = 0; k < c; ++k) b -= W.row(k).transpose() * kernel(one, rbf.centers.row(k).transpose(), rbf.epsilon);
  // Keep alpha_K + dalpha > 0 everywhere on the states (no passivity clamp in the data).
  auto corr = std::make_shared<correction::RbfCorrection>(rbf.centers, W, A, b, 0.1 * wa, a0,
                                                          rbf.epsilon, rbf.lower, rbf.upper);
  auto truth = std::make_shared<Model>(*nominal);
  truth->set_correction(corr);

  const int frames = 3;
  MatX3 X(frames * n, 3), V(frames * n, 3), FC(frames * n, 3), Z = MatX3::Zero(frames * n, 3);
  for (int j = 0; j < frames; ++j) {
    MatX3 x = nominal->mesh().vertices(), v(n, 3);
    for (int i = 0; i < n; ++i) {
      const double t = x(i, 0) / kL;
      x(i, 0) *= 1.0 + 0.04 * (j + 1);
      x(i, 1) += 0.1 * kL * t * t * (j - 1);
      for (int k = 0; k < 3; ++k) {
        x(i, k) += 0.002 * kW * g(rng);
        v(i, k) = 0.05 * g(rng);
      }
    }
    X.middleRows(j * n, n) = x;
    V.middleRows(j * n, n) = v;
    const VecX f = truth->forces(x, v) - nominal->forces(x, v);
    FC.middleRows(j * n, n) = Eigen::Map<const MatX3>(f.data(), n, 3);
  }
  VecX theta(3 * (c + 3) + c + 1);
  for (int k = 0; k < 3; ++k) {
    theta.segment(k * (c + 3), c) = W.col(k);
    theta.segment(k * (c + 3) + c, 3) = A.row(k).transpose();
  }
  theta.segment(3 * (c + 3), c) = 0.1 * wa;
  theta[3 * (c + 3) + c] = a0;

  Eigen::Matrix<bool, Eigen::Dynamic, 1> all = Eigen::Matrix<bool, Eigen::Dynamic, 1>::Constant(3 * n, true);
  MatX phi(3 * n, 8);
  for (int i = 0; i < phi.size(); ++i) phi.data()[i] = g(rng);
  struct Case { const char* name; const Model* current; const MatX3* fc; const MatX* phi; };
  const MatX none;
  for (const Case& cs : {Case{"control forces", nullptr, &FC, &none},
                         Case{"current correction", truth.get(), &Z, &none},
                         Case{"basis", nullptr, &FC, &phi}}) {
    const auto ne = learning::fit_normal_equations(*nominal, cs.current, X, V, *cs.fc, *cs.phi,
                                                   all, rbf, true);
    CHECK(ne.frames == frames);
    CHECK_MSG(ne.yy > 0, cs.name);
    const double res = ne.yy - 2 * theta.dot(ne.rhs) + theta.dot(ne.N * theta);
    CHECK_MSG(std::abs(res) <= 1e-9 * ne.yy, std::string(cs.name) + ": residual " + std::to_string(res / ne.yy));
    CHECK_MSG((ne.N - ne.N.transpose()).norm() <= 1e-12 * ne.N.norm(), cs.name);
  }
}

TEST_CASE(bad_input_is_rejected) {
  auto M = make_model();
  const int n = M->mesh().num_vertices();
  learning::RbfFeatures rbf;
  rbf.centers = MatX3::Ones(2, 3);
  const MatX3 X = M->mesh().vertices(), V = MatX3::Zero(n, 3);
  Eigen::Matrix<bool, Eigen::Dynamic, 1> all = Eigen::Matrix<bool, Eigen::Dynamic, 1>::Constant(3 * n, true);
  CHECK_THROWS(learning::fit_normal_equations(*M, nullptr, X, V, MatX3::Zero(n + 1, 3), MatX(), all, rbf, true),
               InvalidInput);
  rbf.lower = Vec3::Ones();
  CHECK_THROWS(learning::fit_normal_equations(*M, nullptr, X, V, V, MatX(), all, rbf, true), InvalidInput);
}
