#pragma once
/// Small meshes and seeded random states shared by the C++ tests.
#include <memory>
#include <random>

#include "common/types.hpp"
#include "fem/tet_mesh.hpp"

namespace mltest {

/// Box of nx x ny x nz cells of size (lx, ly, lz) at the origin, six positively oriented tets
/// per cell (the same Kuhn split as matlearn.meshes.grid_tets).
inline std::shared_ptr<matlearn::fem::TetMesh> grid_mesh(int nx, int ny, int nz, double lx,
                                                         double ly, double lz) {
  using namespace matlearn;
  auto id = [&](int i, int j, int k) { return (i * (ny + 1) + j) * (nz + 1) + k; };
  MatX3 V((nx + 1) * (ny + 1) * (nz + 1), 3);
  for (int i = 0; i <= nx; ++i)
    for (int j = 0; j <= ny; ++j)
      for (int k = 0; k <= nz; ++k)
        V.row(id(i, j, k)) << lx * i / nx, ly * j / ny, lz * k / nz;
  static const int kuhn[6][4] = {{0, 1, 3, 7}, {0, 1, 7, 5}, {0, 5, 7, 4},
                                 {0, 3, 2, 7}, {0, 2, 6, 7}, {0, 6, 4, 7}};
  MatX4i T(6 * nx * ny * nz, 4);
  int t = 0;
  for (int i = 0; i < nx; ++i)
    for (int j = 0; j < ny; ++j)
      for (int k = 0; k < nz; ++k) {
        int c[8];
        for (int b = 0; b < 8; ++b) c[b] = id(i + (b & 1), j + ((b >> 1) & 1), k + ((b >> 2) & 1));
        for (const auto& tet : kuhn) {
          for (int a = 0; a < 4; ++a) T(t, a) = c[tet[a]];
          Mat3 D;
          for (int a = 0; a < 3; ++a) D.col(a) = (V.row(T(t, a + 1)) - V.row(T(t, 0))).transpose();
          if (D.determinant() < 0) std::swap(T(t, 1), T(t, 2));
          ++t;
        }
      }
  return std::make_shared<fem::TetMesh>(V, T);
}

/// A proper rotation from a seeded generator (QR of a Gaussian matrix, sign fixed).
inline matlearn::Mat3 random_rotation(std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  matlearn::Mat3 A;
  for (int i = 0; i < 9; ++i) A.data()[i] = n(rng);
  Eigen::HouseholderQR<matlearn::Mat3> qr(A);
  matlearn::Mat3 Q = qr.householderQ();
  if (Q.determinant() < 0) Q.col(0) *= -1;
  return Q;
}

}  // namespace mltest
