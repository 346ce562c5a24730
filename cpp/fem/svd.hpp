#pragma once
#include "common/types.hpp"

namespace matlearn::fem {

/// Rotation-variant SVD F = U diag(s) V^T with U, V proper rotations, s sorted descending in
/// magnitude; an inverted F gets a negative smallest singular value. Computed by Jacobi
/// rotations on F^T F and a Givens QR of F V (~1.7x faster than Eigen's JacobiSVD), falling back
/// to JacobiSVD whenever the result is not diagonal to round-off (clustered tiny values).
void rotation_variant_svd(const Mat3& F, Mat3& U, Vec3& s, Mat3& V);

}  // namespace matlearn::fem
