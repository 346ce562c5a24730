#pragma once
// Linearised backward Euler (one Newton iteration per step, exactly Integrator's step with
// max_newton = 1) for many simulations of the same mesh and clamp with different models, as in
// fitting: the system matrix is solved by conjugate gradients preconditioned with a Cholesky
// factor of an earlier system matrix (earlier step or earlier model), refactorised only when
// the iteration count grows. The solve is converged to a tight relative residual, so results
// match the direct solve to round-off; the factorisation, which dominates a step, is mostly
// skipped.
#include <memory>

#include "common/types.hpp"
#include "fem/model.hpp"
#include "fem/sparse_assembler.hpp"
#include "solvers/cholmod_solver.hpp"

namespace matlearn::time {

using MatX4 = Eigen::Matrix<double, Eigen::Dynamic, 4, Eigen::RowMajor>;

struct ReplayStats {
  long steps = 0;
  long factorizations = 0;
  long pcg_iterations = 0;
  long direct_fallbacks = 0;
};

class LinearisedReplay {
 public:
  /// `mesh_model` fixes the mesh (pattern); models passed to simulate() must share its mesh size.
  /// `prescribed`: vertices that follow given targets (drive points), as Integrator's
  /// set_prescribed: each step gives them the velocity that reaches their target at its end and
  /// leaves them there; simulate() and tangent() then need `targets`.
  LinearisedReplay(const fem::Model& mesh_model, const VecXi& fixed, double time_step,
                   const Vec3& gravity, double tolerance = 1e-10, int refresh_iterations = 10,
                   int max_iterations = 40, const VecXi& prescribed = VecXi());

  /// Simulate `steps` steps of `model` from (x0, v0) with constant external forces; returns the
  /// positions ((steps+1) * #V, 3), the initial state first; velocities likewise if requested.
  /// targets: (steps * #prescribed, 3) positions of the prescribed vertices at the end of each
  /// step (Integrator::simulate_constrained's layout); required iff there are prescribed vertices.
  MatX3 simulate(const fem::Model& model, const MatX3& x0, const MatX3& v0, int steps,
                 const MatX3& f_ext, MatX3* velocities = nullptr, const MatX3* targets = nullptr);

  /// Forward-mode sensitivities of simulate() with respect to per-element log-stiffness changes
  /// (E_e -> E_e exp(theta_e): mu, lambda and the stiffness-damping force of the element scale
  /// together), for the k directions in the columns of `directions` (#T x k) at once: every
  /// step is factorised once and the k tangent systems share the factor. Output points are
  /// barycentric combinations of 4 vertices (`point_vertices`, `point_weights`, P x 4), e.g.
  /// markers; `dx0` (3#V x k) is the derivative of the initial positions (that of the initial
  /// velocities is zero). The step is differentiated with its matrix's dependence on the state
  /// dropped (kept: its dependence on theta), i.e. the Newton-consistent linearisation with the
  /// projected tangent; it matches finite differences of simulate() to O(h) in relative terms.
  /// Needs a model without correction and stretch edits (stress linear in mu and lambda).
  /// Prescribed vertices (targets as in simulate()) have zero derivative: their motion is given.
  /// Writes `out` ((steps+1) x P x 3 x k, C order); returns the positions like simulate().
  MatX3 tangent(const fem::Model& model, const MatX3& x0, const MatX3& v0, int steps,
                const MatX3& f_ext, const MatX& dx0, const MatX& directions,
                const MatX4i& point_vertices, const MatX4& point_weights, double* out,
                const MatX3* targets = nullptr);
  const VecXi& prescribed() const { return prescribed_; }

  const ReplayStats& stats() const { return stats_; }

 private:
  VecX solve(const VecX& b, int step);
  /// Factorises A_ (errors name the step), counts it in the stats.
  void factorize_at(int step);
  /// Adds the free-DOF velocity update dv to v, checks it for divergence (step s), and
  /// advances the state: vs = v, xs += h v.
  void advance(const VecX& dv, int s, MatX3& v, MatX3& vs, MatX3& xs);
  /// Checks `targets` for `steps` steps (shape, finite; present iff there are prescribed vertices).
  void check_targets(const MatX3* targets, int steps) const;
  /// The start velocity of step s: zero on the clamped vertices, on the prescribed ones the
  /// velocity that reaches their target at the step's end.
  void start_velocity(const MatX3& xs, const MatX3* targets, int s, MatX3& v) const;
  /// After step s: the prescribed vertices exactly at their targets (as Integrator::step).
  void place_prescribed(const MatX3* targets, int s, MatX3& xs) const;
  /// Backward-Euler residual on the free DOFs at velocity v from vs: M (v - vs) - h (f + fconst),
  /// f the forces of the evaluated element state `st`.
  VecX step_residual(const fem::Model& model, const fem::ElementState& st, const MatX3& v,
                     const MatX3& vs, const VecX& mass, const VecX& fconst) const;
  VecXi fixed_, prescribed_, dof_map_;
  int nv_, nt_, n_free_ = 0;
  double h_, tol_;
  int refresh_, max_it_;
  Vec3 gravity_;
  double size_;
  std::unique_ptr<fem::SparseAssembler> assembler_;
  solvers::CholmodSolver solver_;
  bool have_factor_ = false;
  SpMat A_;
  VecX coeff_, diag_;
  ReplayStats stats_;
};

}  // namespace matlearn::time
