// LinearisedReplay: the linearised step equals the integrator's with one Newton iteration, with
// clamped and with prescribed (driven) vertices; bad targets are rejected.
#include "check.hpp"
#include "fixtures.hpp"
#include "time/integrator.hpp"
#include "time/linearised_replay.hpp"

using namespace matlearn;
using namespace matlearn::fem;
using time::Integrator;
using time::LinearisedReplay;

namespace {

const double kL = 0.2, kW = 0.04;

std::shared_ptr<Model> bar_model() {
  auto mesh = mltest::grid_mesh(6, 2, 2, kL, kW, kW);
  const int nt = mesh->num_tets();
  const double E = 2e5, nu = 0.4;
  return std::make_shared<Model>(mesh, MaterialModel::Corotated, VecX::Constant(nt, lame_mu(E, nu)),
                                 VecX::Constant(nt, lame_lambda(E, nu)), VecX::Constant(nt, 1000.0),
                                 std::vector<StretchEdit>{}, DampingParams{0.5, 0.002, {}, {}});
}

VecXi vertices_where(const Model& M, double x_lo, double x_hi) {
  std::vector<int> idx;
  for (int i = 0; i < M.mesh().num_vertices(); ++i) {
    const double x = M.mesh().vertices()(i, 0);
    if (x >= x_lo && x <= x_hi) idx.push_back(i);
  }
  return Eigen::Map<VecXi>(idx.data(), idx.size());
}

}  // namespace

TEST_CASE(driven_linearised_replay_equals_the_one_newton_integrator) {
  auto M = bar_model();
  const int nv = M->mesh().num_vertices();
  const VecXi fixed = vertices_where(*M, -1.0, 1e-9), tip = vertices_where(*M, kL - 1e-9, 1.0);
  const double h = 2e-3;
  const int steps = 30;
  const Vec3 g(0, 0, -9.81);
  MatX3 targets(steps * tip.size(), 3);
  for (int s = 0; s < steps; ++s)
    for (int k = 0; k < tip.size(); ++k)
      targets.row(s * tip.size() + k) =
          M->mesh().vertices().row(tip[k]) + 0.01 * std::sin(0.2 * (s + 1)) * Eigen::RowVector3d(0.2, 1.0, 0.5);
  time::StepOptions o;
  o.max_newton = 1;
  Integrator ref(M, fixed, h, g, o);
  ref.set_prescribed(tip);
  const MatX3 X = ref.simulate_constrained(targets, MatX3::Zero(nv, 3));
  LinearisedReplay R(*M, fixed, h, g, 1e-12, 10, 40, tip);
  const MatX3 Y = R.simulate(*M, M->mesh().vertices(), MatX3::Zero(nv, 3), steps, MatX3::Zero(nv, 3),
                             nullptr, &targets);
  CHECK(Y.rows() == X.rows());
  const double motion = (X.bottomRows(nv) - X.topRows(nv)).cwiseAbs().maxCoeff();
  CHECK_MSG(motion > 1e-3, "the driven run should move");
  const double err = (Y - X).cwiseAbs().maxCoeff();
  CHECK_MSG(err <= 1e-9 * motion, "linearised replay differs by " + std::to_string(err) + " m");
  for (int k = 0; k < tip.size(); ++k)  // the driven vertices end each step at their targets
    CHECK((Y.row(steps * nv + tip[k]) - targets.row((steps - 1) * tip.size() + k)).norm() == 0.0);
  // a clamped-only replay of the same start does not follow the drive
  LinearisedReplay free(*M, fixed, h, g);
  const MatX3 Z = free.simulate(*M, M->mesh().vertices(), MatX3::Zero(nv, 3), steps, MatX3::Zero(nv, 3));
  CHECK((Z - X).cwiseAbs().maxCoeff() > 0.1 * motion);
}

TEST_CASE(driven_replay_rejects_bad_targets) {
  auto M = bar_model();
  const int nv = M->mesh().num_vertices();
  const VecXi fixed = vertices_where(*M, -1.0, 1e-9), tip = vertices_where(*M, kL - 1e-9, 1.0);
  LinearisedReplay R(*M, fixed, 1e-3, Vec3::Zero(), 1e-10, 10, 40, tip);
  const MatX3 x = M->mesh().vertices(), v = MatX3::Zero(nv, 3), f = MatX3::Zero(nv, 3);
  CHECK_THROWS(R.simulate(*M, x, v, 2, f), InvalidInput);  // no targets
  MatX3 short_targets(tip.size(), 3);
  short_targets.setZero();
  CHECK_THROWS(R.simulate(*M, x, v, 2, f, nullptr, &short_targets), InvalidInput);
  MatX3 nan_targets = MatX3::Zero(2 * tip.size(), 3);
  nan_targets(0, 0) = std::nan("");
  CHECK_THROWS(R.simulate(*M, x, v, 2, f, nullptr, &nan_targets), InvalidInput);
  LinearisedReplay clamped_only(*M, fixed, 1e-3, Vec3::Zero());
  MatX3 t2 = MatX3::Zero(2 * tip.size(), 3);
  CHECK_THROWS(clamped_only.simulate(*M, x, v, 2, f, nullptr, &t2), InvalidInput);  // nothing to drive
  CHECK_THROWS(LinearisedReplay(*M, fixed, 1e-3, Vec3::Zero(), 1e-10, 10, 40, fixed), InvalidInput);
}


