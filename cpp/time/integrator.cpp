#include "time/integrator.hpp"

#include <chrono>
#include <sstream>

namespace matlearn::time {

namespace {
using Clock = std::chrono::steady_clock;
double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}
}  // namespace

Integrator::Integrator(std::shared_ptr<const fem::Model> model, const VecXi& fixed,
                       double time_step, const Vec3& gravity, StepOptions options)
    : model_(std::move(model)), fixed_(fixed), h_(time_step), gravity_(gravity), opts_(options) {
  const int nv = model_->mesh().num_vertices();
  if (!(h_ > 0) || !std::isfinite(h_)) throw InvalidInput("time_step must be a positive number (s)");
  if (!gravity_.allFinite()) throw InvalidInput("gravity contains NaN or Inf");
  if (fixed_.size() && (fixed_.minCoeff() < 0 || fixed_.maxCoeff() >= nv))
    throw InvalidInput("fixed vertex index out of range [0, " + std::to_string(nv) + ")");
  if (opts_.max_newton < 1) throw InvalidInput("max_newton must be >= 1");
  x_ = model_->mesh().vertices();
  v_ = MatX3::Zero(nv, 3);
  const auto& X = model_->mesh().vertices();
  size_ = (X.colwise().maxCoeff() - X.colwise().minCoeff()).norm();
  rebuild_pattern();
}

void Integrator::set_state(const MatX3& x, const MatX3& v) {
  model_->check_state(x, "x");
  model_->check_state(v, "v");
  x_ = x;
  v_ = v;
  has_prev_v_ = false;
  unconverged_ = 0;
}

void Integrator::set_prescribed(const VecXi& vertices) {
  const int nv = model_->mesh().num_vertices();
  if (vertices.size() && (vertices.minCoeff() < 0 || vertices.maxCoeff() >= nv))
    throw InvalidInput("prescribed vertex index out of range [0, " + std::to_string(nv) + ")");
  prescribed_ = vertices;
  has_prev_v_ = false;
  rebuild_pattern();
}

void Integrator::rebuild_pattern() {
  const int nv = model_->mesh().num_vertices();
  dof_map_ = VecXi::Zero(3 * nv);
  for (int i = 0; i < fixed_.size(); ++i) dof_map_.segment<3>(3 * fixed_[i]).setConstant(-1);
  for (int i = 0; i < prescribed_.size(); ++i) dof_map_.segment<3>(3 * prescribed_[i]).setConstant(-1);
  n_free_ = 0;
  for (int g = 0; g < 3 * nv; ++g)
    if (dof_map_[g] >= 0) dof_map_[g] = n_free_++;
  if (n_free_ == 0) throw InvalidInput("every vertex is fixed or prescribed: nothing to simulate");
  assembler_ = std::make_unique<fem::SparseAssembler>(model_->mesh().tets(), dof_map_, n_free_, true);
  A_ = assembler_->pattern();
  solver_.analyze(A_);
  factor_valid_ = false;
}

