#pragma once
/// Normal equations of the stress-correction fit (method.md section 6), accumulated over all
/// frames of a recording in one call. See python/matlearn/learning/fit.py for the model:
///
///   unknowns theta = [w_0 A_0 | w_1 A_1 | w_2 A_2 | wa a0]   (per principal stress component
///   k: c RBF weights then the row k of the linear part; then the damping weights and bias)
///   features per element: g_k(Fh) - g_k(1) and Fh - 1 (elastic; g_k the box-extended kernel
///                         of RbfCorrection), phi_k(clamp(Fh)) and 1 (damping, times the
///                         stiffness-damping map)
///   rows: P^T (B_j dPh + G_j dalpha) = P^T (fc_j + f_corr,current(x_j, v_j))
///
/// with P the basis (3#V x r) or, when it has no columns, the selection of the free DOFs.
#include <memory>

#include "common/types.hpp"
#include "fem/model.hpp"

namespace matlearn::learning {

/// RBF feature layout shared with RbfCorrection: centres (c x 3), kernel width, and the box
/// [lower, upper] beyond which the kernels are extended (RbfCorrection; empty: no box).
struct RbfFeatures {
  MatX3 centers;
  double epsilon = 0.05;
  VecX lower, upper;
};

struct NormalEquations {
  MatX N;       ///< (p x p) D^T D summed over frames
  VecX rhs;     ///< (p) D^T y
  double yy = 0;  ///< sum y^T y
  int frames = 0;
};

/// Accumulate the normal equations over frames j of X, V, FC (each frames*#V x 3, stacked).
/// current may be null (no current correction). phi: (3#V x r) or empty (then `free_dofs`,
/// length 3#V, selects the rows kept). damping: include the alpha_K unknowns. tangent_damping:
/// the fitted correction has tangent damping (correction.hpp; then so must `current`'s): the
/// elastic features also carry their share of the stiffness-proportional damping force,
/// linearised at the current model (see the .cpp).
NormalEquations fit_normal_equations(const fem::Model& nominal, const fem::Model* current,
                                     const MatX3& X, const MatX3& V, const MatX3& FC,
                                     const MatX& phi, const Eigen::Matrix<bool, Eigen::Dynamic, 1>& free_dofs,
                                     const RbfFeatures& rbf, bool damping,
                                     bool tangent_damping = false);

/// Principal stretches (frames*#T x 3) of every frame of X (frames*#V x 3), frame-major.
MatX3 principal_stretches(const fem::Model& model, const MatX3& X);

}  // namespace matlearn::learning
