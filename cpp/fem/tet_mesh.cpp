#include "fem/tet_mesh.hpp"

#include <algorithm>
#include <array>
#include <map>
#include <sstream>

namespace matlearn::fem {

TetMesh::TetMesh(const MatX3& vertices, const MatX4i& tets) : X_(vertices), T_(tets) {
  const int nv = X_.rows(), nt = T_.rows();
  if (nv < 4 || nt < 1) throw InvalidInput("TetMesh: need at least 4 vertices and 1 tet");
  if (!X_.allFinite()) throw InvalidInput("TetMesh: vertices contain NaN or Inf");
  if (T_.minCoeff() < 0 || T_.maxCoeff() >= nv) {
    std::ostringstream os;
    os << "TetMesh: tet indices must lie in [0, " << nv << "), got range [" << T_.minCoeff()
       << ", " << T_.maxCoeff() << "]";
    throw InvalidInput(os.str());
  }
  const double scale = (X_.colwise().maxCoeff() - X_.colwise().minCoeff()).norm();
  const double vol_eps = 1e-14 * scale * scale * scale;
  Bm_.resize(nt);
  W_.resize(nt);
  std::vector<int> bad_inverted, bad_degenerate;
  for (int e = 0; e < nt; ++e) {
    Mat3 Dm;
    for (int k = 0; k < 3; ++k) Dm.col(k) = (X_.row(T_(e, k + 1)) - X_.row(T_(e, 0))).transpose();
    const double det = Dm.determinant();
    if (std::abs(det) / 6.0 <= vol_eps) {
      bad_degenerate.push_back(e);
      continue;
    }
    if (det < 0) {
      bad_inverted.push_back(e);
      continue;
    }
    Bm_[e] = Dm.inverse();
    W_[e] = det / 6.0;
  }
  auto list = [](const std::vector<int>& v) {
    std::ostringstream os;
    for (size_t i = 0; i < std::min<size_t>(v.size(), 10); ++i) os << (i ? ", " : "") << v[i];
    if (v.size() > 10) os << ", ...";
    return os.str();
  };
  if (!bad_degenerate.empty())
    throw InvalidInput("TetMesh: " + std::to_string(bad_degenerate.size()) +
                       " degenerate (zero-volume) tets, e.g. tets " + list(bad_degenerate));
  if (!bad_inverted.empty())
    throw InvalidInput("TetMesh: " + std::to_string(bad_inverted.size()) +
                       " inverted tets (negative orientation), e.g. tets " + list(bad_inverted) +
                       "; swap two indices of each to fix the orientation");

  // Boundary faces: faces that belong to exactly one tet. Orientation: outward normal, i.e. the
  // opposite vertex lies on the negative side.
  static const int fv[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};
  std::map<std::array<int, 3>, std::pair<int, std::array<int, 3>>> faces;
  for (int e = 0; e < nt; ++e)
    for (int f = 0; f < 4; ++f) {
      std::array<int, 3> tri{T_(e, fv[f][0]), T_(e, fv[f][1]), T_(e, fv[f][2])};
      std::array<int, 3> key = tri;
      std::sort(key.begin(), key.end());
      auto it = faces.find(key);
      if (it == faces.end())
        faces.emplace(key, std::make_pair(1, tri));
      else
        it->second.first += 1;
    }
  std::vector<std::array<int, 3>> boundary;
  for (auto& [key, val] : faces) {
    if (val.first > 2)
      throw InvalidInput("TetMesh: non-manifold mesh, a face is shared by more than two tets");
    if (val.first == 1) boundary.push_back(val.second);
  }
  F_.resize(boundary.size(), 3);
  for (size_t i = 0; i < boundary.size(); ++i)
    for (int k = 0; k < 3; ++k) F_(i, k) = boundary[i][k];
}

VecX TetMesh::lumped_mass(const VecX& density) const {
  if (density.size() != num_tets())
    throw InvalidInput("lumped_mass: density must have one value per tet");
  VecX m = VecX::Zero(num_vertices());
  for (int e = 0; e < num_tets(); ++e)
    for (int a = 0; a < 4; ++a) m[T_(e, a)] += density[e] * W_[e] / 4.0;
  return m;
}

Mat3 TetMesh::deformation_gradient(const MatX3& x, int e) const {
  Mat3 Ds;
  for (int k = 0; k < 3; ++k) Ds.col(k) = (x.row(T_(e, k + 1)) - x.row(T_(e, 0))).transpose();
  return Ds * Bm_[e];
}

}  // namespace matlearn::fem
