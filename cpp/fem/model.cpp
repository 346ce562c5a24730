#include "fem/model.hpp"

#include <algorithm>
#include <atomic>

#include "fem/svd.hpp"

namespace matlearn::fem {

using Mat9 = Eigen::Matrix<double, 9, 9>;
using Mat9x12 = Eigen::Matrix<double, 9, 12>;

Model::Model(std::shared_ptr<const TetMesh> mesh, MaterialModel material, VecX mu, VecX lambda,
             VecX density, std::vector<StretchEdit> edits, DampingParams damping)
    : mesh_(std::move(mesh)), material_(material), mu_(std::move(mu)), lambda_(std::move(lambda)),
      density_(std::move(density)), edits_(std::move(edits)), damping_(std::move(damping)) {
  const int m = mesh_->num_tets();
  if (mu_.size() != m || lambda_.size() != m || density_.size() != m)
    throw InvalidInput("Model: mu, lambda and density need one value per tet (" +
                       std::to_string(m) + ")");
  if (!mu_.allFinite() || !lambda_.allFinite() || !density_.allFinite())
    throw InvalidInput("Model: material parameters contain NaN or Inf");
  if ((mu_.array() <= 0).any()) throw InvalidInput("Model: shear modulus must be > 0");
  if ((lambda_.array() < 0).any())
    throw InvalidInput("Model: Lame lambda must be >= 0 (Poisson ratio in [0, 0.5))");
  if ((density_.array() <= 0).any()) throw InvalidInput("Model: density must be > 0");
  if (damping_.alpha_mass < 0 || damping_.alpha_stiffness < 0)
    throw InvalidInput("Model: Rayleigh coefficients must be >= 0");
  for (const auto& ed : edits_) {
    if (!(ed.half_width > 0)) throw InvalidInput("Model: stretch edit half_width must be > 0");
    if (std::abs(ed.center - 1.0) < ed.half_width)
      throw InvalidInput("Model: a stretch edit must not cover the rest stretch 1 "
                         "(|center - 1| >= half_width), or the rest state would be stressed");
  }
  mass_ = mesh_->lumped_mass(density_);
  dof_mass_.resize(3 * mass_.size());
  for (int i = 0; i < mass_.size(); ++i) dof_mass_.segment<3>(3 * i).setConstant(mass_[i]);
}

void Model::check_state(const MatX3& x, const char* name) const {
  if (x.rows() != mesh_->num_vertices())
    throw InvalidInput(std::string(name) + ": expected shape (" +
                       std::to_string(mesh_->num_vertices()) + ", 3), got (" +
                       std::to_string(x.rows()) + ", 3)");
  if (!x.allFinite()) throw InvalidInput(std::string(name) + " contains NaN or Inf");
}

double Model::damping_alpha(double base, const std::vector<double>& poly, double s1) const {
  double a = base, p = 1.0;
  for (double c : poly) {
    p *= (s1 - 1.0);
    a += c * p;
  }
  return std::max(a, 0.0);
}

Mat9x12 Model::shape_gradient(int e) const {
  const Mat3& Bm = mesh_->Bm()[e];
  Mat9x12 G = Mat9x12::Zero();
  // F_ij = sum_k Ds_ik Bm_kj, Ds_:k = x_{k+1} - x_0.
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      double s = 0;
      for (int a = 1; a < 4; ++a) {
        G(i + 3 * j, 3 * a + i) = Bm(a - 1, j);
        s += Bm(a - 1, j);
      }
      G(i + 3 * j, i) = -s;
    }
  return G;
}

