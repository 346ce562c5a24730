#pragma once
#include <vector>

#include "common/types.hpp"

namespace matlearn::fem {

/// A linear tetrahedral mesh with its rest data.
class TetMesh {
 public:
  /// vertices (#V x 3) rest positions in m, tets (#T x 4) 0-based indices.
  /// Throws InvalidInput on NaN, out-of-range indices, or degenerate/inverted tets.
  TetMesh(const MatX3& vertices, const MatX4i& tets);

  int num_vertices() const { return static_cast<int>(X_.rows()); }
  int num_tets() const { return static_cast<int>(T_.rows()); }
  const MatX3& vertices() const { return X_; }
  const MatX4i& tets() const { return T_; }
  /// Inverse rest edge matrices Bm = Dm^-1, one per tet.
  const std::vector<Mat3>& Bm() const { return Bm_; }
  /// Rest volumes W (m^3), (#T).
  const VecX& volumes() const { return W_; }
  /// Boundary triangles (#F x 3), oriented outward.
  const MatX3i& surface_faces() const { return F_; }
  /// Lumped vertex masses (kg) for per-tet density (kg/m^3), (#V).
  VecX lumped_mass(const VecX& density) const;
  /// Deformation gradient of tet e for positions x (#V x 3).
  Mat3 deformation_gradient(const MatX3& x, int e) const;

 private:
  MatX3 X_;
  MatX4i T_;
  std::vector<Mat3> Bm_;
  VecX W_;
  MatX3i F_;
};

}  // namespace matlearn::fem
