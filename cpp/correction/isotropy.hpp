#pragma once
#include "common/types.hpp"

namespace matlearn::correction {

/// Isotropy of a principal stress correction (shared by RbfCorrection and MlpCorrection): a
/// stress correction must be an isotropic function of F, dPh_i = dPh_j wherever s_i = s_j, or
/// U diag(Ph) V^T depends on the arbitrary principal frame there and the force jumps (Newton then
/// cycles between the two sides). Learned corrections are not exactly isotropic.
///
/// Makes p (principal stress correction at stretches s, with Jacobians J = dp/ds and Jdot =
/// dp/dsdot when given) consistent at coincident stretches: p' = (I + L)^{-1} p with the graph
/// Laplacian L = sum over pairs ij of k(|s_i - s_j|) (e_i - e_j)(e_i - e_j)^T,
/// k(d) = ((w/d)^2 - 1)^2 for d < w, else 0 (capped at 1e8). The mean of p is kept; p'_i = p'_j
/// when s_i = s_j (all three equal when all coincide); p is untouched (bitwise) when every gap is
/// >= w. J and Jdot become the exact derivatives of p'. Returns whether p changed.
bool isotropic_blend(const Vec3& s, double w, Vec3& p, Mat3* J, Mat3* Jdot);

}  // namespace matlearn::correction
