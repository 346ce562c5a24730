// Forward-mode (tangent) sensitivities of the linearised replay with respect to per-element
// log-stiffness changes; see LinearisedReplay::tangent.
//
// One linearised step (free DOFs): v^ = v_s with clamped rows zeroed (prescribed rows: the
// velocity to their target, which does not depend on theta), x = x_s + h v^,
//   A dv = h (f(x, v^) + f_const),  A = M + h D + h^2 K,  v_{s+1} = v^ + dv,  x_{s+1} = x_s + h v_{s+1},
// with K the projected tangent stiffness and D = alpha_K K + alpha_M M per element. Its
// derivative for theta (element log-stiffness) along a direction d, holding A's dependence on
// the state fixed:
//   A ddv = -K_t (h dx + h^2 dv^) - h alpha_K K dv^ - h alpha_M M dv^ + sum_e d_e (h f_e - c_e K_e dv_e),
// where K_t is the true (unprojected) tangent (the force is evaluated exactly, only the step
// matrix uses the projected one), f_e is element e's force that scales with its stiffness
// (elastic + stiffness damping) and c_e = h^2 + h alpha_K,e (dA/dtheta_e = c_e K_e). The
// x-derivative of the stiffness-damping force's tangent is dropped with A's.
#include <cmath>
#include <sstream>

#include "time/integrator.hpp"
#include "time/linearised_replay.hpp"

