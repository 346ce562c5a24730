#pragma once
/// DOF conventions used everywhere in matlearn:
///  * vertex positions/velocities are (#V x 3) row-major; the global DOF vector interleaves
///    xyz per vertex (dof 3*i+k is coordinate k of vertex i);
///  * double precision; sparse matrices are column-compressed with `int` indices (CHOLMOD's
///    "int" interface), which limits a model to ~700M nonzeros.
#include <Eigen/Core>
#include <Eigen/Dense>
#include <Eigen/Sparse>
#include <stdexcept>
#include <string>

namespace matlearn {

using Index = int;
using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using Mat12 = Eigen::Matrix<double, 12, 12>;
using Vec12 = Eigen::Matrix<double, 12, 1>;
using VecX = Eigen::VectorXd;
using VecXi = Eigen::VectorXi;
using MatX = Eigen::MatrixXd;
using MatX3 = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
using MatX4i = Eigen::Matrix<int, Eigen::Dynamic, 4, Eigen::RowMajor>;
using MatX3i = Eigen::Matrix<int, Eigen::Dynamic, 3, Eigen::RowMajor>;
using SpMat = Eigen::SparseMatrix<double, Eigen::ColMajor, int>;

/// View a (#V x 3) row-major matrix as the interleaved DOF vector (no copy).
inline Eigen::Map<const VecX> as_dofs(const MatX3& x) { return {x.data(), x.size()}; }
inline Eigen::Map<VecX> as_dofs(MatX3& x) { return {x.data(), x.size()}; }

/// Invalid user input (shapes, values): surfaces as Python ValueError.
struct InvalidInput : std::invalid_argument {
  using std::invalid_argument::invalid_argument;
};
/// Numerical failure (divergence, non-SPD system): surfaces as Python RuntimeError.
struct NumericalError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

}  // namespace matlearn
