#include "spacetime/spacetime_problem.hpp"

#include <Eigen/SparseCholesky>
#include <cmath>
#include <limits>

namespace matlearn::spacetime {

SpaceTimeProblem::SpaceTimeProblem(std::shared_ptr<const fem::Model> model, MatX phi, MatXr base,
                                   MatXr fext, double h, Observations obs, double lambda,
                                   bool nominal_tangent)
    : model_(std::move(model)), phi_(std::move(phi)), base_(std::move(base)),
      fext_(std::move(fext)), h_(h), lambda_(lambda), obs_(std::move(obs)) {
  if (!model_) throw InvalidInput("SpaceTimeProblem: model is None");
  n_ = model_->mesh().num_vertices();
  r_ = int(phi_.cols());
  if (phi_.rows() != 3 * n_ || r_ < 1)
    throw InvalidInput("SpaceTimeProblem: phi must be (3*#V x r) with r >= 1, #V = " +
                       std::to_string(n_));
  if (!(h_ > 0)) throw InvalidInput("SpaceTimeProblem: time_step must be > 0");
  if (!(lambda_ >= 0)) throw InvalidInput("SpaceTimeProblem: lambda must be >= 0");
  if (base_.cols() != 3 * n_ || base_.rows() < 1)
    throw InvalidInput("SpaceTimeProblem: base must be (frames x 3*#V) or (1 x 3*#V)");
  if (fext_.cols() != 3 * n_ || fext_.rows() < 1)
    throw InvalidInput("SpaceTimeProblem: fext must be (frames x 3*#V) or (1 x 3*#V)");
  frames_ = int(base_.rows() > 1 ? base_.rows() : fext_.rows());
  const int T = int(obs_.frame.size());
  // Frame count comes from the largest of base, fext and the sample frames.
  for (int t = 0; t < T; ++t) frames_ = std::max(frames_, obs_.frame[t] + 2);
  if (base_.rows() > 1 && base_.rows() != frames_)
    throw InvalidInput("SpaceTimeProblem: base has " + std::to_string(base_.rows()) +
                       " frames but the problem has " + std::to_string(frames_));
  if (fext_.rows() > 1 && fext_.rows() != frames_)
    throw InvalidInput("SpaceTimeProblem: fext has " + std::to_string(fext_.rows()) +
                       " frames but the problem has " + std::to_string(frames_));
  if (frames_ < 3) throw InvalidInput("SpaceTimeProblem: need at least 3 frames");
  obs_rows_ = int(obs_.S_phi.rows());
  if (T > 0) {
    if (obs_.S_phi.cols() != r_) throw InvalidInput("Observations: S_phi must have r columns");
    if (obs_.weight.size() != T || obs_.targets.rows() != T || obs_.targets.cols() != obs_rows_)
      throw InvalidInput("Observations: frame, weight and targets must have one entry per sample "
                         "and targets (T x 3K)");
    if (obs_.S_base.cols() != obs_rows_ ||
        (obs_.S_base.rows() != 1 && obs_.S_base.rows() != frames_))
      throw InvalidInput("Observations: S_base must be (frames x 3K) or (1 x 3K)");
    for (int t = 0; t < T; ++t) {
      if (obs_.frame[t] < 0 || obs_.weight[t] < 0 || obs_.weight[t] > 1)
        throw InvalidInput("Observations: sample " + std::to_string(t) +
                           " has a negative frame or a weight outside [0, 1]");
    }
  }
  if (!phi_.allFinite() || !base_.allFinite() || !fext_.allFinite())
    throw InvalidInput("SpaceTimeProblem: phi, base or fext contain NaN or Inf");

  const VecX& m = model_->dof_mass();
  Mr_ = phi_.transpose() * m.asDiagonal() * phi_;
  constrained_ = VecX::Zero(3 * n_);
  for (int d = 0; d < 3 * n_; ++d)
    if (phi_.row(d).isZero(0)) constrained_[d] = 1.0;
  if (nominal_tangent && model_->correction()) {
    auto nom = std::make_shared<fem::Model>(*model_);
    nom->set_correction(nullptr);
    nominal_ = nom;
  } else {
    nominal_ = model_;
  }
}

void SpaceTimeProblem::frame_state(const MatXr& Z, int j, MatX3& x, MatX3& v) const {
  auto state = [&](int k, MatX3& out) {
    out.resize(n_, 3);
    const auto b = base_.row(base_.rows() > 1 ? k : 0);
    Eigen::Map<VecX> o(out.data(), 3 * n_);
    o = b.transpose() + phi_ * Z.row(k).transpose();
  };
  state(j, x);
  if (j > 0) {
    MatX3 xp;
    state(j - 1, xp);
    v = (x - xp) / h_;
  } else {
    v = MatX3::Zero(n_, 3);
  }
}

MatX3 SpaceTimeProblem::positions(const MatXr& Z) const {
  if (Z.rows() != frames_ || Z.cols() != r_)
    throw InvalidInput("Z: expected shape (" + std::to_string(frames_) + ", " +
                       std::to_string(r_) + ")");
  MatX3 X(size_t(frames_) * n_, 3);
  for (int j = 0; j < frames_; ++j) {
    MatX3 x, v;
    frame_state(Z, j, x, v);
    X.middleRows(size_t(j) * n_, n_) = x;
  }
  return X;
}

// Physics residual block for row i (1..N-1): needs f(x_{i+1}, v_{i+1}) (3n).
VecX SpaceTimeProblem::physics_block(const MatXr& Z, int i, const VecX& f_next) const {
  MatX3 xm, xi, xp, v;
  frame_state(Z, i - 1, xm, v);
  frame_state(Z, i, xi, v);
  frame_state(Z, i + 1, xp, v);
  const VecX& m = model_->dof_mass();
  const auto fe = fext_.row(fext_.rows() > 1 ? i + 1 : 0).transpose();
  VecX g = m.cwiseProduct(as_dofs(xm) - 2.0 * as_dofs(xi) + as_dofs(xp)) / (h_ * h_) - f_next - fe;
  return phi_.transpose() * g;
}

static bool parallel_ok(const fem::Model& m) {
  return !m.correction() || m.correction()->thread_safe();
}

VecX SpaceTimeProblem::residual(const MatXr& Z) const {
  if (Z.rows() != frames_ || Z.cols() != r_)
    throw InvalidInput("Z: expected shape (" + std::to_string(frames_) + ", " +
                       std::to_string(r_) + ")");
  VecX C = VecX::Zero(num_residuals());
  const int nb = frames_ - 2;
  std::string err;
#pragma omp parallel for schedule(dynamic) if (parallel_ok(*model_))
  for (int b = 0; b < nb; ++b) {
    try {
      MatX3 x, v;
      frame_state(Z, b + 2, x, v);
      const VecX f = model_->forces(x, v);
      C.segment(size_t(b) * r_, r_) = physics_block(Z, b + 1, f);
    } catch (const std::exception& e) {
#pragma omp critical
      err = e.what();
    }
  }
  if (!err.empty()) throw NumericalError("space-time residual: " + err);
  const int T = int(obs_.frame.size());
  const int off = num_physics_rows();
#pragma omp parallel for schedule(static)
  for (int t = 0; t < T; ++t) {
    const int f0 = obs_.frame[t];
    const double a = obs_.weight[t];
    auto sb = [&](int k) { return obs_.S_base.row(obs_.S_base.rows() > 1 ? k : 0).transpose(); };
    VecX s = (1 - a) * (sb(f0) + obs_.S_phi * Z.row(f0).transpose());
    if (a > 0) s += a * (sb(f0 + 1) + obs_.S_phi * Z.row(f0 + 1).transpose());
    for (int k = 0; k < obs_rows_; ++k) {
      const double tk = obs_.targets(t, k);
      C[off + size_t(t) * obs_rows_ + k] = std::isnan(tk) ? 0.0 : lambda_ * (s[k] - tk);
    }
  }
  return C;
}

void SpaceTimeProblem::linearize(const MatXr& Z) {
  C_ = residual(Z);
  linearize_jacobian(Z);
}

void SpaceTimeProblem::linearize_jacobian(const MatXr& Z) {
  const int nb = frames_ - 2;
  A_.assign(nb, MatX());
  B_.assign(nb, MatX());
  const auto& T = model_->mesh().tets();
  const int m = model_->mesh().num_tets();
  const MatX Mh = Mr_ / (h_ * h_);
  std::string err;
  // With tangent_stride k > 1 the tangent is evaluated at the middle frame of each run of k
  // frames and shared by the run (the rows' mass and Mr/h^2 terms stay exact per frame).
  const int k = std::max(1, tangent_stride_);
#pragma omp parallel for schedule(dynamic) if (parallel_ok(*nominal_))
  for (int b = 0; b < nb; ++b) {
    if (b % k != 0) continue;
    try {
      MatX3 x, v;
      frame_state(Z, std::min(b + k / 2, nb - 1) + 2, x, v);
      if (!nominal_->correction()) {
        // Reduced products straight from the principal-frame tangents (fem::Model::
        // reduced_tangents): the same blocks without 12 x 12 element matrices.
        MatX Kr, Dr;
        nominal_->reduced_tangents(x, phi_, Kr, Dr);
        A_[b] = Mh + Kr + Dr / h_;
        B_[b] = -2.0 * Mh - Dr / h_;
        continue;
      }
      fem::ElementState st;
      nominal_->evaluate(x, v, fem::kStiffness | fem::kDamping, false, st);
      MatX KD = MatX::Zero(r_, r_), Dr = MatX::Zero(r_, r_);
      Eigen::Matrix<double, 12, Eigen::Dynamic> Pe(12, r_);
      for (int e = 0; e < m; ++e) {
        bool active = false;
        for (int a = 0; a < 12; ++a) {
          const int d = 3 * T(e, a / 3) + a % 3;
          Pe.row(a) = phi_.row(d);
          active |= constrained_[d] == 0.0;
        }
        if (!active) continue;
        const Eigen::Matrix<double, 12, Eigen::Dynamic> DP = st.D[e] * Pe;
        KD.noalias() += Pe.transpose() * (st.K[e] * Pe + DP / h_);
        Dr.noalias() += Pe.transpose() * DP;
      }
      A_[b] = Mh + KD;
      B_[b] = -2.0 * Mh - Dr / h_;
    } catch (const std::exception& e) {
#pragma omp critical
      err = e.what();
    }
  }
  if (!err.empty()) throw NumericalError("space-time linearisation: " + err);
  for (int b = 0; b < nb; ++b)
    if (b % k != 0) {
      A_[b] = A_[b - b % k];
      B_[b] = B_[b - b % k];
    }
  linearized_ = true;
}

VecX SpaceTimeProblem::jvp(const VecX& p) const {
  if (!linearized_) throw InvalidInput("jvp: call linearize(Z) first");
  if (p.size() != num_unknowns())
    throw InvalidInput("jvp: p must have length " + std::to_string(num_unknowns()));
  VecX out = VecX::Zero(num_residuals());
  const int nb = frames_ - 2;
  const double ih2 = 1.0 / (h_ * h_);
  const bool big = double(frames_) * r_ * r_ > 2e6;  // threads only pay off on large products
#pragma omp parallel for schedule(static) if (big)
  for (int b = 0; b < nb; ++b) {
    const int i = b + 1;
    out.segment(size_t(b) * r_, r_) = A_[b] * p.segment(size_t(i + 1) * r_, r_) +
                                      B_[b] * p.segment(size_t(i) * r_, r_) +
                                      ih2 * (Mr_ * p.segment(size_t(i - 1) * r_, r_));
  }
  const int T = int(obs_.frame.size());
  const int off = num_physics_rows();
#pragma omp parallel for schedule(static) if (big)
  for (int t = 0; t < T; ++t) {
    const int f0 = obs_.frame[t];
    const double a = obs_.weight[t];
    VecX s = (1 - a) * (obs_.S_phi * p.segment(size_t(f0) * r_, r_));
    if (a > 0) s += a * (obs_.S_phi * p.segment(size_t(f0 + 1) * r_, r_));
    for (int k = 0; k < obs_rows_; ++k)
      out[off + size_t(t) * obs_rows_ + k] = std::isnan(obs_.targets(t, k)) ? 0.0 : lambda_ * s[k];
  }
  return out;
}

VecX SpaceTimeProblem::vjp(const VecX& q) const {
  if (!linearized_) throw InvalidInput("vjp: call linearize(Z) first");
  if (q.size() != num_residuals())
    throw InvalidInput("vjp: q must have length " + std::to_string(num_residuals()));
  VecX out = VecX::Zero(num_unknowns());
  const int nb = frames_ - 2;
  const double ih2 = 1.0 / (h_ * h_);
  // Gather per unknown frame j: rows b = j-2 (A), b = j-1 (B), b = j (Mr/h^2).
  const bool big = double(frames_) * r_ * r_ > 2e6;
#pragma omp parallel for schedule(static) if (big)
  for (int j = 0; j < frames_; ++j) {
    VecX g = VecX::Zero(r_);
    if (j - 2 >= 0 && j - 2 < nb) g += A_[j - 2].transpose() * q.segment(size_t(j - 2) * r_, r_);
    if (j - 1 >= 0 && j - 1 < nb) g += B_[j - 1].transpose() * q.segment(size_t(j - 1) * r_, r_);
    if (j < nb) g += ih2 * (Mr_ * q.segment(size_t(j) * r_, r_));
    out.segment(size_t(j) * r_, r_) = g;
  }
  const int T = int(obs_.frame.size());
  const int off = num_physics_rows();
  MatXr G(T, r_);
#pragma omp parallel for schedule(static) if (big)
  for (int t = 0; t < T; ++t) {
    VecX qt = q.segment(off + size_t(t) * obs_rows_, obs_rows_);
    for (int k = 0; k < obs_rows_; ++k)
      if (std::isnan(obs_.targets(t, k))) qt[k] = 0.0;
    G.row(t) = lambda_ * (obs_.S_phi.transpose() * qt).transpose();
  }
  for (int t = 0; t < T; ++t) {
    const int f0 = obs_.frame[t];
    const double a = obs_.weight[t];
    out.segment(size_t(f0) * r_, r_) += (1 - a) * G.row(t).transpose();
    if (a > 0) out.segment(size_t(f0 + 1) * r_, r_) += a * G.row(t).transpose();
  }
  return out;
}

namespace {
// Squared column norms of J (the diagonal of J^T J) raised to 1e-12 of the largest, so that a
// column no residual touches still gets a finite scale (CGLS) or damping (Levenberg-Marquardt).
void floor_column_norms(VecX& d) {
  const double floor = 1e-12 * std::max(d.maxCoeff(), 1e-300);
  for (int i = 0; i < d.size(); ++i) d[i] = std::max(d[i], floor);
}
}  // namespace

VecX SpaceTimeProblem::column_scale() const {
  VecX d = VecX::Zero(num_unknowns());
  const int nb = frames_ - 2;
  const double ih2 = 1.0 / (h_ * h_);
  const VecX mcol = (ih2 * Mr_).colwise().squaredNorm().transpose();
  for (int j = 0; j < frames_; ++j) {
    auto dj = d.segment(size_t(j) * r_, r_);
    if (j - 2 >= 0 && j - 2 < nb) dj += A_[j - 2].colwise().squaredNorm().transpose();
    if (j - 1 >= 0 && j - 1 < nb) dj += B_[j - 1].colwise().squaredNorm().transpose();
    if (j < nb) dj += mcol;
  }
  const int T = int(obs_.frame.size());
  const MatXr S2 = obs_.S_phi.array().square().matrix();
  for (int t = 0; t < T; ++t) {
    VecX c = VecX::Zero(r_);
    for (int k = 0; k < obs_rows_; ++k)
      if (!std::isnan(obs_.targets(t, k))) c += S2.row(k).transpose();
    const int f0 = obs_.frame[t];
    const double a = obs_.weight[t];
    d.segment(size_t(f0) * r_, r_) += lambda_ * lambda_ * (1 - a) * (1 - a) * c;
    if (a > 0) d.segment(size_t(f0 + 1) * r_, r_) += lambda_ * lambda_ * a * a * c;
  }
  floor_column_norms(d);
  for (int i = 0; i < d.size(); ++i) d[i] = 1.0 / std::sqrt(d[i]);
  return d;
}

Eigen::SparseMatrix<double> SpaceTimeProblem::assemble_jacobian() const {
  // J as a sparse matrix of dense r x r blocks (for the direct solve / preconditioner only).
  std::vector<Eigen::Triplet<double>> trip;
  const int nb = frames_ - 2;
  const double ih2 = 1.0 / (h_ * h_);
  auto add_block = [&](int row0, int col0, const MatX& Bk) {
    for (int a = 0; a < Bk.rows(); ++a)
      for (int c = 0; c < Bk.cols(); ++c)
        if (Bk(a, c) != 0.0) trip.emplace_back(row0 + a, col0 + c, Bk(a, c));
  };
  const MatX Mh = ih2 * Mr_;
  for (int b = 0; b < nb; ++b) {
    add_block(b * r_, (b + 2) * r_, A_[b]);
    add_block(b * r_, (b + 1) * r_, B_[b]);
    add_block(b * r_, b * r_, Mh);
  }
  const int off = num_physics_rows();
  for (int t = 0; t < int(obs_.frame.size()); ++t) {
    const int f0 = obs_.frame[t];
    const double a = obs_.weight[t];
    MatX S = lambda_ * obs_.S_phi;
    for (int k = 0; k < obs_rows_; ++k)
      if (std::isnan(obs_.targets(t, k))) S.row(k).setZero();
    add_block(off + t * obs_rows_, f0 * r_, (1 - a) * S);
    if (a > 0) add_block(off + t * obs_rows_, (f0 + 1) * r_, a * S);
  }
  Eigen::SparseMatrix<double> J(num_residuals(), num_unknowns());
  J.setFromTriplets(trip.begin(), trip.end());
  return J;
}

void SpaceTimeProblem::factorize_normal(const Eigen::SparseMatrix<double>& J) const {
  Eigen::SparseMatrix<double> JtJ = J.transpose() * J;
  const double reg = 1e-14 * JtJ.diagonal().maxCoeff();
  for (int i = 0; i < JtJ.rows(); ++i) JtJ.coeffRef(i, i) += reg;
  precond_ = std::make_shared<Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>>(JtJ);
  if (precond_->info() != Eigen::Success) {
    precond_.reset();
    throw NumericalError("space-time: factorisation of J^T J failed");
  }
}

VecX SpaceTimeProblem::solve_linear(const SolveOptions& opt, int* iterations) const {
  if (!linearized_) throw InvalidInput("solve_linear: call linearize(Z) first");
  if (opt.solver == "direct") {
    const Eigen::SparseMatrix<double> J = assemble_jacobian();
    factorize_normal(J);
    if (iterations) *iterations = 0;
    const VecX dz = precond_->solve(-(J.transpose() * C_));
    precond_.reset();
    return dz;
  }
  if (opt.solver == "pcgls") {
    // CG on the normal equations J^T J dz = -J^T C, products matrix-free, preconditioned by a
    // frozen factorisation of an earlier J^T J (exact at the first step of a solve).
    if (!precond_) factorize_normal(assemble_jacobian());
    VecX x = VecX::Zero(num_unknowns());
    VecX r = -vjp(C_);
    const double r0 = r.norm();
    VecX z = precond_->solve(r);
    VecX p = z;
    double rz = r.dot(z);
    int k = 0;
    for (; k < opt.cg_iterations && r0 > 0; ++k) {
      const VecX Jp = jvp(p);
      const double pAp = Jp.squaredNorm();
      if (!(pAp > 0)) break;
      const double alpha = rz / pAp;
      x += alpha * p;
      r -= alpha * vjp(Jp);
      if (r.norm() <= opt.cg_tolerance * r0) {
        ++k;
        break;
      }
      z = precond_->solve(r);
      const double rz_new = r.dot(z);
      p = z + (rz_new / rz) * p;
      rz = rz_new;
    }
    if (k > opt.refresh_iterations) precond_.reset();  // stale: refactorise at the next step
    if (iterations) *iterations = k;
    return x;
  }
  if (opt.solver != "cgls") throw InvalidInput("solver must be 'pcgls', 'cgls', 'direct' or 'lm'");
  // CGLS on min |J D y + C| with Jacobi column scaling D, dz = D y.
  const VecX D = column_scale();
  VecX y = VecX::Zero(num_unknowns());
  VecX res = -C_;
  VecX s = D.cwiseProduct(vjp(res));
  VecX p = s;
  double gamma = s.squaredNorm();
  const double norm0 = std::sqrt(gamma);
  int k = 0;
  for (; k < opt.cg_iterations && norm0 > 0; ++k) {
    const VecX q = jvp(D.cwiseProduct(p));
    const double delta = q.squaredNorm();
    if (!(delta > 0)) break;
    const double alpha = gamma / delta;
    y += alpha * p;
    res -= alpha * q;
    s = D.cwiseProduct(vjp(res));
    const double gnew = s.squaredNorm();
    if (std::sqrt(gnew) <= opt.cg_tolerance * norm0) {
      ++k;
      break;
    }
    p = s + (gnew / gamma) * p;
    gamma = gnew;
  }
  if (iterations) *iterations = k;
  return D.cwiseProduct(y);
}

namespace {
// A cost this far below the initial one is round-off: the residual is ~1e-10 of where it started.
constexpr double kRoundoffCost = 1e-20;

void record_cost(SolveReport& rep, const VecX& C, int physics_rows) {
  rep.cost.push_back(0.5 * C.squaredNorm());
  rep.physics_cost.push_back(0.5 * C.head(physics_rows).squaredNorm());
}

// Books one step: its inner iterations (CG iterations or damping trials) and its length t (0: no
// trial lowered the cost, the solve stops) with the residual Ct it reached from `cost`. True when
// the solve stops: no step, a gain below opt.tolerance of the cost, or a round-off cost.
bool book_step(SolveReport& rep, int inner, double t, const VecX& Ct, double cost, int physics_rows,
               const SolveOptions& opt, const ProgressFn& progress, int it) {
  rep.cg_iterations.push_back(inner);
  rep.step_length.push_back(t);
  if (t == 0.0) return true;
  record_cost(rep, Ct, physics_rows);
  if (progress) progress(it + 1, opt.max_iterations);
  if (cost - 0.5 * Ct.squaredNorm() < opt.tolerance * cost) return true;
  // Converged to round-off (an exact model fitted exactly): further steps only shuffle
  // rounding errors, the line search shortens them and CG cannot reach its relative tolerance.
  return 0.5 * Ct.squaredNorm() <= kRoundoffCost * rep.cost.front();
}
}  // namespace

bool SpaceTimeProblem::trial_residual(const MatXr& Zt, VecX& Ct) const {
  try {
    Ct = residual(Zt);
    return true;
  } catch (const NumericalError&) {
    return false;  // e.g. an element inverted so far that the correction blew up
  }
}

SolveReport SpaceTimeProblem::solve_lm(MatXr& Z, const SolveOptions& opt, const ProgressFn& progress) {
  // Levenberg-Marquardt with Marquardt's scaling: (J^T J + mu diag(J^T J)) dz = -J^T C, the
  // damped normal equations factorised at every trial; mu adapted from the gain ratio
  // (Nielsen's rule). Damping bounds the step in the directions sparse observations barely
  // determine, where an undamped factorised step is dominated by round-off.
  SolveReport rep;
  precond_.reset();
  const int np = num_physics_rows();
  linearize(Z);
  record_cost(rep, C_, np);
  double mu = opt.lm_damping, nu = 2.0;
  for (int it = 0; it < opt.max_iterations; ++it) {
    if (it > 0) linearize_jacobian(Z);
    const Eigen::SparseMatrix<double> J = assemble_jacobian();
    const Eigen::SparseMatrix<double> JtJ = J.transpose() * J;
    const VecX g = J.transpose() * C_;
    VecX d = JtJ.diagonal();
    floor_column_norms(d);
    const double cost = 0.5 * C_.squaredNorm();
    bool accepted = false;
    int trials = 0;
    VecX Ct;
    MatXr Zt;
    // The damped matrices of this step share one pattern (J^T J with its whole diagonal): one
    // symbolic analysis for all trials.
    Eigen::SparseMatrix<double> pattern = JtJ;
    for (int i = 0; i < pattern.rows(); ++i) pattern.coeffRef(i, i) += 0.0;  // inserts a missing diagonal entry
    Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt;
    ldlt.analyzePattern(pattern);
    for (; trials < 16 && !accepted; ++trials) {
      Eigen::SparseMatrix<double> A = pattern;
      A.diagonal() += mu * d;
      ldlt.factorize(A);
      if (ldlt.info() != Eigen::Success) {
        mu *= nu;
        nu *= 2;
        continue;
      }
      const VecX dz = ldlt.solve(-g);
      const double predicted = -g.dot(dz) - 0.5 * (J * dz).squaredNorm();
      Zt = Z + Eigen::Map<const MatXr>(dz.data(), frames_, r_);
      const bool ok = trial_residual(Zt, Ct);
      const double new_cost = ok ? 0.5 * Ct.squaredNorm() : std::numeric_limits<double>::infinity();
      if (ok && new_cost < cost && predicted > 0) {
        accepted = true;
        const double rho = (cost - new_cost) / predicted;
        mu *= std::max(1.0 / 3.0, 1.0 - std::pow(2.0 * rho - 1.0, 3));
        nu = 2.0;
      } else {
        mu *= nu;
        nu *= 2;
      }
    }
    if (accepted) {
      Z = Zt;
      C_ = Ct;
    }
    if (book_step(rep, trials, accepted ? 1.0 : 0.0, Ct, cost, np, opt, progress, it)) break;
  }
  linearized_ = false;
  precond_.reset();
  return rep;
}

SolveReport SpaceTimeProblem::solve(MatXr& Z, const SolveOptions& opt, const ProgressFn& progress) {
  if (Z.rows() != frames_ || Z.cols() != r_)
    throw InvalidInput("Z: expected shape (" + std::to_string(frames_) + ", " +
                       std::to_string(r_) + ")");
  if (opt.solver == "lm") {
    if (!(opt.lm_damping > 0)) throw InvalidInput("lm_damping must be > 0");
    if (opt.jacobian_every != 1)
      throw InvalidInput("solver 'lm' re-evaluates the Jacobian at every step: jacobian_every must be 1");
    return solve_lm(Z, opt, progress);
  }
  SolveReport rep;
  precond_.reset();
  const int np = num_physics_rows();
  if (opt.jacobian_every < 1) throw InvalidInput("jacobian_every must be >= 1");
  double last_step = 1.0;
  for (int it = 0; it < opt.max_iterations; ++it) {
    if (it == 0) {
      linearize(Z);
      record_cost(rep, C_, np);
    } else if (opt.jacobian_every == 1) {
      linearize_jacobian(Z);  // C_ is already the residual at Z (from the line search)
    } else if (it % opt.jacobian_every == 0 || last_step < 1.0) {
      linearize_jacobian(Z);
      precond_.reset();  // chord steps: the preconditioner of the blocks they reuse (exact)
    } else {
      linearized_ = true;  // chord step: the blocks of an earlier step, the residual at Z
    }
    const double cost = 0.5 * C_.squaredNorm();
    int cg = 0;
    const VecX dz = solve_linear(opt, &cg);
    const Eigen::Map<const MatXr> dZ(dz.data(), frames_, r_);
    double t = 1.0;
    bool accepted = false;
    VecX Ct;
    MatXr Zt;
    for (int ls = 0; ls < 12; ++ls, t *= 0.5) {
      Zt = Z + t * dZ;
      if (!trial_residual(Zt, Ct)) continue;  // shorten the step
      if (0.5 * Ct.squaredNorm() < cost) {
        accepted = true;
        break;
      }
    }
    if (accepted) {
      Z = Zt;
      C_ = Ct;
      last_step = t;
    }
    if (book_step(rep, cg, accepted ? t : 0.0, Ct, cost, np, opt, progress, it)) break;
  }
  linearized_ = false;  // Z moved past the last linearisation
  precond_.reset();
  return rep;
}

MatX3 SpaceTimeProblem::control_forces(const MatXr& Z) const {
  if (Z.rows() != frames_ || Z.cols() != r_)
    throw InvalidInput("Z: expected shape (" + std::to_string(frames_) + ", " +
                       std::to_string(r_) + ")");
  const int nb = frames_ - 2;
  MatX3 out(size_t(nb) * n_, 3);
  const VecX& m = model_->dof_mass();
  std::string err;
#pragma omp parallel for schedule(dynamic) if (parallel_ok(*model_))
  for (int b = 0; b < nb; ++b) {
    try {
      MatX3 xm, xi, xp, v, vtmp;
      frame_state(Z, b, xm, vtmp);
      frame_state(Z, b + 1, xi, vtmp);
      frame_state(Z, b + 2, xp, v);
      const VecX f = model_->forces(xp, v);
      const auto fe = fext_.row(fext_.rows() > 1 ? b + 2 : 0).transpose();
      VecX g = m.cwiseProduct(as_dofs(xm) - 2.0 * as_dofs(xi) + as_dofs(xp)) / (h_ * h_) - f - fe;
      g = g.cwiseProduct((1.0 - constrained_.array()).matrix());
      out.middleRows(size_t(b) * n_, n_) = Eigen::Map<const MatX3>(g.data(), n_, 3);
    } catch (const std::exception& e) {
#pragma omp critical
      err = e.what();
    }
  }
  if (!err.empty()) throw NumericalError("control forces: " + err);
  return out;
}

}  // namespace matlearn::spacetime
