#include "fem/sparse_assembler.hpp"

#include <algorithm>

namespace matlearn::fem {

SparseAssembler::SparseAssembler(const MatX4i& tets, const VecXi& dof_map, int n, bool upper_only)
    : dof_map_(dof_map) {
  const int nt = tets.rows();
  std::vector<Eigen::Triplet<double, int>> trip;
  trip.reserve(size_t(nt) * (upper_only ? 78 : 144) + n);
  auto dof = [&](int e, int a) { return 3 * tets(e, a / 3) + a % 3; };
  auto kept = [&](int e, int a, int b, int& r, int& c) {
    r = dof_map[dof(e, a)];
    c = dof_map[dof(e, b)];
    return r >= 0 && c >= 0 && !(upper_only && r > c);
  };
  for (int e = 0; e < nt; ++e)
    for (int b = 0; b < 12; ++b)
      for (int a = 0; a < 12; ++a) {
        int r, c;
        if (kept(e, a, b, r, c)) trip.emplace_back(r, c, 0.0);
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
  entry_begin_.assign(nt + 1, 0);
  local_.reserve(trip.size());
  slot_.reserve(trip.size());
  for (int e = 0; e < nt; ++e) {
    for (int b = 0; b < 12; ++b)
      for (int a = 0; a < 12; ++a) {
        int r, c;
        if (!kept(e, a, b, r, c)) continue;
        local_.push_back(short(a + 12 * b));
        slot_.push_back(find(r, c));
      }
    entry_begin_[e + 1] = int(slot_.size());
  }
  diag_slot_.resize(n);
  for (int i = 0; i < n; ++i) diag_slot_[i] = find(i, i);

}

template <class Entry>
void SparseAssembler::scatter(const Entry& entry, const VecX& d, double cdiag, SpMat& out) const {
  if (out.nonZeros() != pattern_.nonZeros() || out.rows() != pattern_.rows()) out = pattern_;
  double* val = out.valuePtr();
  std::fill(val, val + out.nonZeros(), 0.0);
  // Serial on purpose: the scatter is memory bound and ~2 ms per 10k tets, and a threaded
  // version (coloured chunks) was slower on the shared 2-core machines we run on.
  const int nt = int(entry_begin_.size()) - 1;
  for (int e = 0; e < nt; ++e)
    for (int j = entry_begin_[e]; j < entry_begin_[e + 1]; ++j) val[slot_[j]] += entry(e, local_[j]);
  if (d.size() > 0 && cdiag != 0.0) {
    // d is in global DOFs; map to reduced.
    for (int g = 0; g < dof_map_.size(); ++g) {
      const int r = dof_map_[g];
      if (r >= 0) val[diag_slot_[r]] += cdiag * d[g];
    }
  }
}

void SparseAssembler::assemble(const std::vector<Mat12>& A, double ca, const std::vector<Mat12>& B,
                               double cb, const VecX& d, double cdiag, SpMat& out) const {
  if (!B.empty() && cb != 0.0)
    scatter([&](int e, int l) { return ca * A[e].data()[l] + cb * B[e].data()[l]; }, d, cdiag, out);
  else
    scatter([&](int e, int l) { return ca * A[e].data()[l]; }, d, cdiag, out);
}

void SparseAssembler::assemble_scaled(const std::vector<Mat12>& A, const VecX& c, const VecX& d,
                                      SpMat& out) const {
  scatter([&](int e, int l) { return c[e] * A[e].data()[l]; }, d, 1.0, out);
}

}  // namespace matlearn::fem
