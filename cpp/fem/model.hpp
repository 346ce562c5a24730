#pragma once
#include <memory>
#include <vector>

#include "common/types.hpp"
#include "correction/correction.hpp"
#include "fem/material.hpp"
#include "fem/sparse_assembler.hpp"
#include "fem/tet_mesh.hpp"

namespace matlearn::fem {

/// Rayleigh damping D = alpha_M M + alpha_K K, with each alpha optionally a polynomial of the
/// element's first (largest) principal stretch s1: alpha(s1) = alpha + sum_k c_k (s1 - 1)^k,
/// k = 1..len(c), clamped at 0 so damping stays passive.
struct DampingParams {
  double alpha_mass = 0.0;       ///< 1/s
  double alpha_stiffness = 0.0;  ///< s
  std::vector<double> mass_poly;
  std::vector<double> stiffness_poly;
};

/// Everything evaluated per element at one state (x, v).
struct ElementState {
  std::vector<Mat3> U, V;
  std::vector<Mat3> Fdot;  ///< velocity gradients
  MatX3 Fh, Fhdot;     ///< (#T x 3) principal stretches and stretch rates
  MatX3 Ph;            ///< (#T x 3) total principal stress (nominal + correction), Pa
  MatX3 dPh_corr;      ///< (#T x 3) correction part of Ph
  VecX alpha_K;        ///< (#T) effective stiffness-damping coefficient (s)
  VecX alpha_M;        ///< (#T) effective mass-damping coefficient (1/s)
  std::vector<Eigen::Matrix<double, 12, 1>> f;  ///< element internal force (elastic + damping)
  std::vector<Mat12> K;  ///< element stiffness -df/dx (elastic, no damping term derivative)
  std::vector<Mat12> D;  ///< element damping -df/dv (alpha_K K_damp + correction rate part)
  /// K_e v_e with the tangent alpha_K multiplies (K_nominal; the corrected tangent when the
  /// correction has tangent damping), for damping fits
  std::vector<Eigen::Matrix<double, 12, 1>> Kv;
};

enum EvalFlags { kForce = 1, kStiffness = 2, kDamping = 4, kDampingKv = 8 };

/// Vertex forces -W P Bm^T of a tet (12), vertex 0 first, for the world stress P.
Vec12 element_forces(const Mat3& P, const Mat3& Bm, double W);

/// A deformable body: mesh + per-element material + damping + optional learned correction.
class Model {
 public:
  Model(std::shared_ptr<const TetMesh> mesh, MaterialModel material, VecX mu, VecX lambda,
        VecX density, std::vector<StretchEdit> edits, DampingParams damping);

  const TetMesh& mesh() const { return *mesh_; }
  std::shared_ptr<const TetMesh> mesh_ptr() const { return mesh_; }
  MaterialModel material() const { return material_; }
  const VecX& mu() const { return mu_; }
  const VecX& lambda() const { return lambda_; }
  const VecX& density() const { return density_; }
  const DampingParams& damping() const { return damping_; }
  const std::vector<StretchEdit>& edits() const { return edits_; }
  /// Lumped vertex masses (kg), (#V).
  const VecX& vertex_mass() const { return mass_; }
  /// Mass per DOF (3#V), for diagonal mass matrices.
  const VecX& dof_mass() const { return dof_mass_; }

  void set_correction(std::shared_ptr<const correction::Correction> c) { correction_ = std::move(c); }
  std::shared_ptr<const correction::Correction> correction() const { return correction_; }

  /// Evaluate per-element quantities at (x, v), each (#V x 3). flags: EvalFlags.
  /// project_psd clamps each element tangent to PSD (what implicit solves need).
  void evaluate(const MatX3& x, const MatX3& v, int flags, bool project_psd, ElementState& st) const;

  /// Global internal force (elastic + damping, no gravity), (3#V).
  VecX forces(const MatX3& x, const MatX3& v) const;
  /// Scatter element forces into a global vector.
  VecX gather_forces(const ElementState& st) const;
  /// Assembled tangent stiffness K = -df/dx (3#V x 3#V) at (x, v).
  SpMat stiffness_matrix(const MatX3& x, const MatX3& v, bool project_psd) const;
  /// Assembled damping matrix D = -df/dv (3#V x 3#V) at (x, v).
  SpMat damping_matrix(const MatX3& x, const MatX3& v) const;
  /// Force map B (3#V x 3#T): f_elastic = B ph for principal stresses ph, at positions x.
  SpMat force_map(const MatX3& x) const;
  /// Stiffness-damping map (3#V x #T): column e = -K_e v_e (force per unit alpha_K), K the
  /// projected nominal tangent, or the corrected one when the correction has tangent damping.
  SpMat stiffness_damping_map(const MatX3& x, const MatX3& v) const;
  /// The same map from a state evaluated with kDampingKv.
  SpMat stiffness_damping_map(const ElementState& st) const;
  /// Mass-damping map (3#V x #T): column e = -M_e v_e (force per unit alpha_M).
  SpMat mass_damping_map(const MatX3& v) const;
  /// Reduced tangents of the model *without* its correction at (x, v): Kr = Phi^T K Phi with the
  /// unprojected elastic tangent K = -df/dx and Dr = Phi^T D Phi with the Rayleigh damping
  /// D = alpha_K K_psd + alpha_M M_lumped (r x r each), for phi (3#V x r). The same matrices as
  /// assembling evaluate(kStiffness | kDamping, project_psd = false) element by element and
  /// projecting, at a fraction of the cost: each tet's principal-frame columns A (Phi rows of
  /// its vertices relative to vertex 0) give W (A Q)^T H (A Q) directly (no 12 x 12 blocks).
  void reduced_tangents(const MatX3& x, const MatX& phi, MatX& Kr, MatX& Dr) const;
  /// Shape derivative (9 x 12): vec(dF) = G dx_e for tet e (vec column-major).
  Eigen::Matrix<double, 9, 12> shape_gradient(int e) const;

  void check_state(const MatX3& x, const char* name) const;

 private:
  double damping_alpha(double base, const std::vector<double>& poly, double s1) const;
  /// Scatter pattern of the full 3#V x 3#V operators, built on first use and shared by copies.
  const SparseAssembler& full_assembler() const;
  mutable std::shared_ptr<const SparseAssembler> full_assembler_;

  std::shared_ptr<const TetMesh> mesh_;
  MaterialModel material_;
  VecX mu_, lambda_, density_;
  std::vector<StretchEdit> edits_;
  DampingParams damping_;
  VecX mass_, dof_mass_;
  std::shared_ptr<const correction::Correction> correction_;
};

}  // namespace matlearn::fem