namespace {

using Vec9 = Eigen::Matrix<double, 9, 1>;

// Below this many elements a parallel region costs more than it saves (thread wake-up, and
// on a loaded machine the wait for a descheduled peer thread: 4x slower steps at 1k tets).
// Element loops use dynamic chunks so a thread that is descheduled on a busy machine does not
// hold back a fixed half of the work.
constexpr int kParallelMinTets = 4096;

/// Principal-frame shape columns of a tet: column 3a + k (vertex a+1 of the tet, coordinate k)
/// is vec(U^T dF V) for a unit displacement of that DOF, i.e. the outer product
/// U.row(k)^T (Bm V).row(a). Vertex 0 is minus the sum of the others (translation invariance).
Mat9 principal_shape_columns(const Mat3& U, const Mat3& BmV) {
  Mat9 A;
  for (int a = 0; a < 3; ++a)
    for (int k = 0; k < 3; ++k) {
      Eigen::Map<Mat3> X(A.col(3 * a + k).data());
      X.noalias() = U.row(k).transpose() * BmV.row(a);
    }
  return A;
}

/// W A^T Hh A for the 9 DOFs of vertices 1..3, expanded to the 12 x 12 element matrix by
/// translation invariance. Equal to W G^T (dP/dF) G with dP/dF = (V kron U) Hh (V kron U)^T,
/// at a fraction of the cost (Hh has 21 non-zeros).
void element_matrix(const Mat9& A, const PrincipalTangent& T, double W, Mat12& out) {
  Mat9 HA;
  for (int c = 0; c < 9; ++c) {
    const Mat3 Y = T.apply(Eigen::Map<const Mat3>(A.col(c).data()));
    HA.col(c) = Eigen::Map<const Vec9>(Y.data());
  }
  Mat9 K9;
  K9.noalias() = W * A.transpose().lazyProduct(HA);
  out.bottomRightCorner<9, 9>() = K9;
  for (int c = 0; c < 9; ++c) {
    out(0, 3 + c) = -(K9(0, c) + K9(3, c) + K9(6, c));
    out(1, 3 + c) = -(K9(1, c) + K9(4, c) + K9(7, c));
    out(2, 3 + c) = -(K9(2, c) + K9(5, c) + K9(8, c));
  }
  for (int r = 0; r < 12; ++r)
    for (int l = 0; l < 3; ++l) out(r, l) = -(out(r, 3 + l) + out(r, 6 + l) + out(r, 9 + l));
}

}  // namespace

/// Vertex forces -W P Bm^T of a tet (12), vertex 0 first, for the world stress P.
Vec12 element_forces(const Mat3& P, const Mat3& Bm, double W) {
  const Mat3 H = -W * P * Bm.transpose();  // column a: force on vertex a+1
  Vec12 f;
  f.segment<3>(3) = H.col(0);
  f.segment<3>(6) = H.col(1);
  f.segment<3>(9) = H.col(2);
  f.segment<3>(0) = -(H.col(0) + H.col(1) + H.col(2));
  return f;
}

