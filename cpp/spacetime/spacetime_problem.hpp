#pragma once
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "common/types.hpp"
#include <Eigen/SparseCholesky>

#include "fem/model.hpp"

namespace matlearn::spacetime {

/// Row-major dense matrix (frames x dofs, samples x rows...).
using MatXr = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

/// Sparse observations of a trajectory (method.md section 5). Marker k sits at a fixed linear
/// combination of vertices (barycentric embedding E, K x #V); S = E (x) I3 selects marker
/// coordinates. Sample t is taken at a time between frames frame[t] and frame[t]+1:
///   s_t ~ (1 - weight[t]) S x_{frame[t]} + weight[t] S x_{frame[t]+1}.
struct Observations {
  MatXr S_phi;     ///< (3K x r) S Phi: marker coordinates per unit modal coordinate
  MatXr S_base;    ///< (frames x 3K) or (1 x 3K): S x_base per frame (x = x_base + Phi z)
  VecXi frame;     ///< (T) frame before each sample
  VecX weight;     ///< (T) interpolation weight of frame[t]+1, in [0, 1]
  MatXr targets;   ///< (T x 3K) observed marker coordinates, NaN where unseen
};

/// Options of the Gauss-Newton solve.
struct SolveOptions {
  int max_iterations = 10;     ///< Gauss-Newton steps
  int cg_iterations = 300;     ///< CGLS iterations per step
  double cg_tolerance = 1e-6;  ///< CGLS stops when |J^T r| <= tol |J^T r_0|
  double tolerance = 1e-5;     ///< stop when the cost decreases by less than this fraction
  /// "pcgls": matrix-free CGLS (on J p, J^T q) preconditioned by a factorisation of J^T J frozen
  /// at the first Gauss-Newton step of a solve (refreshed when CG needs > refresh_iterations);
  /// "cgls": matrix-free CGLS with Jacobi column scaling only;
  /// "direct": factorise the block-banded normal equations J^T J at every step;
  /// "lm": Levenberg-Marquardt (solve_lm; what matlearn.learning uses).
  std::string solver = "pcgls";
  int refresh_iterations = 30;
  /// "lm": Levenberg-Marquardt on the factorised damped normal equations, starting damping
  /// (relative to diag(J^T J)).
  double lm_damping = 1e-3;
  /// Gauss-Newton steps per evaluation of the Jacobian blocks (1: every step, exact
  /// Gauss-Newton on the nominal tangent). k > 1 re-evaluates them at every k-th step and after
  /// a step the line search had to shorten, reusing them in between (a chord Gauss-Newton: the
  /// residual stays exact; the blocks are dominated by the mass term M/h^2 and the linear
  /// observation rows, and their evaluation costs more than a residual on long recordings).
  int jacobian_every = 1;
};

/// Called after each Gauss-Newton step with (step, max steps); may throw to cancel.
using ProgressFn = std::function<void(int, int)>;

struct SolveReport {
  std::vector<double> cost;           ///< 0.5 |C|^2 before the first step and after each step
  std::vector<double> physics_cost;   ///< 0.5 |C_f|^2 likewise
  std::vector<int> cg_iterations;     ///< CGLS iterations of each step (0 for direct)
  std::vector<double> step_length;    ///< accepted line-search factor of each step
};

/// Sparse reduced space-time problem over frames 0..N (method.md section 5):
///   x_i = x_base_i + Phi z_i, v_i = (x_i - x_{i-1}) / h,
///   physics  C_f,i = Phi^T (M (x_{i-1} - 2 x_i + x_{i+1}) / h^2 - f(x_{i+1}, v_{i+1}) - fext_{i+1})
///            for i = 1..N-1 (r rows each),
///   observation C_z,t = lambda (S x(t_t) - s_t) on the seen coordinates of each sample.
/// Constrained vertices (clamped or driven) have zero rows in Phi and follow x_base.
/// The Jacobian is kept as per-frame reduced r x r blocks built from the *nominal* tangent
/// (the correction stays in the residual); products J p and J^T q cost O(N r^2 + T K r).
class SpaceTimeProblem {
 public:
  /// phi (3#V x r); base (frames x 3#V) or (1 x 3#V); fext (frames x 3#V) or (1 x 3#V), N,
  /// external force including gravity; h time step (s); lambda observation weight.
  SpaceTimeProblem(std::shared_ptr<const fem::Model> model, MatX phi, MatXr base, MatXr fext,
                   double h, Observations obs, double lambda, bool nominal_tangent = true);

