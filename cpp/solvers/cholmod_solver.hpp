#pragma once
#include <memory>

#include "common/types.hpp"

struct cholmod_common_struct;
struct cholmod_factor_struct;

namespace matlearn::solvers {

/// Sparse Cholesky via CHOLMOD (supernodal where it pays). Owns its handles (RAII, move-only).
/// analyze() once per sparsity pattern, factorize() per matrix values, solve() after that.
/// The matrix must be symmetric with its upper triangle stored (row <= col).
class CholmodSolver {
 public:
  CholmodSolver();
  ~CholmodSolver();
  CholmodSolver(const CholmodSolver&) = delete;
  CholmodSolver& operator=(const CholmodSolver&) = delete;
  CholmodSolver(CholmodSolver&&) noexcept;
  CholmodSolver& operator=(CholmodSolver&&) noexcept;

  void analyze(const SpMat& A_upper);
  /// Throws NumericalError if A is not positive definite.
  void factorize(const SpMat& A_upper);
  VecX solve(const VecX& b) const;
  /// Several right-hand sides (columns of B) with one pass over the factor.
  MatX solve_many(const MatX& B) const;
  bool analyzed() const { return factor_ != nullptr; }
  bool factorized() const { return factorized_; }

 private:
  void release();
  cholmod_common_struct* common_ = nullptr;
  cholmod_factor_struct* factor_ = nullptr;
  int n_ = 0;
  bool factorized_ = false;
};

}  // namespace matlearn::solvers
