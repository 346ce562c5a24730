#include "learning/fit_normal_equations.hpp"

#include <algorithm>
#include <cmath>

#include "fem/svd.hpp"

namespace matlearn::learning {

namespace {

/// Elastic kernels g_k(s) (extended beyond the box, RbfCorrection) and damping kernels
/// phi_k(clamp(s)) for the rows of S (m x 3) -> (m x c) each; with Gd, the elastic kernels'
/// gradients dg_k/ds_d too (Gd[d], m x c).
void kernels(const MatX3& S, const RbfFeatures& rbf, MatX& G, MatX& Pa, MatX* Gd = nullptr) {
  const int m = S.rows(), c = rbf.centers.rows();
  const bool box = rbf.lower.size() == 3;
  G.resize(m, c);
  Pa.resize(m, c);
  if (Gd)
    for (int d = 0; d < 3; ++d) Gd[d].resize(m, c);
  for (int e = 0; e < m; ++e) {
    const Vec3 s = S.row(e).transpose();
    const Vec3 sc = box ? Vec3(s.cwiseMax(rbf.lower).cwiseMin(rbf.upper)) : s;
    for (int k = 0; k < c; ++k) {
      Vec3 g;
      G(e, k) = correction::extended_kernel(s, sc, rbf.centers.row(k).transpose(), rbf.epsilon,
                                            Gd ? &g : nullptr, &Pa(e, k));
      if (Gd)
        for (int d = 0; d < 3; ++d) Gd[d](e, k) = g[d];
    }
  }
}

MatX3 frame_rows(const MatX3& A, int j, int n) { return A.middleRows(long(j) * n, n); }

/// Tangent damping (correction.hpp): the elastic features' damping forces. A feature f(s) in
/// principal component k adds the stress f e_k; its unprojected principal tangent is linear in
/// (f, grad f), so its damping stress rate at the rate hat(Fdot) is f Y_0k + sum_j df/ds_j Y_jk
/// with Y_0k = T(Ph = e_k, dPh = 0) hat(Fdot), Y_jk = T(Ph = 0, dPh = sym(e_k e_j^T)) hat(Fdot)
/// (dPh symmetrised as the Model's projected damping tangent does), each passed through the
/// derivative of the PSD projection at the element's total tangent `proj[e]` (the Model damps
/// with the projected total). R[k] (3#V x 4#T) holds, per element e, the vertex forces of
/// those 4 responses (columns 4e .. 4e+3); Fe (4#T x (c+3)) the matching alpha_K,e (f, grad f)
/// of every feature, so R[k] Fe is the features' damping force.
void tangent_damping_responses(const fem::Model& model, const fem::ElementState& st,
                               const std::vector<fem::ProjectedTangentDerivative>& proj, SpMat R[3]) {
  const auto& mesh = model.mesh();
  const int n = mesh.num_vertices(), m = mesh.num_tets();
  const auto& T = mesh.tets();
  std::vector<Eigen::Triplet<double>> trip[3];
  for (int k = 0; k < 3; ++k) trip[k].reserve(size_t(m) * 48);
  for (int e = 0; e < m; ++e) {
    const Mat3& U = st.U[e];
    const Mat3& V = st.V[e];
    const Mat3 Xhat = U.transpose() * st.Fdot[e] * V;
    const Mat3& Bm = mesh.Bm()[e];
    const double W = mesh.volumes()[e];
    for (int k = 0; k < 3; ++k)
      for (int q = 0; q < 4; ++q) {
        Vec3 P = Vec3::Zero();
        Mat3 dP = Mat3::Zero();
        if (q == 0) {
          P[k] = 1.0;
        } else {
          dP(k, q - 1) += 0.5;
          dP(q - 1, k) += 0.5;
        }
        const Vec12 f = fem::element_forces(U * proj[e](P, dP).apply(Xhat) * V.transpose(), Bm, W);
        for (int a = 0; a < 12; ++a) trip[k].emplace_back(3 * T(e, a / 3) + a % 3, 4 * e + q, f[a]);
      }
  }
  for (int k = 0; k < 3; ++k) {
    R[k].resize(3 * n, 4 * m);
    R[k].setFromTriplets(trip[k].begin(), trip[k].end());
  }
}

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
                                     const RbfFeatures& rbf, bool damping, bool tangent_damping) {
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
  if (tangent_damping && current &&
      !(current->correction() && current->correction()->tangent_damping()))
    throw InvalidInput("fit_normal_equations: tangent_damping is on but the current model's "
                       "correction does not have tangent damping");
  if (!tangent_damping && current && current->correction() &&
      current->correction()->tangent_damping())
    throw InvalidInput("fit_normal_equations: the current model's correction has tangent "
                       "damping; pass tangent_damping=True");
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
    MatX Pe, P, Gd[3];
    kernels(S, rbf, Pe, P, tangent_damping ? Gd : nullptr);
    MatX feat(m, c + 3);
    feat.leftCols(c) = Pe.rowwise() - rest_phi.transpose();
    feat.rightCols(3) = S.array() - 1.0;
    const SpMat B = nominal.force_map(x);
    VecX y = Eigen::Map<const VecX>(FC.data() + j * n * 3, 3 * n);
    // Tangent damping: the damping force (alpha_K + dalpha) K(nominal + correction) v is
    // bilinear in (elastic, damping) weights; linearised at the current model (Gauss-Newton):
    // elastic features damp with the current effective alpha_K, the damping columns act on the
    // current corrected tangent, and y loses the cross term dalpha_cur K_corr,cur v counted twice.
    // st_nom / st: the nominal model's and the damping model's state (forces and K v), each
    // evaluated once per frame; the damping model is the nominal one unless tangent damping
    // acts on the current corrected tangent.
    const bool corrected_damping = tangent_damping && current;
    const fem::Model& damp_model = corrected_damping ? *current : nominal;
    fem::ElementState st_nom, st_cur;
    if (current || damping || tangent_damping)
      nominal.evaluate(x, v, fem::kForce | fem::kDampingKv, true, st_nom);
    if (corrected_damping) current->evaluate(x, v, fem::kForce | fem::kDampingKv, true, st_cur);
    const fem::ElementState& st = corrected_damping ? st_cur : st_nom;
    if (current)
      y += VecX((corrected_damping ? current->gather_forces(st_cur) : current->forces(x, v)) -
                nominal.gather_forces(st_nom));
    SpMat R[3];
    MatX Fe;
    if (tangent_damping) {
      // the current correction's own stress and Jacobian (none at the first fit)
      correction::CorrectionOutput co;
      if (current) current->correction()->evaluate(st.Fh, st.Fhdot, co);
      std::vector<fem::ProjectedTangentDerivative> proj;
      proj.reserve(m);
      for (int e = 0; e < m; ++e) {
        const Vec3 sv = st.Fh.row(e).transpose();
        Mat3 dPtot = fem::principal_stress_derivative(nominal.material(), sv, nominal.mu()[e],
                                                      nominal.lambda()[e], nominal.edits());
        if (current) dPtot += co.d_dFh[e];
        proj.emplace_back(sv, Vec3(st.Ph.row(e).transpose()), dPtot);
      }
      tangent_damping_responses(damp_model, st, proj, R);
      Fe.resize(4 * m, c + 3);
      for (int e = 0; e < m; ++e) {
        const double aK = st.alpha_K[e];
        Fe.row(4 * e) = aK * feat.row(e);  // the features' values
        for (int d = 0; d < 3; ++d) {  // and gradients
          Fe.row(4 * e + 1 + d).head(c) = aK * Gd[d].row(e);
          Fe.row(4 * e + 1 + d).tail(3) = aK * Vec3::Unit(d).transpose();
        }
      }
      if (current) {
        // y -= k, k = model(theta_cur) - design(theta_cur) (damping parts; K v as in Kv):
        //   k_e = -aK0 (K_tot,cur - K_nom) v + aK_cur K_lin,cur v,
        // K_tot,cur the projected corrected tangent, K_lin,cur the projection's derivative
        // applied to the current correction (the design's), so the linearisation is exact at
        // the current model also where the PSD projection is active.
        const auto& mesh = nominal.mesh();
        const auto& T = mesh.tets();
        for (int e = 0; e < m; ++e) {
          const Mat3& U = st.U[e];
          const Mat3& Vm = st.V[e];
          const Mat3 J = 0.5 * (co.d_dFh[e] + co.d_dFh[e].transpose());
          const Mat3 Y = proj[e](co.dPh.row(e).transpose(), J).apply(U.transpose() * st.Fdot[e] * Vm);
          const Vec12 klin = -fem::element_forces(U * Y * Vm.transpose(), mesh.Bm()[e], mesh.volumes()[e]);
          const Vec12 k =
              -st_nom.alpha_K[e] * (st.Kv[e] - st_nom.Kv[e]) + st.alpha_K[e] * klin;
          for (int a = 0; a < 4; ++a) y.segment<3>(3 * T(e, a)) -= k.segment<3>(3 * a);
        }
      }
    }
    // the damping columns: force per unit alpha_K change, on the damping model's tangent
    const SpMat G = damping ? damp_model.stiffness_damping_map(st) : SpMat();
    if (basis) {
      const MatX Bt = SpMat(B.transpose()) * phi;  // (3m x r)
      for (int k = 0; k < 3; ++k) {
        MatX Bk(m, rows);
        for (int e = 0; e < m; ++e) Bk.row(e) = Bt.row(3 * e + k);
        D.middleCols(k * (c + 3), c + 3).noalias() = Bk.transpose() * feat;
        if (tangent_damping) {
          const MatX Rt = SpMat(R[k].transpose()) * phi;  // (4m x r)
          D.middleCols(k * (c + 3), c + 3).noalias() += Rt.transpose() * Fe;
        }
      }
      if (damping) {
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
        if (tangent_damping) Dfull.middleCols(k * (c + 3), c + 3).noalias() += R[k] * Fe;
      }
      if (damping) {
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