  int frames() const { return frames_; }
  int modes() const { return r_; }
  int num_unknowns() const { return frames_ * r_; }
  int num_physics_rows() const { return (frames_ - 2) * r_; }
  int num_residuals() const { return num_physics_rows() + int(obs_.frame.size()) * obs_rows_; }
  double lambda() const { return lambda_; }

  /// Full positions of all frames, (frames*#V x 3), for modal coordinates Z (frames x r).
  MatX3 positions(const MatXr& Z) const;
  /// Residual vector C(Z): physics rows first, then observation rows (unseen rows are 0).
  VecX residual(const MatXr& Z) const;
  /// Frames per tangent evaluation in the Jacobian blocks (1: every frame, the default). k > 1
  /// evaluates the nominal tangent at the middle frame of each run of k frames and shares it
  /// (long recordings at 1 ms change little within a few frames; the residual stays exact,
  /// only the Gauss-Newton direction is approximated).
  int tangent_stride() const { return tangent_stride_; }
  void set_tangent_stride(int k) {
    if (k < 1) throw InvalidInput("tangent_stride must be >= 1");
    tangent_stride_ = k;
    linearized_ = false;
  }
  /// Evaluate residual and reduced Jacobian blocks at Z (needed before jvp/vjp).
  void linearize(const MatXr& Z);
  /// J p for p of length frames*r (frame-major); J^T q for q of length num_residuals().
  VecX jvp(const VecX& p) const;
  VecX vjp(const VecX& q) const;
  /// Residual at the last linearisation point.
  const VecX& last_residual() const { return C_; }
  /// Solve min |J dz + C| at the last linearisation point.
  VecX solve_linear(const SolveOptions& opt, int* iterations) const;
  /// Gauss-Newton with backtracking line search from Z (updated in place).
  SolveReport solve(MatXr& Z, const SolveOptions& opt, const ProgressFn& progress = {});
  /// Levenberg-Marquardt from Z (updated in place): (J^T J + mu diag(J^T J)) dz = -J^T C
  /// factorised at every trial, mu from opt.lm_damping adapted by the gain ratio (Nielsen).
  /// The report's cg_iterations are the trials per step, step_length 1 (accepted) or 0.
  SolveReport solve_lm(MatXr& Z, const SolveOptions& opt, const ProgressFn& progress = {});
  /// The residual at a trial point into Ct; false (Ct unchanged) where the model cannot be
  /// evaluated there (NumericalError: the step is rejected, not the solve).
  bool trial_residual(const MatXr& Zt, VecX& Ct) const;
  /// Control forces fc_j for frames j = 2..N, ((frames-2)*#V x 3), N; zero on constrained
  /// vertices. fc_j = M (x_{j-2} - 2 x_{j-1} + x_j)/h^2 - f(x_j, v_j) - fext_j.
  MatX3 control_forces(const MatXr& Z) const;

 private:
  void frame_state(const MatXr& Z, int j, MatX3& x, MatX3& v) const;
  void linearize_jacobian(const MatXr& Z);  // the blocks A_, B_ only (C_ unchanged)
  VecX physics_block(const MatXr& Z, int i, const VecX& f_next) const;
  VecX column_scale() const;
  Eigen::SparseMatrix<double> assemble_jacobian() const;
  void factorize_normal(const Eigen::SparseMatrix<double>& J) const;

  std::shared_ptr<const fem::Model> model_, nominal_;
  MatX phi_;          // 3n x r
  MatXr base_, fext_;
  double h_, lambda_;
  Observations obs_;
  int frames_, r_, n_, obs_rows_;
  MatX Mr_;           // Phi^T M Phi
  VecX constrained_;  // 1 per dof where Phi row is zero
  // Linearisation: for residual block i (1..N-1): A_i = d/dz_{i+1}, B_i = d/dz_i; d/dz_{i-1} = Mr/h^2.
  std::vector<MatX> A_, B_;
  VecX C_;
  bool linearized_ = false;
  int tangent_stride_ = 1;
  mutable std::shared_ptr<Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>> precond_;
};

}  // namespace matlearn::spacetime
