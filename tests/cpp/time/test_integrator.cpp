// Backward Euler: constrained stepping (prescribed vertices following the observed positions of
// an unconstrained run) reproduces the unconstrained trajectory; a static solve balances the
// load; errors are thrown with the step number.
#include "check.hpp"
#include "fixtures.hpp"
#include "correction/correction.hpp"
#include "time/integrator.hpp"

using namespace matlearn;
using namespace matlearn::fem;
using time::Integrator;

namespace {

const double kL = 0.2, kW = 0.04;

std::shared_ptr<Model> bar_model(MaterialModel m, DampingParams d = {}) {
  auto mesh = mltest::grid_mesh(6, 2, 2, kL, kW, kW);
  const int nt = mesh->num_tets();
  const double E = 2e5, nu = 0.4;
  return std::make_shared<Model>(mesh, m, VecX::Constant(nt, lame_mu(E, nu)),
                                 VecX::Constant(nt, lame_lambda(E, nu)), VecX::Constant(nt, 1000.0),
                                 std::vector<StretchEdit>{}, d);
}

VecXi clamped(const Model& M) {
  std::vector<int> idx;
  for (int i = 0; i < M.mesh().num_vertices(); ++i)
    if (M.mesh().vertices()(i, 0) < 1e-9) idx.push_back(i);
  return Eigen::Map<VecXi>(idx.data(), idx.size());
}

}  // namespace

TEST_CASE(constrained_stepping_reproduces_unconstrained_trajectory) {
  for (auto mm : {MaterialModel::Corotated, MaterialModel::NeoHookean}) {
    auto M = bar_model(mm, {0.5, 0.002, {}, {0.01}});
    const int nv = M->mesh().num_vertices();
    time::StepOptions o;
    o.max_newton = 30;
    o.tolerance = 1e-12;
    const Vec3 g(0, 0, -9.81);
    const double h = 2e-3;
    const int steps = 40;
    MatX3 f = MatX3::Zero(nv, 3);
    Integrator ref(M, clamped(*M), h, g, o);
    const MatX3 X = ref.simulate(steps, f, 1);  // ((steps+1) nv x 3)
    // Observe every other vertex of the free ones (sparse observations).
    const VecXi fixed = clamped(*M);
    std::vector<int> obs;
    for (int i = 0; i < nv; ++i)
      if (M->mesh().vertices()(i, 0) > 1e-9 && i % 2 == 0) obs.push_back(i);
    const VecXi P = Eigen::Map<VecXi>(obs.data(), obs.size());
    MatX3 targets(steps * P.size(), 3);
    for (int s = 0; s < steps; ++s)
      for (int k = 0; k < P.size(); ++k) targets.row(s * P.size() + k) = X.row((s + 1) * nv + P[k]);
    Integrator con(M, fixed, h, g, o);
    con.set_prescribed(P);
    const MatX3 Y = con.simulate_constrained(targets, f);
    CHECK(Y.rows() == X.rows());
    const double tip = (X.bottomRows(nv) - X.topRows(nv)).cwiseAbs().maxCoeff();
    CHECK_MSG(tip > 1e-4, "the reference run should move (max displacement " + std::to_string(tip) + ")");
    const double err = (Y - X).cwiseAbs().maxCoeff();
    CHECK_MSG(err <= 1e-8 * tip, to_string(mm) + ": constrained run differs by " +
                                     std::to_string(err) + " m (motion " + std::to_string(tip) + " m)");
  }
}

TEST_CASE(static_solve_balances_gravity) {
  auto M = bar_model(MaterialModel::NeoHookean);
  const int nv = M->mesh().num_vertices();
  const VecXi fixed = clamped(*M);
  Integrator I(M, fixed, 1e-3, Vec3(0, 0, -9.81));
  I.static_solve(MatX3::Zero(nv, 3), 2);
  const VecX f = M->forces(I.x(), MatX3::Zero(nv, 3));
  // Free vertices: internal force balances weight; clamp reactions carry the total weight.
  Vec3 reaction = Vec3::Zero();
  std::vector<bool> is_fixed(nv, false);
  for (int i = 0; i < fixed.size(); ++i) is_fixed[fixed[i]] = true;
  const double weight = M->vertex_mass().sum() * 9.81;
  for (int i = 0; i < nv; ++i) {
    const Vec3 r = f.segment<3>(3 * i) + M->vertex_mass()[i] * Vec3(0, 0, -9.81);
    if (is_fixed[i])
      reaction += r;
    else
      CHECK_MSG(r.norm() <= 1e-6 * weight, "vertex " + std::to_string(i) + " unbalanced");
  }
  CHECK_CLOSE(reaction[2], -weight, 1e-6, "clamp reaction");
  CHECK(I.x().col(2).minCoeff() < M->mesh().vertices().col(2).minCoeff());  // it sagged
}