void Integrator::step(const MatX3& f_ext, const MatX3* targets) {
  const int nv = model_->mesh().num_vertices();
  if (f_ext.rows() != nv) throw InvalidInput("f_ext must have shape (#V, 3)");
  if (prescribed_.size() > 0) {
    if (!targets || targets->rows() != prescribed_.size())
      throw InvalidInput("step: targets must have shape (" + std::to_string(prescribed_.size()) +
                         ", 3) for the prescribed vertices");
    if (!targets->allFinite()) throw InvalidInput("step: targets contain NaN or Inf");
  }
  const VecX& mass = model_->dof_mass();
  const MatX3 x0 = x_, v0 = v_;
  // Initial guess: constant acceleration from the last step (v_n + (v_n - v_{n-1})), which
  // starts the iteration O(h^2) instead of O(h) from the answer; the fixed point and stopping
  // test are unchanged. Only when the last step led to this state (not after set_state).
  MatX3 v = v_;
  if (opts_.extrapolate && opts_.max_newton > 1 && has_prev_v_) v += v_ - prev_v_;
  for (int i = 0; i < fixed_.size(); ++i) v.row(fixed_[i]).setZero();
  for (int i = 0; i < prescribed_.size(); ++i)
    v.row(prescribed_[i]) = ((*targets).row(i) - x0.row(prescribed_[i])) / h_;
  VecX fconst = as_dofs(f_ext);
  for (int i = 0; i < nv; ++i) fconst.segment<3>(3 * i) += mass[3 * i] * gravity_;
  fem::ElementState st;
  const double v_ref = 1e-6 * size_ / h_;
  last_iters_ = 0;
  timings_ = StepTimings{};
  // Without a correction the element damping matrix is alpha_K,e K_e + c_e I (Rayleigh on the
  // same projected tangent), so the system matrix is assembled from K alone with per-element
  // coefficients: half the element data to compute, store and scatter.
  const bool rayleigh_only = model_->correction() == nullptr;
  const bool reuse = opts_.reuse_factorization && opts_.max_newton > 1;
  // Chord iterations with the last factorised matrix cost a force evaluation and one
  // triangular solve; the tangent is evaluated and refactorised only when they stop
  // contracting fast enough. Bounded: at most max_newton refactorisations and 4 max_newton
  // iterations in all.
  bool refresh = !(reuse && factor_valid_);
  int fresh = 0;
  double prev_dv = 0.0;
  bool converged = false;
  for (int it = 0; it < 4 * opts_.max_newton; ++it) {
    auto t0 = Clock::now();
    MatX3 x = x0 + h_ * v;
    const int flags = fem::kForce | (refresh ? fem::kStiffness | (rayleigh_only ? 0 : fem::kDamping) : 0);
    try {
      model_->evaluate(x, v, flags, true, st);
    } catch (const NumericalError& err) {  // e.g. a correction returning NaN: say when
      std::ostringstream os;
      os << "step " << steps_ << ", Newton iteration " << it << ": " << err.what();
      throw NumericalError(os.str());
    }
    const VecX f = model_->gather_forces(st);
    timings_.evaluate_s += seconds_since(t0);
    VecX g(n_free_);
    const auto vd = as_dofs(v);
    const auto v0d = as_dofs(v0);
    for (int d = 0; d < 3 * nv; ++d)
      if (dof_map_[d] >= 0) g[dof_map_[d]] = mass[d] * (vd[d] - v0d[d]) - h_ * (f[d] + fconst[d]);
    if (refresh) {
      t0 = Clock::now();
      assemble_step_matrix(*model_, st, h_, mass, rayleigh_only, *assembler_, coeff_, diag_, A_);
      timings_.assemble_s += seconds_since(t0);
      t0 = Clock::now();
      factor_valid_ = false;
      try {
        solver_.factorize(A_);
      } catch (const NumericalError& err) {
        std::ostringstream os;
        os << "step " << steps_ << ", Newton iteration " << it << ": " << err.what();
        throw NumericalError(os.str());
      }
      factor_valid_ = true;
      ++fresh;
      timings_.factorize_s += seconds_since(t0);
    }
    t0 = Clock::now();
    const VecX dv = solver_.solve(-g);
    timings_.solve_s += seconds_since(t0);
    if (!dv.allFinite()) {
      std::ostringstream os;
      os << "step " << steps_ << ": linear solve produced NaN (diverged)";
      throw NumericalError(os.str());
    }
    const double dv_norm = dv.norm();
    timings_.updates.push_back(refresh ? -dv_norm : dv_norm);
    const bool slow = !refresh && it > 0 && dv_norm > opts_.reuse_ratio * prev_dv;
    if (slow && dv_norm >= prev_dv) {
      // The stale matrix does not contract here: discard this update and redo the iteration
      // with the current tangent.
      refresh = true;
      continue;
    }
    auto vdm = as_dofs(v);
    double vnorm2 = 0;
    for (int d = 0; d < 3 * nv; ++d)
      if (dof_map_[d] >= 0) {
        vdm[d] += dv[dof_map_[d]];
        vnorm2 += vdm[d] * vdm[d];
      }
    last_iters_ = it + 1;
    timings_.iterations = last_iters_;
    timings_.factorizations = fresh;
    if (dv_norm <= opts_.tolerance * (std::sqrt(vnorm2) + v_ref)) {
      converged = true;
      break;
    }
    if (fresh >= opts_.max_newton) break;
    prev_dv = dv_norm;
    refresh = !reuse || slow;
  }
  if (!converged && opts_.max_newton > 1) ++unconverged_;
  check_divergence(v, h_, size_, steps_);
  prev_v_ = v_;
  has_prev_v_ = true;
  v_ = v;
  x_ = x0 + h_ * v;
  for (int i = 0; i < prescribed_.size(); ++i) x_.row(prescribed_[i]) = (*targets).row(i);
  ++steps_;
}

MatX3 Integrator::simulate(int steps, const MatX3& f_ext, int record_every,
                           const ProgressFn& progress, MatX3* velocities) {
  if (steps < 0) throw InvalidInput("steps must be >= 0");
  if (record_every < 1) throw InvalidInput("record_every must be >= 1");
  const int nv = x_.rows();
  const int frames = steps / record_every + 1;
  MatX3 out(frames * nv, 3);
  if (velocities) velocities->resize(frames * nv, 3);
  out.topRows(nv) = x_;
  if (velocities) velocities->topRows(nv) = v_;
  for (int s = 1; s <= steps; ++s) {
    step(f_ext);
    if (s % record_every == 0) {
      out.middleRows((s / record_every) * nv, nv) = x_;
      if (velocities) velocities->middleRows((s / record_every) * nv, nv) = v_;
    }
    if (progress && (s % 20 == 0 || s == steps)) progress(s, steps);
  }
  return out;
}

