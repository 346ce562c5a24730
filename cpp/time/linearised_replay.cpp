#include "time/linearised_replay.hpp"

#include "time/integrator.hpp"

#include <cmath>
#include <sstream>

namespace matlearn::time {

LinearisedReplay::LinearisedReplay(const fem::Model& mesh_model, const VecXi& fixed,
                                   double time_step, const Vec3& gravity, double tolerance,
                                   int refresh_iterations, int max_iterations, const VecXi& prescribed)
    : fixed_(fixed),
      prescribed_(prescribed),
      nv_(mesh_model.mesh().num_vertices()),
      nt_(mesh_model.mesh().num_tets()),
      h_(time_step),
      tol_(tolerance),
      refresh_(refresh_iterations),
      max_it_(max_iterations),
      gravity_(gravity) {
  if (!(h_ > 0) || !std::isfinite(h_)) throw InvalidInput("time_step must be a positive number (s)");
  if (!gravity_.allFinite()) throw InvalidInput("gravity contains NaN or Inf");
  if (!(tol_ > 0) || tol_ >= 1) throw InvalidInput("tolerance must lie in (0, 1)");
  if (refresh_ < 1 || max_it_ < refresh_) throw InvalidInput("need 1 <= refresh_iterations <= max_iterations");
  if (fixed_.size() && (fixed_.minCoeff() < 0 || fixed_.maxCoeff() >= nv_))
    throw InvalidInput("fixed vertex index out of range [0, " + std::to_string(nv_) + ")");
  const auto& X = mesh_model.mesh().vertices();
  size_ = (X.colwise().maxCoeff() - X.colwise().minCoeff()).norm();
  if (prescribed_.size() && (prescribed_.minCoeff() < 0 || prescribed_.maxCoeff() >= nv_))
    throw InvalidInput("prescribed vertex index out of range [0, " + std::to_string(nv_) + ")");
  dof_map_ = VecXi::Zero(3 * nv_);
  for (int i = 0; i < fixed_.size(); ++i) dof_map_.segment<3>(3 * fixed_[i]).setConstant(-1);
  for (int i = 0; i < prescribed_.size(); ++i) {
    if (dof_map_[3 * prescribed_[i]] < 0)
      throw InvalidInput("prescribed vertex " + std::to_string(prescribed_[i]) + " is also fixed or listed twice");
    dof_map_.segment<3>(3 * prescribed_[i]).setConstant(-1);
  }
  for (int g = 0; g < 3 * nv_; ++g)
    if (dof_map_[g] >= 0) dof_map_[g] = n_free_++;
  if (n_free_ == 0) throw InvalidInput("every vertex is fixed or prescribed: nothing to simulate");
  assembler_ = std::make_unique<fem::SparseAssembler>(mesh_model.mesh().tets(), dof_map_, n_free_, true);
  A_ = assembler_->pattern();
  solver_.analyze(A_);
}

void LinearisedReplay::factorize_at(int step) {
  try {
    solver_.factorize(A_);
  } catch (const NumericalError& err) {
    std::ostringstream os;
    os << "step " << step << ", Newton iteration 0: " << err.what();
    throw NumericalError(os.str());
  }
  have_factor_ = true;
  ++stats_.factorizations;
}

VecX LinearisedReplay::solve(const VecX& b, int step) {
  if (!have_factor_) factorize_at(step);
  const double bnorm = b.norm();
  if (bnorm == 0) return VecX::Zero(b.size());
  const auto A = A_.selfadjointView<Eigen::Upper>();
  VecX x = solver_.solve(b);
  VecX r = b - A * x;
  int it = 0;
  if (r.norm() > tol_ * bnorm) {
    VecX z = solver_.solve(r);
    VecX p = z;
    double rz = r.dot(z);
    for (it = 1; it <= max_it_; ++it) {
      const VecX Ap = A * p;
      const double pAp = p.dot(Ap);
      if (!(pAp > 0)) break;  // not SPD in floating point: fall back to the direct solve
      const double alpha = rz / pAp;
      x += alpha * p;
      r -= alpha * Ap;
      if (r.norm() <= tol_ * bnorm) break;
      z = solver_.solve(r);
      const double rz_new = r.dot(z);
      p = z + (rz_new / rz) * p;
      rz = rz_new;
    }
    stats_.pcg_iterations += std::min(it, max_it_);
  }
  if (it > max_it_ || !(r.norm() <= tol_ * bnorm) || !x.allFinite()) {
    factorize_at(step);  // stale preconditioner: factorise this matrix and solve directly
    ++stats_.direct_fallbacks;
    return solver_.solve(b);
  }
  if (it > refresh_) factorize_at(step);  // drifting: a fresh factor for the next steps
  return x;
}

void LinearisedReplay::check_targets(const MatX3* targets, int steps) const {
  const long k = prescribed_.size();
  if (k == 0) {
    if (targets && targets->rows() > 0)
      throw InvalidInput("targets given but the replay has no prescribed vertices");
    return;
  }
  if (!targets || targets->rows() != static_cast<long>(steps) * k)
    throw InvalidInput("targets must have shape (steps * #prescribed, 3) = (" +
                       std::to_string(static_cast<long>(steps) * k) + ", 3) for the prescribed vertices");
  if (!targets->allFinite()) throw InvalidInput("targets contain NaN or Inf");
}

void LinearisedReplay::start_velocity(const MatX3& xs, const MatX3* targets, int s, MatX3& v) const {
  for (int i = 0; i < fixed_.size(); ++i) v.row(fixed_[i]).setZero();
  const long k = prescribed_.size();
  for (long i = 0; i < k; ++i)
    v.row(prescribed_[i]) = (targets->row(s * k + i) - xs.row(prescribed_[i])) / h_;
}

void LinearisedReplay::place_prescribed(const MatX3* targets, int s, MatX3& xs) const {
  const long k = prescribed_.size();
  for (long i = 0; i < k; ++i) xs.row(prescribed_[i]) = targets->row(s * k + i);
}

MatX3 LinearisedReplay::simulate(const fem::Model& model, const MatX3& x0_in, const MatX3& v0_in,
                                 int steps, const MatX3& f_ext, MatX3* velocities, const MatX3* targets) {
  if (model.mesh().num_vertices() != nv_ || model.mesh().num_tets() != nt_)
    throw InvalidInput("LinearisedReplay::simulate: the model's mesh differs from the replay's");
  if (steps < 0) throw InvalidInput("steps must be >= 0");
  check_targets(targets, steps);
  if (f_ext.rows() != nv_) throw InvalidInput("f_ext must have shape (#V, 3)");
  model.check_state(x0_in, "x");
  model.check_state(v0_in, "v");
  const VecX& mass = model.dof_mass();
  VecX fconst = as_dofs(f_ext);
  for (int i = 0; i < nv_; ++i) fconst.segment<3>(3 * i) += mass[3 * i] * gravity_;
  const bool rayleigh_only = model.correction() == nullptr;
  MatX3 out((steps + 1) * nv_, 3);
  if (velocities) velocities->resize((steps + 1) * nv_, 3);
  MatX3 xs = x0_in, vs = v0_in;
  out.topRows(nv_) = xs;
  if (velocities) velocities->topRows(nv_) = vs;
  fem::ElementState st;
  for (int s = 0; s < steps; ++s) {
    MatX3 v = vs;
    start_velocity(xs, targets, s, v);
    const MatX3 x = xs + h_ * v;
    try {
      model.evaluate(x, v, fem::kForce | fem::kStiffness | (rayleigh_only ? 0 : fem::kDamping), true, st);
    } catch (const NumericalError& err) {
      std::ostringstream os;
      os << "step " << s << ", Newton iteration 0: " << err.what();
      throw NumericalError(os.str());
    }
    const VecX g = step_residual(model, st, v, vs, mass, fconst);
    assemble_step_matrix(model, st, h_, mass, rayleigh_only, *assembler_, coeff_, diag_, A_);
    const VecX dv = solve(-g, s);
    if (!dv.allFinite()) {
      std::ostringstream os;
      os << "step " << s << ": linear solve produced NaN (diverged)";
      throw NumericalError(os.str());
    }
    advance(dv, s, v, vs, xs);
    place_prescribed(targets, s, xs);
    ++stats_.steps;
    out.middleRows((s + 1) * nv_, nv_) = xs;
    if (velocities) velocities->middleRows((s + 1) * nv_, nv_) = vs;
  }
  return out;
}

VecX LinearisedReplay::step_residual(const fem::Model& model, const fem::ElementState& st,
                                     const MatX3& v, const MatX3& vs, const VecX& mass,
                                     const VecX& fconst) const {
  const VecX f = model.gather_forces(st);
  VecX g(n_free_);
  const auto vd = as_dofs(v);
  const auto v0d = as_dofs(vs);
  for (int d = 0; d < 3 * nv_; ++d)
    if (dof_map_[d] >= 0) g[dof_map_[d]] = mass[d] * (vd[d] - v0d[d]) - h_ * (f[d] + fconst[d]);
  return g;
}

void LinearisedReplay::advance(const VecX& dv, int s, MatX3& v, MatX3& vs, MatX3& xs) {
  auto vdm = as_dofs(v);
  for (int d = 0; d < 3 * nv_; ++d)
    if (dof_map_[d] >= 0) vdm[d] += dv[dof_map_[d]];
  check_divergence(v, h_, size_, s);
  vs = v;
  xs = xs + h_ * v;
}

}  // namespace matlearn::time
