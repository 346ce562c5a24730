#pragma once
/// Probabilistic point-cloud correspondences and the cloud observation residual (method.md
/// section 7, the paper's eq. 9).
///
/// Surface points s_k (mesh vertices, or points embedded barycentrically in surface triangles)
/// and cloud points c_n are linked by candidate pairs (k, n) found by a spatial search (a KD
/// tree in Python, radius a few sigma). Each pair carries the Gaussian weight
///   p_kn = exp(-|c_n - s_k|^2 / (2 sigma^2)),  set to 0 when below `threshold`
/// (the normalising constant (2 pi sigma^2)^(-3/2) is left out: it only rescales lambda).
/// The residual of surface point k is
///   r_k = sum_n p_kn (c_n - s_k) / sigma^2,
/// which is the gradient in s_k of the cloud's Gaussian kernel density: it vanishes where s_k
/// sits on the (noise-averaged) scanned surface. Rows of surface points without a pair are 0.
///
/// Several frames are handled in one call by stacking: S holds the surface points of all frames,
/// C all clouds, and pairs index into the stacked arrays.
#include "common/types.hpp"

namespace matlearn::observation {

/// Gaussian weights of the pairs (#P): p = exp(-|C[n] - S[k]|^2 / (2 sigma^2)), 0 below threshold.
/// S (#K x 3), C (#N x 3), pair_point/pair_cloud (#P) indices into S and C.
VecX cloud_weights(const MatX3& S, const MatX3& C, const VecXi& pair_point, const VecXi& pair_cloud,
                   double sigma, double threshold);

/// Derivative of each pair's weight with respect to its surface point, (#P x 3):
/// dp/ds_k = p (c_n - s_k) / sigma^2 (0 for truncated pairs).
MatX3 cloud_weight_gradients(const MatX3& S, const MatX3& C, const VecXi& pair_point,
                             const VecXi& pair_cloud, double sigma, double threshold);

/// Residual r_k (#K x 3) of every surface point (see file comment).
MatX3 cloud_residual(const MatX3& S, const MatX3& C, const VecXi& pair_point, const VecXi& pair_cloud,
                     double sigma, double threshold);

/// dr_k / ds_k for every surface point as row-major 3x3 blocks (#K x 9). r_k depends only on
/// s_k, so the Jacobian with respect to all surface points is block diagonal.
/// full = false: weights held fixed (EM / Gauss-Newton on a fixed correspondence),
///   -W_k / sigma^2 I with W_k = sum_n p_kn;
/// full = true: exact derivative including the weights,
///   sum_n p_kn ((c_n - s_k)(c_n - s_k)^T / sigma^2 - I) / sigma^2.
Eigen::Matrix<double, Eigen::Dynamic, 9, Eigen::RowMajor> cloud_residual_blocks(
    const MatX3& S, const MatX3& C, const VecXi& pair_point, const VecXi& pair_cloud, double sigma,
    double threshold, bool full);

/// Correspondence targets: the p-weighted mean of the cloud points of each surface point
/// (#K x 3, NaN where W_k = 0) and the total weights W_k (#K). r_k = W_k (mean_k - s_k) / sigma^2.
void cloud_targets(const MatX3& S, const MatX3& C, const VecXi& pair_point, const VecXi& pair_cloud,
                   double sigma, double threshold, MatX3& mean, VecX& total_weight);

}  // namespace matlearn::observation