void Model::evaluate(const MatX3& x, const MatX3& v, int flags, bool project_psd,
                     ElementState& st) const {
  check_state(x, "x");
  check_state(v, "v");
  const int m = mesh_->num_tets();
  const auto& T = mesh_->tets();
  st.U.resize(m);
  st.V.resize(m);
  st.Fh.resize(m, 3);
  st.Fhdot.resize(m, 3);
  st.Fdot.resize(m);
  // Element SVDs kSvdLanes at a time (bitwise the scalar SVD), straight into st.U / st.V.
  const int blocks = (m + kSvdLanes - 1) / kSvdLanes;
#pragma omp parallel for schedule(dynamic, 32) if (m >= kParallelMinTets)
  for (int b = 0; b < blocks; ++b) {
    const int e0 = b * kSvdLanes, count = std::min(kSvdLanes, m - e0);
    Mat3 F[kSvdLanes];
    Vec3 s[kSvdLanes];
    for (int l = 0; l < count; ++l) F[l] = mesh_->deformation_gradient(x, e0 + l);
    rotation_variant_svd_lanes(F, &st.U[e0], s, &st.V[e0], count);
    for (int l = 0; l < count; ++l) {
      const int e = e0 + l;
      st.Fdot[e] = mesh_->deformation_gradient(v, e);
      st.Fh.row(e) = s[l].transpose();
      st.Fhdot.row(e) = (st.U[e].transpose() * st.Fdot[e] * st.V[e]).diagonal().transpose();
    }
  }
  correction::CorrectionOutput corr;
  const bool has_corr = correction_ != nullptr;
  // Tangent damping: alpha_K acts on the corrected tangent, so forces need its Jacobian too.
  const bool corr_damp = has_corr && correction_->tangent_damping();
  if (has_corr) {
    // Force-only evaluations (residuals, chord steps) need no correction Jacobians.
    if ((flags & (kStiffness | kDamping)) || (corr_damp && (flags & (kForce | kDampingKv))))
      correction_->evaluate(st.Fh, st.Fhdot, corr);
    else
      correction_->evaluate_values(st.Fh, st.Fhdot, corr);
    if (!corr.dPh.allFinite()) throw NumericalError("correction returned NaN or Inf stress");
  }
  st.Ph.resize(m, 3);
  st.dPh_corr = has_corr ? corr.dPh : MatX3::Zero(m, 3);
  st.alpha_K.resize(m);
  st.alpha_M.resize(m);
  if (flags & kForce) st.f.resize(m);
  if (flags & kStiffness) st.K.resize(m);
  if (flags & kDamping) st.D.resize(m);
  if (flags & kDampingKv) st.Kv.resize(m);
  const bool need_nominal = flags & (kForce | kDamping | kDampingKv);
#pragma omp parallel for schedule(dynamic, 256) if (m >= kParallelMinTets)
  for (int e = 0; e < m; ++e) {
    const Vec3 s = st.Fh.row(e).transpose();
    const double W = mesh_->volumes()[e];
    const Mat3& Bm = mesh_->Bm()[e];
    const Vec3 Pn = principal_stress(material_, s, mu_[e], lambda_[e], edits_);
    const Mat3 dPn = principal_stress_derivative(material_, s, mu_[e], lambda_[e], edits_);
    Vec3 Ph = Pn;
    double aK = damping_alpha(damping_.alpha_stiffness, damping_.stiffness_poly, s[0]);
    if (has_corr) {
      Ph += corr.dPh.row(e).transpose();
      aK = std::max(aK + corr.dalpha[e], 0.0);
    }
    st.Ph.row(e) = Ph.transpose();
    st.alpha_K[e] = aK;
    st.alpha_M[e] = damping_alpha(damping_.alpha_mass, damping_.mass_poly, s[0]);
    const Mat3& U = st.U[e];
    const Mat3& V = st.V[e];
    const double cm = st.alpha_M[e] * density_[e] * W / 4.0;  // lumped mass damping per corner
    // Nominal tangent (always projected: Rayleigh damping built on it must stay passive); the
    // damping tangent is the nominal one, or with tangent damping the corrected one (projected).
    PrincipalTangent Tnom, Tdamp;
    Mat3 Pd_hat = Mat3::Zero();  // damping stress per unit alpha_K, principal frame
    if (need_nominal || (project_psd && !has_corr)) {
      Tnom = principal_tangent(s, Pn, dPn, true);
      Tdamp = corr_damp ? principal_tangent(s, Ph, dPn + corr.d_dFh[e], true) : Tnom;
      Pd_hat = Tdamp.apply(U.transpose() * st.Fdot[e] * V);
    }
    if (flags & kForce) {
      Mat3 Phat = aK * Pd_hat;
      Phat.diagonal() += Ph;
      Vec12 f = element_forces(U * Phat * V.transpose(), Bm, W);
      for (int a = 0; a < 4; ++a) f.segment<3>(3 * a) -= cm * v.row(T(e, a)).transpose();
      st.f[e] = f;
    }
    if (flags & kDampingKv) st.Kv[e] = -element_forces(U * Pd_hat * V.transpose(), Bm, W);
    if (!(flags & (kStiffness | kDamping))) continue;
    const Mat9 A = principal_shape_columns(U, Bm * V);
    if (flags & kStiffness) {
      if (!has_corr && project_psd)
        element_matrix(A, Tnom, W, st.K[e]);
      else if (!has_corr)
        element_matrix(A, principal_tangent(s, Pn, dPn, false), W, st.K[e]);
      else
        element_matrix(A, principal_tangent(s, Ph, dPn + corr.d_dFh[e], project_psd), W, st.K[e]);
    }
    if (flags & kDamping) {
      if ((flags & kStiffness) && !has_corr && project_psd) {
        // Same projected nominal tangent as K: reuse it instead of a second element product.
        Mat12 De = aK * st.K[e];
        De.diagonal().array() += cm;
        st.D[e] = De;
        continue;
      }
      PrincipalTangent Td = Tdamp;
      Td.diag *= aK;
      Td.a *= aK;
      Td.b *= aK;
      if (has_corr && !corr.d_dFhdot[e].isZero()) {
        // Rate-dependent correction: only its principal-diagonal block enters the tangent.
        const Mat3 J = 0.5 * (corr.d_dFhdot[e] + corr.d_dFhdot[e].transpose());
        const PrincipalTangent Tr = principal_tangent(s, Vec3::Zero(), J, project_psd);
        Td.diag += Tr.diag;
        Td.a += Tr.a;
        Td.b += Tr.b;
      }
      Mat12 De;
      element_matrix(A, Td, W, De);
      De.diagonal().array() += cm;
      st.D[e] = De;
    }
  }
}

