#include "fem/sparse_assembler.hpp"

#include <algorithm>

namespace matlearn::fem {

SparseAssembler::SparseAssembler(const MatX4i& tets, const VecXi& dof_map, int n, bool upper_only)
    : dof_map_(dof_map) {
  const int nt = tets.rows();
  std::vector<Eigen::Triplet<double, int>> trip;
  trip.reserve(size_t(nt) * 144 + n);
  auto dof = [&](int e, int a) { return 3 * tets(e, a / 3) + a % 3; };
  for (int e = 0; e < nt; ++e)
    for (int a = 0; a < 12; ++a)
      for (int b = 0; b < 12; ++b) {
        const int r = dof_map[dof(e, a)], c = dof_map[dof(e, b)];
        if (r < 0 || c < 0 || (upper_only && r > c)) continue;
        trip.emplace_back(r, c, 0.0);
      }
  for (int i = 0; i < n; ++i) trip.emplace_back(i, i, 0.0);
  pattern_.resize(n, n);
  pattern_.setFromTriplets(trip.begin(), trip.end());
  pattern_.makeCompressed();
  const int* outer = pattern_.outerIndexPtr();
  const int* inner = pattern_.innerIndexPtr();
  auto find = [&](int r, int c) {
    const int* begin = inner + outer[c];
    const int* end = inner + outer[c + 1];
    return int(std::lower_bound(begin, end, r) - inner);
  };
  slots_.assign(size_t(nt) * 144, -1);
  for (int e = 0; e < nt; ++e)
    for (int a = 0; a < 12; ++a)
      for (int b = 0; b < 12; ++b) {
        const int r = dof_map[dof(e, a)], c = dof_map[dof(e, b)];
        if (r < 0 || c < 0 || (upper_only && r > c)) continue;
        slots_[size_t(e) * 144 + a * 12 + b] = find(r, c);
      }
  diag_slot_.resize(n);
  for (int i = 0; i < n; ++i) diag_slot_[i] = find(i, i);
}

void SparseAssembler::assemble(const std::vector<Mat12>& A, double ca, const std::vector<Mat12>& B,
                               double cb, const VecX& d, double cdiag, SpMat& out) const {
  if (out.nonZeros() != pattern_.nonZeros() || out.rows() != pattern_.rows()) out = pattern_;
  double* val = out.valuePtr();
  std::fill(val, val + out.nonZeros(), 0.0);
  const int nt = int(slots_.size() / 144);
  const bool useB = !B.empty() && cb != 0.0;
  for (int e = 0; e < nt; ++e) {
    const int* s = slots_.data() + size_t(e) * 144;
    const Mat12& Ae = A[e];
    for (int a = 0; a < 12; ++a)
      for (int b = 0; b < 12; ++b) {
        const int k = s[a * 12 + b];
        if (k < 0) continue;
        // Eigen matrices are column-major: entry (a, b) is Ae(a, b).
        double v = ca * Ae(a, b);
        if (useB) v += cb * B[e](a, b);
        val[k] += v;
      }
  }
  if (d.size() > 0 && cdiag != 0.0) {
    // d is in global DOFs; map to reduced.
    for (int g = 0; g < dof_map_.size(); ++g) {
      const int r = dof_map_[g];
      if (r >= 0) val[diag_slot_[r]] += cdiag * d[g];
    }
  }
}

}  // namespace matlearn::fem
