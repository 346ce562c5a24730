// CHOLMOD wrapper: relative residual on SPD systems (simplicial and supernodal sizes), reuse of
// the symbolic analysis across values, and exceptions on a non-SPD matrix and on misuse.
#include <random>

#include "check.hpp"
#include "solvers/cholmod_solver.hpp"

using namespace matlearn;
using solvers::CholmodSolver;

namespace {

/// Upper triangle of a 3D grid Laplacian (n^3 unknowns) + shift * I: SPD, well conditioned.
SpMat laplacian_upper(int n, double shift, double diag_scale = 1.0) {
  auto id = [n](int i, int j, int k) { return (i * n + j) * n + k; };
  std::vector<Eigen::Triplet<double, int>> t;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      for (int k = 0; k < n; ++k) {
        const int r = id(i, j, k);
        t.emplace_back(r, r, diag_scale * (6.0 + shift));
        if (i + 1 < n) t.emplace_back(r, id(i + 1, j, k), -1.0);
        if (j + 1 < n) t.emplace_back(r, id(i, j + 1, k), -1.0);
        if (k + 1 < n) t.emplace_back(r, id(i, j, k + 1), -1.0);
      }
  SpMat A(n * n * n, n * n * n);
  A.setFromTriplets(t.begin(), t.end());
  A.makeCompressed();
  return A;
}

double relative_residual(const SpMat& upper, const VecX& x, const VecX& b) {
  const SpMat full = SpMat(upper.selfadjointView<Eigen::Upper>());
  return (full * x - b).norm() / b.norm();
}

}  // namespace

TEST_CASE(solves_spd_systems_small_and_large) {
  std::mt19937 rng(1);
  std::normal_distribution<double> n(0, 1);
  for (int size : {5, 30}) {  // 125 unknowns (simplicial) and 27k unknowns (supernodal)
    const SpMat A = laplacian_upper(size, 0.1);
    VecX b(A.rows());
    for (int i = 0; i < b.size(); ++i) b[i] = n(rng);
    CholmodSolver s;
    s.analyze(A);
    s.factorize(A);
    const VecX x = s.solve(b);
    CHECK_MSG(relative_residual(A, x, b) < 1e-10, "size " + std::to_string(size) + " residual " +
                                                     std::to_string(relative_residual(A, x, b)));
  }
}

TEST_CASE(reuses_analysis_for_new_values) {
  CholmodSolver s;
  SpMat A = laplacian_upper(6, 0.5);
  s.analyze(A);
  const VecX b = VecX::LinSpaced(A.rows(), -1, 1);
  for (double scale : {1.0, 3.0, 0.2}) {
    SpMat B = A;
    B.coeffs() *= scale;
    s.factorize(B);
    const VecX x = s.solve(b);
    CHECK(relative_residual(B, x, b) < 1e-12);
  }
}

TEST_CASE(non_spd_matrix_throws) {
  CholmodSolver s;
  SpMat A = laplacian_upper(4, 0.1);
  s.analyze(A);
  SpMat N = A;
  N.coeffRef(7, 7) = -1.0;
  CHECK_THROWS(s.factorize(N), NumericalError);
  CHECK(!s.factorized());
  CHECK_THROWS(s.solve(VecX::Ones(A.rows())), std::logic_error);
  // The solver recovers on the next valid matrix.
  s.factorize(A);
  const VecX b = VecX::Ones(A.rows());
  CHECK(relative_residual(A, s.solve(b), b) < 1e-12);
  // Supernodal path too.
  CholmodSolver big;
  SpMat L = laplacian_upper(30, 0.1);
  big.analyze(L);
  L.coeffRef(12345, 12345) = -50.0;
  CHECK_THROWS(big.factorize(L), NumericalError);
}

TEST_CASE(misuse_throws) {
  CholmodSolver s;
  CHECK_THROWS(s.solve(VecX::Ones(3)), std::logic_error);  // solve before factorize
  SpMat rect(3, 4);
  CHECK_THROWS(s.analyze(rect), InvalidInput);
  const SpMat A = laplacian_upper(3, 0.1);
  s.analyze(A);
  s.factorize(A);
  CHECK_THROWS(s.solve(VecX::Ones(5)), InvalidInput);  // wrong right-hand side size
  CHECK_THROWS(s.factorize(laplacian_upper(4, 0.1)), InvalidInput);  // size changed
  // Moving keeps the factorisation usable.
  CholmodSolver moved(std::move(s));
  const VecX b = VecX::Ones(A.rows());
  CHECK(relative_residual(A, moved.solve(b), b) < 1e-12);
}