void Model::reduced_tangents(const MatX3& x, const MatX& phi, MatX& Kr, MatX& Dr) const {
  check_state(x, "x");
  const int n = mesh_->num_vertices();
  if (phi.rows() != 3 * n) throw InvalidInput("reduced_tangents: phi must have 3#V rows");
  const int r = int(phi.cols());
  const int m = mesh_->num_tets();
  const auto& T = mesh_->tets();
  using MatXrm = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  const MatXrm P = phi;  // row access per vertex DOF
  // Stacked per-element principal-frame columns Y_e = A_e Q_e (9 rows each) and W H Y_e for
  // the elastic (first r columns) and damping (last r columns) tangents; then one product
  // Y^T [HK HD] instead of 2 #T small ones.
  MatXrm Y(size_t(9) * m, r), H(size_t(9) * m, 2 * r);
  VecX cdiag = VecX::Zero(3 * n);  // lumped mass damping per DOF
  Eigen::Matrix<double, 9, Eigen::Dynamic> Q(9, r);
  auto at = [](int i, int j) { return i + 3 * j; };  // vec (column-major) index of entry (i, j)
  const int pi[3] = {0, 0, 1}, pj[3] = {1, 2, 2};
  for (int e = 0; e < m; ++e) {
    for (int a = 1; a < 4; ++a)
      for (int k = 0; k < 3; ++k)
        Q.row(3 * (a - 1) + k) = P.row(3 * T(e, a) + k) - P.row(3 * T(e, 0) + k);
    const double W = mesh_->volumes()[e];
    Mat3 U, V;
    Vec3 s;
    rotation_variant_svd(mesh_->deformation_gradient(x, e), U, s, V);
    const double cm = damping_alpha(damping_.alpha_mass, damping_.mass_poly, s[0]) * density_[e] * W / 4.0;
    if (cm != 0.0)
      for (int a = 0; a < 4; ++a) cdiag.segment<3>(3 * T(e, a)).array() += cm;
    auto Ye = Y.middleRows(size_t(9) * e, 9);
    auto He = H.middleRows(size_t(9) * e, 9);
    if (Q.isZero(0.0)) {  // every vertex constrained (zero Phi rows)
      Ye.setZero();
      He.setZero();
      continue;
    }
    const Vec3 Pn = principal_stress(material_, s, mu_[e], lambda_[e], edits_);
    const Mat3 dPn = principal_stress_derivative(material_, s, mu_[e], lambda_[e], edits_);
    const PrincipalTangent Tk = principal_tangent(s, Pn, dPn, false);
    const PrincipalTangent Td = principal_tangent(s, Pn, dPn, true);
    const double aK = W * damping_alpha(damping_.alpha_stiffness, damping_.stiffness_poly, s[0]);
    const Mat9 A = principal_shape_columns(U, mesh_->Bm()[e] * V);
    Ye.noalias() = A.lazyProduct(Q);  // principal-frame vec(dF) per unit modal coordinate
    // H Y entry by entry (H: a 3x3 block on the diagonal entries + three 2x2 shear blocks).
    for (int c = 0; c < r; ++c) {
      const Vec3 dg(Ye(at(0, 0), c), Ye(at(1, 1), c), Ye(at(2, 2), c));
      const Vec3 hk = W * (Tk.diag * dg), hd = aK * (Td.diag * dg);
      for (int i = 0; i < 3; ++i) {
        He(at(i, i), c) = hk[i];
        He(at(i, i), r + c) = hd[i];
      }
      for (int q = 0; q < 3; ++q) {
        const double xij = Ye(at(pi[q], pj[q]), c), xji = Ye(at(pj[q], pi[q]), c);
        He(at(pi[q], pj[q]), c) = W * (Tk.a[q] * xij + Tk.b[q] * xji);
        He(at(pj[q], pi[q]), c) = W * (Tk.b[q] * xij + Tk.a[q] * xji);
        He(at(pi[q], pj[q]), r + c) = aK * (Td.a[q] * xij + Td.b[q] * xji);
        He(at(pj[q], pi[q]), r + c) = aK * (Td.b[q] * xij + Td.a[q] * xji);
      }
    }
  }
  const MatX KD = Y.transpose() * H;
  Kr = KD.leftCols(r);
  Dr = KD.rightCols(r);
  Dr.noalias() += phi.transpose() * cdiag.asDiagonal() * phi;
}

