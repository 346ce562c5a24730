#pragma once
#include <functional>
#include <memory>
#include <vector>

#include "common/types.hpp"
#include "fem/model.hpp"
#include "fem/sparse_assembler.hpp"
#include "solvers/cholmod_solver.hpp"

namespace matlearn::time {

/// Called every few steps with (steps done, steps total); may throw to cancel.
using ProgressFn = std::function<void(int, int)>;

struct StepOptions {
  int max_newton = 8;        ///< 1 = one linearised solve per step (Baraff-Witkin style)
  double tolerance = 1e-7;   ///< Newton stops when |dv| <= tolerance * (|v| + v_ref)
  /// Reuse the last factorised step matrix (a chord / lagged-Newton iteration: forces only,
  /// one triangular solve per iteration) while it contracts by at least `reuse_ratio` per
  /// iteration; otherwise refactorise at the current state. Same fixed point and stopping test
  /// as Newton (whose PSD-projected tangent converges only linearly anyway, ratio ~1e-2).
  /// Never used with max_newton = 1 (the linearised step stays exactly that).
  bool reuse_factorization = true;
  double reuse_ratio = 0.25;
  /// Start each step's iteration from v_n + (v_n - v_{n-1}) instead of v_n (not with
  /// max_newton = 1, whose answer depends on the starting point).
  bool extrapolate = true;
};

/// Wall-clock seconds spent in each phase of the last step, summed over its Newton iterations
/// (for benchmarks and profiling).
struct StepTimings {
  double evaluate_s = 0;   ///< element evaluation (SVD, stresses, element matrices) + force gather
  double assemble_s = 0;   ///< scatter into the fixed-pattern system matrix
  double factorize_s = 0;  ///< CHOLMOD numeric factorisation
  double solve_s = 0;      ///< CHOLMOD triangular solves
  int iterations = 0;
  int factorizations = 0;  ///< iterations that evaluated the tangent and refactorised
  /// Per iteration of the last step: |dv| (signed: negative for an iteration that used a freshly
  /// factorised tangent), including discarded chord updates (for diagnosis and tests).
  std::vector<double> updates;
};

/// Backward Euler for a Model with clamped vertices, gravity, external forces and optionally
/// prescribed ("constrained") vertices that follow given trajectories (method.md section 4).
/// Owns the state (x, v) and a CHOLMOD factorisation whose symbolic analysis is reused.
class Integrator {
 public:
  Integrator(std::shared_ptr<const fem::Model> model, const VecXi& fixed, double time_step,
             const Vec3& gravity, StepOptions options = {});

  const fem::Model& model() const { return *model_; }
  double time_step() const { return h_; }
  const MatX3& x() const { return x_; }
  const MatX3& v() const { return v_; }
  void set_state(const MatX3& x, const MatX3& v);
  int steps_taken() const { return steps_; }
  const VecXi& fixed() const { return fixed_; }
  const VecXi& prescribed() const { return prescribed_; }
  StepOptions& options() { return opts_; }
  /// Newton iterations used by the last step.
  int last_iterations() const { return last_iters_; }
  /// Steps since construction or the last set_state() whose Newton iteration stopped at its
  /// iteration limit without meeting the tolerance (the step was kept as it was: an inaccurate,
  /// possibly unstable step). Never counted with max_newton = 1, whose single linearised solve
  /// is the step by design.
  int unconverged_steps() const { return unconverged_; }
  /// Phase timings of the last step.
  const StepTimings& last_timings() const { return timings_; }

  /// Vertices whose positions are prescribed at the end of each constrained step.
  void set_prescribed(const VecXi& vertices);

  /// One step with external force f_ext (#V x 3, N). targets: (#prescribed x 3) positions at
  /// the end of the step (required iff prescribed vertices are set).
  void step(const MatX3& f_ext, const MatX3* targets = nullptr);

  /// `steps` steps under constant f_ext; returns positions at every `record_every`-th step
  /// (including the initial state), stacked as (frames*#V x 3).
  MatX3 simulate(int steps, const MatX3& f_ext, int record_every, const ProgressFn& progress = {},
                 MatX3* velocities = nullptr);

  /// One step per target frame: targets (steps*#prescribed x 3). Returns positions after each
  /// step, initial state included, as ((steps+1)*#V x 3).
  MatX3 simulate_constrained(const MatX3& targets, const MatX3& f_ext, const ProgressFn& progress = {},
                             MatX3* velocities = nullptr);

  /// Static equilibrium under f_ext + gravity from the current x, in load_steps increments:
  /// Newton on the PSD-projected tangent with backtracking, plus chord steps that reuse the
  /// last factorised tangent while they contract the residual by kChordContraction (or about as
  /// well as the last fresh tangent did, up to 0.75). Stops when |residual| <= tolerance |f_ext + gravity| (free
  /// DOFs); at most max_iterations tangent factorisations and 4 max_iterations steps per load
  /// step. Sets x to the solution and v to zero.
  void static_solve(const MatX3& f_ext, int load_steps = 1, int max_iterations = 50,
                    double tolerance = 1e-9);
  /// Iterations (chord and fresh) and tangent factorisations of the last static_solve.
  const StepTimings& last_static_timings() const { return static_timings_; }
  static constexpr double kChordContraction = 0.25;

 private:
  void rebuild_pattern();
  std::shared_ptr<const fem::Model> model_;
  VecXi fixed_, prescribed_;
  double h_;
  Vec3 gravity_;
  StepOptions opts_;
  MatX3 x_, v_;
  MatX3 prev_v_;  // velocity before the last step (for the extrapolated initial guess)
  bool has_prev_v_ = false;
  int steps_ = 0, last_iters_ = 0, unconverged_ = 0;
  StepTimings timings_, static_timings_;
  VecXi dof_map_;  // global dof -> free index or -1
  int n_free_ = 0;
  std::unique_ptr<fem::SparseAssembler> assembler_;
  solvers::CholmodSolver solver_;
  SpMat A_;
  VecX coeff_, diag_;  // per-element matrix coefficients and system diagonal (Rayleigh path)
  bool factor_valid_ = false;  // solver_ holds a step matrix of this pattern (reusable)
  double size_;
};

// The backward-Euler matrix M + h D + h^2 K of an evaluated state. Without a correction the
// damping is Rayleigh, so it is assembled from the element stiffnesses scaled by h^2 + h alpha_K
// plus a lumped diagonal M + h alpha_M M (no D blocks needed). coeff/diag are scratch.
void assemble_step_matrix(const fem::Model& model, const fem::ElementState& st, double h,
                          const VecX& mass, bool rayleigh_only, const fem::SparseAssembler& assembler,
                          VecX& coeff, VecX& diag, SpMat& A);

// Throws NumericalError naming `step` when the velocities v are not finite or move faster than
// 1e4 object sizes (`size`) per step of length h: no longer a simulation, a divergence.
void check_divergence(const MatX3& v, double h, double size, int step);

}  // namespace matlearn::time