namespace matlearn::time {

namespace {
using RowMat = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using Mat12X = Eigen::Matrix<double, 12, Eigen::Dynamic>;
}  // namespace

MatX3 LinearisedReplay::tangent(const fem::Model& model, const MatX3& x0_in, const MatX3& v0_in,
                                int steps, const MatX3& f_ext, const MatX& dx0,
                                const MatX& directions, const MatX4i& point_vertices,
                                const MatX4& point_weights, double* out, const MatX3* targets) {
  if (model.mesh().num_vertices() != nv_ || model.mesh().num_tets() != nt_)
    throw InvalidInput("LinearisedReplay::tangent: the model's mesh differs from the replay's");
  if (model.correction() != nullptr || !model.edits().empty())
    throw InvalidInput("LinearisedReplay::tangent: needs a model without correction and stretch edits");
  if (steps < 0) throw InvalidInput("steps must be >= 0");
  check_targets(targets, steps);
  if (f_ext.rows() != nv_) throw InvalidInput("f_ext must have shape (#V, 3)");
  const int k = static_cast<int>(directions.cols());
  if (directions.rows() != nt_) throw InvalidInput("directions must have shape (#T, k)");
  if (dx0.rows() != 3 * nv_ || dx0.cols() != k) throw InvalidInput("dx0 must have shape (3 #V, k)");
  if (point_weights.rows() != point_vertices.rows())
    throw InvalidInput("point_vertices and point_weights must have the same number of rows");
  if (point_vertices.size() && (point_vertices.minCoeff() < 0 || point_vertices.maxCoeff() >= nv_))
    throw InvalidInput("point vertex index out of range");
  if (!directions.allFinite() || !dx0.allFinite()) throw InvalidInput("directions or dx0 contain NaN or Inf");
  model.check_state(x0_in, "x");
  model.check_state(v0_in, "v");
  const auto& T = model.mesh().tets();
  const VecX& W = model.mesh().volumes();
  const VecX& rho = model.density();
  const VecX& mass = model.dof_mass();
  const long P = point_vertices.rows();
  VecX fconst = as_dofs(f_ext);
  for (int i = 0; i < nv_; ++i) fconst.segment<3>(3 * i) += mass[3 * i] * gravity_;
  const RowMat dirs = directions;
  RowMat dX = dx0, dV = RowMat::Zero(3 * nv_, k);
  for (int d = 0; d < 3 * nv_; ++d)
    if (dof_map_[d] < 0) dX.row(d).setZero();
  auto record = [&](int s) {
    double* o = out + static_cast<long>(s) * P * 3 * k;
    for (long p = 0; p < P; ++p)
      for (int d = 0; d < 3; ++d) {
        auto row = Eigen::Map<Eigen::RowVectorXd>(o + (p * 3 + d) * k, k);
        row.setZero();
        for (int a = 0; a < 4; ++a) row += point_weights(p, a) * dX.row(3 * point_vertices(p, a) + d);
      }
  };
  MatX3 pos((steps + 1) * nv_, 3);
  MatX3 xs = x0_in, vs = v0_in;
  pos.topRows(nv_) = xs;
  record(0);
  fem::ElementState st, st_true;
  Mat12X Y(12, k), Z(12, k), Re(12, k);
  RowMat R(3 * nv_, k);
  MatX Rf(n_free_, k);
  for (int s = 0; s < steps; ++s) {
    MatX3 v = vs;
    start_velocity(xs, targets, s, v);
    const MatX3 x = xs + h_ * v;
    try {
      model.evaluate(x, v, fem::kForce | fem::kStiffness, true, st);
      model.evaluate(x, v, fem::kStiffness, false, st_true);
    } catch (const NumericalError& err) {
      std::ostringstream os;
      os << "step " << s << ", Newton iteration 0: " << err.what();
      throw NumericalError(os.str());
    }
    const VecX g = step_residual(model, st, v, vs, mass, fconst);
    assemble_step_matrix(model, st, h_, mass, true, *assembler_, coeff_, diag_, A_);
    factorize_at(s);
    const VecX dv = solver_.solve(-g);
    VecX dv_full = VecX::Zero(3 * nv_);
    for (int d = 0; d < 3 * nv_; ++d)
      if (dof_map_[d] >= 0) dv_full[d] = dv[dof_map_[d]];
    // tangent right-hand sides, element by element (dV's clamped and prescribed rows are zero: dV = dv^)
    R.setZero();
    for (int e = 0; e < nt_; ++e) {
      const double c = h_ * h_ + h_ * st.alpha_K[e];
      const double cm = st.alpha_M[e] * rho[e] * W[e] / 4.0;
      Vec12 ve, dve;
      for (int a = 0; a < 4; ++a) {
        const int vi = T(e, a);
        for (int d = 0; d < 3; ++d) {
          Y.row(3 * a + d) = h_ * dX.row(3 * vi + d) + (h_ * h_) * dV.row(3 * vi + d);
          Z.row(3 * a + d) = dV.row(3 * vi + d);
          ve[3 * a + d] = v(vi, d);
          dve[3 * a + d] = dv_full[3 * vi + d];
        }
      }
      const Vec12 fth = st.f[e] + cm * ve;  // elastic + stiffness damping (no mass damping)
      const Vec12 a_e = h_ * fth - c * (st.K[e] * dve);
      Re.noalias() = -st_true.K[e] * Y;
      Re.noalias() -= (h_ * st.alpha_K[e]) * (st.K[e] * Z);
      Re -= (h_ * cm) * Z;
      Re.noalias() += a_e * dirs.row(e);
      for (int a = 0; a < 4; ++a)
        for (int d = 0; d < 3; ++d) R.row(3 * T(e, a) + d) += Re.row(3 * a + d);
    }
    for (int d = 0; d < 3 * nv_; ++d)
      if (dof_map_[d] >= 0) Rf.row(dof_map_[d]) = R.row(d);
    const MatX ddv = solver_.solve_many(Rf);
    if (!ddv.allFinite()) {
      std::ostringstream os;
      os << "step " << s << ": tangent solve produced NaN";
      throw NumericalError(os.str());
    }
    for (int d = 0; d < 3 * nv_; ++d)
      if (dof_map_[d] >= 0) dV.row(d) += ddv.row(dof_map_[d]);
    dX += h_ * dV;
    advance(dv, s, v, vs, xs);
    place_prescribed(targets, s, xs);
    ++stats_.steps;
    pos.middleRows((s + 1) * nv_, nv_) = xs;
    record(s + 1);
  }
  return pos;
}

}  // namespace matlearn::time