VecX Model::gather_forces(const ElementState& st) const {
  const auto& T = mesh_->tets();
  VecX f = VecX::Zero(3 * mesh_->num_vertices());
  for (int e = 0; e < mesh_->num_tets(); ++e)
    for (int a = 0; a < 4; ++a) f.segment<3>(3 * T(e, a)) += st.f[e].segment<3>(3 * a);
  return f;
}

VecX Model::forces(const MatX3& x, const MatX3& v) const {
  ElementState st;
  evaluate(x, v, kForce, true, st);
  return gather_forces(st);
}

namespace {

/// A (nrows x per*#T) CSC matrix whose column per*e + k holds the 12 DOFs of tet e (rows
/// sorted), filled directly without triplets: value(e, k, a) for local DOF a = 3 * corner + i.
template <class Value>
SpMat element_columns(const MatX4i& T, int nrows, int per, const Value& value) {
  const int m = T.rows();
  const long ncols = long(per) * m;
  std::vector<int> outer(ncols + 1), inner(12 * ncols);
  std::vector<double> vals(12 * ncols);
  for (long c = 0; c <= ncols; ++c) outer[c] = int(12 * c);
#pragma omp parallel for schedule(dynamic, 256) if (m >= kParallelMinTets)
  for (int e = 0; e < m; ++e) {
    int order[4] = {0, 1, 2, 3};
    std::sort(order, order + 4, [&](int a, int b) { return T(e, a) < T(e, b); });
    for (int k = 0; k < per; ++k) {
      const long base = 12 * (long(per) * e + k);
      for (int r = 0; r < 4; ++r)
        for (int i = 0; i < 3; ++i) {
          inner[base + 3 * r + i] = 3 * T(e, order[r]) + i;
          vals[base + 3 * r + i] = value(e, k, 3 * order[r] + i);
        }
    }
  }
  return SpMat(Eigen::Map<const SpMat>(nrows, ncols, 12 * ncols, outer.data(), inner.data(),
                                       vals.data()));
}

}  // namespace