MatX3 Integrator::simulate_constrained(const MatX3& targets, const MatX3& f_ext,
                                       const ProgressFn& progress, MatX3* velocities) {
  const int k = prescribed_.size();
  if (k == 0) throw InvalidInput("simulate_constrained: call set_prescribed() first");
  if (targets.rows() % k != 0)
    throw InvalidInput("simulate_constrained: targets must have shape (steps, #prescribed, 3)");
  const int steps = targets.rows() / k;
  const int nv = x_.rows();
  MatX3 out((steps + 1) * nv, 3);
  if (velocities) velocities->resize((steps + 1) * nv, 3);
  out.topRows(nv) = x_;
  if (velocities) velocities->topRows(nv) = v_;
  for (int s = 0; s < steps; ++s) {
    const MatX3 t = targets.middleRows(s * k, k);
    step(f_ext, &t);
    out.middleRows((s + 1) * nv, nv) = x_;
    if (velocities) velocities->middleRows((s + 1) * nv, nv) = v_;
    if (progress && ((s + 1) % 20 == 0 || s + 1 == steps)) progress(s + 1, steps);
  }
  return out;
}

void Integrator::static_solve(const MatX3& f_ext, int load_steps, int max_iterations, double tol) {
  const int nv = x_.rows();
  if (f_ext.rows() != nv) throw InvalidInput("f_ext must have shape (#V, 3)");
  if (load_steps < 1) throw InvalidInput("load_steps must be >= 1");
  if (max_iterations < 1) throw InvalidInput("max_iterations must be >= 1");
  if (fixed_.size() == 0 && prescribed_.size() == 0)
    throw InvalidInput("static_solve needs fixed vertices (a free body has no equilibrium)");
  const VecX& mass = model_->dof_mass();
  factor_valid_ = false;  // the static Newton factorises K into the same solver
  VecX fload = as_dofs(f_ext);
  for (int i = 0; i < nv; ++i) fload.segment<3>(3 * i) += mass[3 * i] * gravity_;
  const MatX3 zero_v = MatX3::Zero(nv, 3);
  fem::ElementState st;
  const VecX empty;
  double fint_norm = 0.0;
  // Residual f_int(x) + scale f_load on the free DOFs; with `tangent` also the element
  // stiffnesses (the forces are bitwise the same either way, see Correction::evaluate_values).
  auto residual = [&](const MatX3& x, double scale, bool tangent, VecX& r) {
    model_->evaluate(x, zero_v, fem::kForce | (tangent ? fem::kStiffness : 0), true, st);
    const VecX f = model_->gather_forces(st);
    r.resize(n_free_);
    fint_norm = 0.0;
    for (int d = 0; d < 3 * nv; ++d)
      if (dof_map_[d] >= 0) {
        r[dof_map_[d]] = f[d] + scale * fload[d];
        fint_norm += f[d] * f[d];
      }
    fint_norm = std::sqrt(fint_norm);
  };
  auto moved = [&](double t, const VecX& dx) {
    MatX3 xt = x_;
    auto xd = as_dofs(xt);
    for (int d = 0; d < 3 * nv; ++d)
      if (dof_map_[d] >= 0) xd[d] += t * dx[dof_map_[d]];
    return xt;
  };
  // The residual is measured against the load, but never against less than the body's weight
  // under standard gravity: with no load (zero gravity, a pose held by prescribed vertices
  // alone) the reference was 1e-12 N and nothing but round-off could pass.
  const double ref = std::max(fload.norm(), 9.81 * mass.norm()) + 1e-12;
  const double dx_floor = 1e-14 * size_ * std::sqrt(double(n_free_));
  static_timings_ = StepTimings{};
  bool factored = false;  // solver_ holds a tangent of this solve (chord steps may reuse it)
  for (int ls = 1; ls <= load_steps; ++ls) {
    const double scale = double(ls) / load_steps;
    VecX r;
    residual(x_, scale, false, r);
    int fresh = 0, uphill = 0;
    // Chord (lagged-tangent) steps: a force evaluation and a triangular solve with the last
    // factorised tangent, taken while they contract the residual about as well as the last
    // fresh tangent did. That tangent is PSD-projected and, with a learned correction, only the
    // symmetric part of dN/dFh, so Newton itself converges only linearly there (measured
    // contraction ~0.6 per iteration on the learned 6k-tet bar): re-evaluating and
    // refactorising it every iteration bought nothing.
    bool chord = factored;
    double q_fresh = 0.0;  // residual contraction of the last fresh-tangent iteration
    for (int it = 0; it < 4 * max_iterations; ++it) {
      const double r0 = r.norm();
      if (r0 <= tol * ref) break;
      if (chord) {
        const VecX dx = solver_.solve(r);
        const MatX3 xt = moved(1.0, dx);
        VecX rt;
        residual(xt, scale, false, rt);
        const double q = rt.allFinite() ? rt.norm() / r0 : 2.0;
        ++static_timings_.iterations;
        if (q < 1.0) {
          x_ = xt;
          r = rt;
          if (dx.norm() <= dx_floor) break;
          // Far from equilibrium a backtracked fresh step may contract by ~1; chord steps
          // must still contract clearly (<= 0.75) or the tangent is refreshed.
          chord = q <= std::max(kChordContraction, std::min(0.75, 1.25 * q_fresh));
          continue;
        }
        // Not a decrease: discard the step, take a fresh tangent at the same point.
      }
      if (fresh >= max_iterations) break;
      residual(x_, scale, true, r);
      assembler_->assemble(st.K, 1.0, {}, 0.0, empty, 0.0, A_);
      try {
        solver_.factorize(A_);
      } catch (const NumericalError& err) {
        throw NumericalError(std::string("static_solve: ") + err.what() +
                             " (is the body clamped enough to be stable?)");
      }
      factored = true;
      ++fresh;
      ++static_timings_.iterations;
      ++static_timings_.factorizations;
      const VecX dx = solver_.solve(r);
      // Backtracking on the residual norm keeps Newton safe far from equilibrium (trials need
      // forces only).
      double t = 1.0;
      bool decreased = false;
      MatX3 xt;
      VecX rt;
      for (int bt = 0; bt < 12; ++bt) {
        xt = moved(t, dx);
        residual(xt, scale, false, rt);
        if (rt.allFinite() && rt.norm() < r0) {
          decreased = true;
          break;
        }
        t *= 0.5;
      }
      if (!decreased) {
        // At the round-off floor (set by the internal forces, which can exceed a small load by
        // orders of magnitude) nothing decreases any more: stop, the check below judges it.
        if (r0 <= 1e-10 * (fint_norm + ref)) {
          residual(x_, scale, false, r);
          break;
        }
        // Otherwise the PSD-projected tangent is not the exact one (large rotations, compressed
        // fibres) and the residual norm may have to rise before it falls: take a short
        // non-monotone step, a bounded number of times.
        if (++uphill > 8) {
          residual(x_, scale, false, r);
          break;
        }
        xt = moved(0.25, dx);
        residual(xt, scale, false, rt);
        if (!rt.allFinite()) {
          residual(x_, scale, false, r);
          break;
        }
        t = 0.25;
      }
      x_ = xt;
      r = rt;
      // A negligible update is convergence too (the residual tolerance may be below round-off).
      if (t * dx.norm() <= dx_floor) break;
      q_fresh = r.norm() / r0;
      chord = decreased;
    }
    if (!r.allFinite() || r.norm() > 1e-3 * ref)
      throw NumericalError("static_solve: Newton did not converge at load step " +
                           std::to_string(ls) + " (relative residual " +
                           std::to_string(r.norm() / ref) + "); try more load_steps");
  }
  v_.setZero();
  has_prev_v_ = false;
}

