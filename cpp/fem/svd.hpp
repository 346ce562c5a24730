#pragma once
#include "common/types.hpp"

namespace matlearn::fem {

/// Rotation-variant SVD F = U diag(s) V^T with U, V proper rotations, s sorted descending in
/// magnitude; an inverted F gets a negative smallest singular value. Computed by Jacobi
/// rotations on F^T F and a Givens QR of F V (~1.7x faster than Eigen's JacobiSVD), falling back
/// to JacobiSVD whenever the result is not diagonal to round-off (clustered tiny values).
void rotation_variant_svd(const Mat3& F, Mat3& U, Vec3& s, Mat3& V);

/// Number of matrices `rotation_variant_svd_lanes` factorises together.
constexpr int kSvdLanes = 8;

/// `rotation_variant_svd` of `count` (1..kSvdLanes, not checked: called per element block in
/// parallel loops) matrices at once, bitwise equal to it matrix
/// by matrix: the same operations, with the Jacobi rotations and the Givens QR of all lanes
/// carried in packed registers (a lane that has converged is masked, not rotated; unused lanes
/// are padded internally). The scalar path is latency-bound (each rotation is a chain of two
/// square roots and two divisions); in the library the lanes save ~15 % of the SVD time (forces
/// 2.52 -> 2.35 ms on 6k tets; a standalone benchmark showed ~2x). Lanes whose result fails the
/// scalar path's acceptance check are redone by it (and so reach its robust fallback).
void rotation_variant_svd_lanes(const Mat3* F, Mat3* U, Vec3* s, Mat3* V, int count = kSvdLanes);

}  // namespace matlearn::fem