const SparseAssembler& Model::full_assembler() const {
  auto a = std::atomic_load(&full_assembler_);
  if (!a) {  // two threads may both build it; either result is the same
    const int n = 3 * mesh_->num_vertices();
    a = std::make_shared<const SparseAssembler>(mesh_->tets(), VecXi::LinSpaced(n, 0, n - 1), n,
                                                false);
    std::atomic_store(&full_assembler_, a);
  }
  return *a;
}

SpMat Model::stiffness_matrix(const MatX3& x, const MatX3& v, bool project_psd) const {
  ElementState st;
  evaluate(x, v, kStiffness, project_psd, st);
  SpMat K;
  full_assembler().assemble(st.K, 1.0, {}, 0.0, VecX(), 0.0, K);
  return K;
}

SpMat Model::damping_matrix(const MatX3& x, const MatX3& v) const {
  ElementState st;
  evaluate(x, v, kDamping, true, st);
  SpMat D;
  full_assembler().assemble(st.D, 1.0, {}, 0.0, VecX(), 0.0, D);
  return D;
}

SpMat Model::force_map(const MatX3& x) const {
  check_state(x, "x");
  const int m = mesh_->num_tets();
  // Column 3e + k is the force of unit principal stress k: -W G^T vec(u_k v_k^T), i.e.
  // -W (Bm v_k)[a-1] u_k on corner a >= 1 and minus their sum on corner 0.
  std::vector<Mat3> U(m), C(m);
#pragma omp parallel for schedule(dynamic, 256) if (m >= kParallelMinTets)
  for (int e = 0; e < m; ++e) {
    Mat3 V;
    Vec3 s;
    rotation_variant_svd(mesh_->deformation_gradient(x, e), U[e], s, V);
    C[e] = -mesh_->volumes()[e] * mesh_->Bm()[e] * V;
  }
  return element_columns(mesh_->tets(), 3 * x.rows(), 3, [&](int e, int k, int a) {
    const int corner = a / 3, i = a % 3;
    const double w = corner == 0 ? -(C[e](0, k) + C[e](1, k) + C[e](2, k)) : C[e](corner - 1, k);
    return w * U[e](i, k);
  });
}

SpMat Model::stiffness_damping_map(const MatX3& x, const MatX3& v) const {
  ElementState st;
  evaluate(x, v, kDampingKv, true, st);
  return stiffness_damping_map(st);
}

SpMat Model::stiffness_damping_map(const ElementState& st) const {
  if (int(st.Kv.size()) != mesh_->num_tets())
    throw InvalidInput("stiffness_damping_map: the state was evaluated without kDampingKv");
  return element_columns(mesh_->tets(), 3 * mesh_->num_vertices(), 1,
                         [&](int e, int, int a) { return -st.Kv[e][a]; });
}

SpMat Model::mass_damping_map(const MatX3& v) const {
  check_state(v, "v");
  const auto& T = mesh_->tets();
  const int m = mesh_->num_tets();
  std::vector<Eigen::Triplet<double, int>> trip;
  trip.reserve(size_t(m) * 12);
  for (int e = 0; e < m; ++e) {
    const double me = density_[e] * mesh_->volumes()[e] / 4.0;
    for (int a = 0; a < 12; ++a)
      trip.emplace_back(3 * T(e, a / 3) + a % 3, e, -me * v(T(e, a / 3), a % 3));
  }
  SpMat G(3 * v.rows(), m);
  G.setFromTriplets(trip.begin(), trip.end());
  return G;
}

}  // namespace matlearn::fem
