#include "fem/svd.hpp"

#include <Eigen/SVD>

namespace matlearn::fem {

void rotation_variant_svd(const Mat3& F, Mat3& U, Vec3& s, Mat3& V) {
  Eigen::JacobiSVD<Mat3> svd(F, Eigen::ComputeFullU | Eigen::ComputeFullV);
  U = svd.matrixU();
  V = svd.matrixV();
  s = svd.singularValues();
  if (U.determinant() < 0) {
    U.col(2) *= -1;
    s[2] *= -1;
  }
  if (V.determinant() < 0) {
    V.col(2) *= -1;
    s[2] *= -1;
  }
}

}  // namespace matlearn::fem
