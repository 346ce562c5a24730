#include "learning/fit_normal_equations.hpp"

#include <algorithm>
#include <cmath>

#include "fem/svd.hpp"

namespace matlearn::learning {

namespace {

/// Elastic kernels g_k(s) (extended beyond the box, RbfCorrection) and damping kernels
/// phi_k(clamp(s)) for the rows of S (m x 3) -> (m x c) each.
void kernels(const MatX3& S, const RbfFeatures& rbf, MatX& G, MatX& Pa) {
  const int m = S.rows(), c = rbf.centers.rows();
  const bool box = rbf.lower.size() == 3;
  G.resize(m, c);
  Pa.resize(m, c);
  for (int e = 0; e < m; ++e) {
    const Vec3 s = S.row(e).transpose();
    const Vec3 sc = box ? Vec3(s.cwiseMax(rbf.lower).cwiseMin(rbf.upper)) : s;
    for (int k = 0; k < c; ++k)
      G(e, k) = correction::extended_kernel(s, sc, rbf.centers.row(k).transpose(), rbf.epsilon,
                                            nullptr, &Pa(e, k));
  }
}

MatX3 frame_rows(const MatX3& A, int j, int n) { return A.middleRows(long(j) * n, n); }

}  // namespace

MatX3 principal_stretches(const fem::Model& model, const MatX3& X) {
  const int n = model.mesh().num_vertices(), m = model.mesh().num_tets();
  if (X.rows() % n != 0) throw InvalidInput("X: rows must be a multiple of #V");
  const long frames = X.rows() / n;
  MatX3 S(frames * m, 3);
  for (long j = 0; j < frames; ++j) {
    const MatX3 x = frame_rows(X, int(j), n);
    model.check_state(x, "X");
    const int blocks = (m + fem::kSvdLanes - 1) / fem::kSvdLanes;
#pragma omp parallel for schedule(static)
    for (int b = 0; b < blocks; ++b) {  // kSvdLanes elements at a time (bitwise the scalar SVD)
      const int e0 = b * fem::kSvdLanes, count = std::min(fem::kSvdLanes, m - e0);
      Mat3 F[fem::kSvdLanes], U[fem::kSvdLanes], Vm[fem::kSvdLanes];
      Vec3 s[fem::kSvdLanes];
      for (int l = 0; l < count; ++l) F[l] = model.mesh().deformation_gradient(x, e0 + l);
      fem::rotation_variant_svd_lanes(F, U, s, Vm, count);
      for (int l = 0; l < count; ++l) S.row(j * m + e0 + l) = s[l].transpose();
    }
  }
  return S;
}

NormalEquations fit_normal_equations(const fem::Model& nominal, const fem::Model* current,
                                     const MatX3& X, const MatX3& V, const MatX3& FC,
                                     const MatX& phi, const Eigen::Matrix<bool, Eigen::Dynamic, 1>& free_dofs,
                                     const RbfFeatures& rbf, bool damping) {
  const int n = nominal.mesh().num_vertices(), m = nominal.mesh().num_tets();
  const int c = rbf.centers.rows();
  if (c < 1) throw InvalidInput("fit_normal_equations: no RBF centres");
  if (!(rbf.epsilon > 0)) throw InvalidInput("fit_normal_equations: epsilon must be > 0");
  if ((rbf.lower.size() != 0 && rbf.lower.size() != 3) || rbf.lower.size() != rbf.upper.size())
    throw InvalidInput("fit_normal_equations: lower/upper must both be empty or have 3 entries");
  if (X.rows() % n != 0 || X.rows() == 0)
    throw InvalidInput("fit_normal_equations: X must hold frames*#V rows, #V = " + std::to_string(n));
  if (V.rows() != X.rows() || FC.rows() != X.rows())
    throw InvalidInput("fit_normal_equations: X, V and FC must have the same shape");
  if (current && (current->mesh().num_vertices() != n || current->mesh().num_tets() != m))
    throw InvalidInput("fit_normal_equations: current model has a different mesh");
  const bool basis = phi.cols() > 0;
  if (basis && phi.rows() != 3 * n)
    throw InvalidInput("fit_normal_equations: phi must have 3*#V rows");
  if (!basis && free_dofs.size() != 3 * n)
    throw InvalidInput("fit_normal_equations: free_dofs must have 3*#V entries when phi is empty");
  std::vector<int> keep;
  if (!basis)
    for (int i = 0; i < 3 * n; ++i)
      if (free_dofs[i]) keep.push_back(i);
  const int rows = basis ? int(phi.cols()) : int(keep.size());
  const int ne = 3 * (c + 3), p = ne + (damping ? c + 1 : 0);
  MatX rest_g, rest_a;
  kernels(MatX3::Ones(1, 3), rbf, rest_g, rest_a);
  const VecX rest_phi = rest_g.row(0).transpose();

  NormalEquations out;
  out.N.setZero(p, p);
  out.rhs.setZero(p);
  const long frames = X.rows() / n;
  const MatX3 S_all = principal_stretches(nominal, X);
  MatX D(rows, p);
  for (long j = 0; j < frames; ++j) {
    const MatX3 x = frame_rows(X, int(j), n), v = frame_rows(V, int(j), n);
    const MatX3 S = S_all.middleRows(j * m, m);
    MatX Pe, P;
    kernels(S, rbf, Pe, P);
    MatX feat(m, c + 3);
    feat.leftCols(c) = Pe.rowwise() - rest_phi.transpose();
    feat.rightCols(3) = S.array() - 1.0;
    const SpMat B = nominal.force_map(x);
    VecX y = Eigen::Map<const VecX>(FC.data() + j * n * 3, 3 * n);
    if (current) y += current->forces(x, v) - nominal.forces(x, v);
    if (basis) {
      const MatX Bt = SpMat(B.transpose()) * phi;  // (3m x r)
      for (int k = 0; k < 3; ++k) {
        MatX Bk(m, rows);
        for (int e = 0; e < m; ++e) Bk.row(e) = Bt.row(3 * e + k);
        D.middleCols(k * (c + 3), c + 3).noalias() = Bk.transpose() * feat;
      }
      if (damping) {
        const SpMat G = nominal.stiffness_damping_map(x, v);
        const MatX Gt = SpMat(G.transpose()) * phi;  // (m x r)
        MatX Q(m, c + 1);
        Q.leftCols(c) = P;
        Q.col(c).setOnes();
        D.rightCols(c + 1).noalias() = Gt.transpose() * Q;
      }
      const VecX yr = phi.transpose() * y;
      out.N.noalias() += D.transpose() * D;
      out.rhs.noalias() += D.transpose() * yr;
      out.yy += yr.squaredNorm();
    } else {
      MatX Dfull(3 * n, p);
      for (int k = 0; k < 3; ++k) {
        MatX E = MatX::Zero(3 * m, c + 3);
        for (int e = 0; e < m; ++e) E.row(3 * e + k) = feat.row(e);
        Dfull.middleCols(k * (c + 3), c + 3).noalias() = B * E;
      }
      if (damping) {
        const SpMat G = nominal.stiffness_damping_map(x, v);
        MatX Q(m, c + 1);
        Q.leftCols(c) = P;
        Q.col(c).setOnes();
        Dfull.rightCols(c + 1).noalias() = G * Q;
      }
      VecX yr(rows);
      for (int i = 0; i < rows; ++i) {
        D.row(i) = Dfull.row(keep[i]);
        yr[i] = y[keep[i]];
      }
      out.N.noalias() += D.transpose() * D;
      out.rhs.noalias() += D.transpose() * yr;
      out.yy += yr.squaredNorm();
    }
    ++out.frames;
  }
  return out;
}

}  // namespace matlearn::learning
