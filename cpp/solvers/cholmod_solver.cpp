#include "solvers/cholmod_solver.hpp"

#include <suitesparse/cholmod.h>

#include <string>

namespace matlearn::solvers {

namespace {
cholmod_sparse view(const SpMat& A) {
  cholmod_sparse s{};
  s.nrow = A.rows();
  s.ncol = A.cols();
  s.nzmax = A.nonZeros();
  s.p = const_cast<int*>(A.outerIndexPtr());
  s.i = const_cast<int*>(A.innerIndexPtr());
  s.x = const_cast<double*>(A.valuePtr());
  s.stype = 1;
  s.itype = CHOLMOD_INT;
  s.xtype = CHOLMOD_REAL;
  s.dtype = CHOLMOD_DOUBLE;
  s.sorted = 1;
  s.packed = 1;
  return s;
}
}  // namespace

CholmodSolver::CholmodSolver() {
  common_ = reinterpret_cast<cholmod_common_struct*>(new cholmod_common);
  cholmod_start(reinterpret_cast<cholmod_common*>(common_));
  auto* c = reinterpret_cast<cholmod_common*>(common_);
  c->print = 0;
  // Simplicial factorisations default to LDL^T, which succeeds on indefinite matrices (only a
  // zero pivot stops it). LL^T fails at the first non-positive pivot, which is what detects a
  // non-SPD system (supernodal is always LL^T).
  c->final_ll = 1;
}

void CholmodSolver::release() {
  auto* c = reinterpret_cast<cholmod_common*>(common_);
  if (c) {
    if (factor_) {
      auto* L = reinterpret_cast<cholmod_factor*>(factor_);
      cholmod_free_factor(&L, c);
    }
    cholmod_finish(c);
    delete c;
  }
  common_ = nullptr;
  factor_ = nullptr;
}

CholmodSolver::~CholmodSolver() { release(); }

CholmodSolver::CholmodSolver(CholmodSolver&& o) noexcept
    : common_(o.common_), factor_(o.factor_), n_(o.n_), factorized_(o.factorized_) {
  o.common_ = nullptr;
  o.factor_ = nullptr;
}

CholmodSolver& CholmodSolver::operator=(CholmodSolver&& o) noexcept {
  if (this != &o) {
    release();
    common_ = o.common_;
    factor_ = o.factor_;
    n_ = o.n_;
    factorized_ = o.factorized_;
    o.common_ = nullptr;
    o.factor_ = nullptr;
  }
  return *this;
}

void CholmodSolver::analyze(const SpMat& A) {
  if (A.rows() != A.cols()) throw InvalidInput("CholmodSolver: matrix must be square");
  auto* c = reinterpret_cast<cholmod_common*>(common_);
  if (factor_) {
    auto* L = reinterpret_cast<cholmod_factor*>(factor_);
    cholmod_free_factor(&L, c);
    factor_ = nullptr;
  }
  cholmod_sparse s = view(A);
  c->supernodal = CHOLMOD_AUTO;
  // Try AMD and both nested dissections and keep the ordering with the least fill: analysis
  // runs once per sparsity pattern, and on 3D tet meshes nested dissection saved ~15 % of the
  // factorisation flops where CHOLMOD's default heuristic kept AMD (10k-tet bar: 4.4e8 -> 3.7e8).
  c->nmethods = 3;
  c->method[0].ordering = CHOLMOD_AMD;
  c->method[1].ordering = CHOLMOD_METIS;
  c->method[2].ordering = CHOLMOD_NESDIS;
  cholmod_factor* L = cholmod_analyze(&s, c);
  // Supernodal pays only once BLAS-3 blocks are big; below ~3e7 flops per factorisation the
  // simplicial code was 2-3x faster here (1.5k DOFs: 10 ms vs 30 ms).
  if (L && c->status >= CHOLMOD_OK && c->fl < 3e7 && L->is_super) {
    cholmod_free_factor(&L, c);
    c->supernodal = CHOLMOD_SIMPLICIAL;
    L = cholmod_analyze(&s, c);
  }
  if (!L || c->status < CHOLMOD_OK)
    throw NumericalError("CHOLMOD analyze failed (status " + std::to_string(c->status) + ")");
  factor_ = reinterpret_cast<cholmod_factor_struct*>(L);
  n_ = A.rows();
  factorized_ = false;
}

void CholmodSolver::factorize(const SpMat& A) {
  if (!factor_) analyze(A);
  if (A.rows() != n_) throw InvalidInput("CholmodSolver: matrix size changed since analyze()");
  auto* c = reinterpret_cast<cholmod_common*>(common_);
  auto* L = reinterpret_cast<cholmod_factor*>(factor_);
  cholmod_sparse s = view(A);
  cholmod_factorize(&s, L, c);
  factorized_ = false;
  if (c->status == CHOLMOD_NOT_POSDEF || L->minor < L->n)
    throw NumericalError("system matrix is not positive definite (CHOLMOD failed at column " +
                         std::to_string(L->minor) + " of " + std::to_string(L->n) + ")");
  if (c->status < CHOLMOD_OK)
    throw NumericalError("CHOLMOD factorize failed (status " + std::to_string(c->status) + ")");
  factorized_ = true;
}

VecX CholmodSolver::solve(const VecX& b) const {
  if (!factorized_) throw std::logic_error("CholmodSolver: solve() called before factorize()");
  if (b.size() != n_) throw InvalidInput("CholmodSolver: right-hand side has wrong size");
  return solve_many(b).col(0);  // one right-hand side: the same CHOLMOD dense solve
}

MatX CholmodSolver::solve_many(const MatX& B) const {
  if (!factorized_) throw std::logic_error("CholmodSolver: solve() called before factorize()");
  if (B.rows() != n_) throw InvalidInput("CholmodSolver: right-hand side has wrong size");
  if (B.cols() == 0) return MatX(n_, 0);
  auto* c = reinterpret_cast<cholmod_common*>(common_);
  auto* L = reinterpret_cast<cholmod_factor*>(factor_);
  cholmod_dense bd{};
  bd.nrow = n_;
  bd.ncol = B.cols();
  bd.nzmax = B.size();
  bd.d = n_;
  bd.x = const_cast<double*>(B.data());
  bd.xtype = CHOLMOD_REAL;
  bd.dtype = CHOLMOD_DOUBLE;
  cholmod_dense* x = cholmod_solve(CHOLMOD_A, L, &bd, c);
  if (!x) throw NumericalError("CHOLMOD solve failed");
  MatX out = Eigen::Map<MatX>(static_cast<double*>(x->x), n_, B.cols());
  cholmod_free_dense(&x, c);
  return out;
}

}  // namespace matlearn::solvers