void check_divergence(const MatX3& v, double h, double size, int step) {
  if (!v.allFinite() || v.cwiseAbs().maxCoeff() * h > 1e4 * size) {
    std::ostringstream os;
    os << "step " << step << ": simulation diverged (velocities blew up; "
       << "try a smaller time step or check the material parameters)";
    throw NumericalError(os.str());
  }
}

void assemble_step_matrix(const fem::Model& model, const fem::ElementState& st, double h,
                          const VecX& mass, bool rayleigh_only, const fem::SparseAssembler& assembler,
                          VecX& coeff, VecX& diag, SpMat& A) {
  if (!rayleigh_only) {
    assembler.assemble(st.K, h * h, st.D, h, mass, 1.0, A);
    return;
  }
  const int m = model.mesh().num_tets();
  const auto& T = model.mesh().tets();
  const VecX& W = model.mesh().volumes();
  const VecX& rho = model.density();
  coeff.resize(m);
  diag = mass;
  for (int e = 0; e < m; ++e) {
    coeff[e] = h * h + h * st.alpha_K[e];
    const double cm = h * st.alpha_M[e] * rho[e] * W[e] / 4.0;
    if (cm != 0.0)
      for (int a = 0; a < 4; ++a) diag.segment<3>(3 * T(e, a)).array() += cm;
  }
  assembler.assemble_scaled(st.K, coeff, diag, A);
}

}  // namespace matlearn::time