TEST_CASE(divergence_reports_the_step) {
  auto M = bar_model(MaterialModel::Corotated);
  const int nv = M->mesh().num_vertices();
  Integrator I(M, clamped(*M), 1e-3, Vec3::Zero());
  MatX3 x = M->mesh().vertices();
  MatX3 v = MatX3::Zero(nv, 3);
  v(nv - 1, 0) = std::nan("");
  CHECK_THROWS(I.set_state(x, v), InvalidInput);
  CHECK_THROWS(I.step(MatX3::Zero(nv + 1, 3)), InvalidInput);
  VecXi bad(1);
  bad << nv;
  CHECK_THROWS(Integrator(M, bad, 1e-3, Vec3::Zero()), InvalidInput);
  CHECK_THROWS(Integrator(M, clamped(*M), -1.0, Vec3::Zero()), InvalidInput);
  // Prescribed vertices need targets of the right shape.
  I.set_prescribed(VecXi::Constant(1, nv - 1));
  CHECK_THROWS(I.step(MatX3::Zero(nv, 3)), InvalidInput);
}

TEST_CASE(unconverged_steps_are_counted) {
  // A bar pulled hard at its tip: at h = 10 ms two Newton iteration cannot meet a 1e-12
  // tolerance (the co-rotated tangent changes with the rotation), thirty can; a linearised
  // integrator (max_newton = 1) never counts; set_state starts a new count.
  auto M = bar_model(MaterialModel::Corotated);
  const int nv = M->mesh().num_vertices();
  MatX3 f = MatX3::Zero(nv, 3);
  for (int i = 0; i < nv; ++i)
    if (M->mesh().vertices()(i, 0) > kL - 1e-9) f(i, 2) = 0.5;
  const MatX3 x0 = M->mesh().vertices(), v0 = MatX3::Zero(nv, 3);
  auto run = [&](int max_newton, double tol) {
    time::StepOptions o;
    o.max_newton = max_newton;
    o.tolerance = tol;
    Integrator I(M, clamped(*M), 1e-2, Vec3::Zero(), o);
    I.set_state(x0, v0);
    I.simulate(10, f, 10);
    const int n = I.unconverged_steps();
    I.set_state(x0, v0);
    CHECK(I.unconverged_steps() == 0);
    return n;
  };
  const int tight = run(2, 1e-12), loose = run(30, 1e-7), linear = run(1, 1e-12);
  CHECK_MSG(tight > 0, "2 Newton iterations at tolerance 1e-12 should leave steps unconverged");
  CHECK_MSG(loose == 0, std::to_string(loose) + " steps unconverged with 30 iterations");
  CHECK_MSG(linear == 0, "max_newton = 1 counted " + std::to_string(linear) + " steps");
}

namespace {
/// A correction that is identically zero: forces the general (correction) assembly path.
struct ZeroCorrection final : correction::Correction {
  void evaluate(const MatX3& Fh, const MatX3&, correction::CorrectionOutput& out) const override {
    const int m = Fh.rows();
    out.dPh.setZero(m, 3);
    out.d_dFh.assign(m, Mat3::Zero());
    out.d_dFhdot.assign(m, Mat3::Zero());
    out.dalpha.setZero(m);
  }
};
}  // namespace

TEST_CASE(rayleigh_fast_path_matches_general_assembly) {
  // Without a correction the system matrix is assembled from K with per-element coefficients;
  // with a (zero) correction it goes through the general K + D assembly. Same trajectory.
  DampingParams d{0.8, 0.004, {0.3}, {0.02, -0.01}};
  auto A = bar_model(MaterialModel::NeoHookean, d);
  auto B = bar_model(MaterialModel::NeoHookean, d);
  B->set_correction(std::make_shared<ZeroCorrection>());
  const int nv = A->mesh().num_vertices();
  MatX3 f = MatX3::Zero(nv, 3);
  f(nv - 1, 2) = -0.5;
  // Refactorise at every iteration (no reuse), so that every iteration compares the assemblies.
  time::StepOptions newton;
  newton.reuse_factorization = false;
  Integrator IA(A, clamped(*A), 2e-3, Vec3(0, 0, -9.81), newton),
      IB(B, clamped(*B), 2e-3, Vec3(0, 0, -9.81), newton);
  const MatX3 XA = IA.simulate(30, f, 1), XB = IB.simulate(30, f, 1);
  const double motion = (XA.bottomRows(nv) - XA.topRows(nv)).cwiseAbs().maxCoeff();
  CHECK(motion > 1e-4);
  CHECK_MSG((XA - XB).cwiseAbs().maxCoeff() <= 1e-10 * motion,
            "paths differ by " + std::to_string((XA - XB).cwiseAbs().maxCoeff()));
  CHECK(IA.last_timings().iterations >= 1 && IA.last_timings().factorize_s > 0);
  CHECK(IA.last_timings().factorizations == IA.last_timings().iterations);
}
