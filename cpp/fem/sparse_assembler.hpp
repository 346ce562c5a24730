#pragma once
#include <vector>

#include "common/types.hpp"

namespace matlearn::fem {

/// Fixed sparsity pattern of a tet mesh's 3n x 3n operators restricted to a DOF subset, with
/// the slot of every element-block entry precomputed so assembly is a scatter without search.
class SparseAssembler {
 public:
  /// dof_map: (3n) global DOF -> reduced index, or -1 to drop it. upper_only keeps entries
  /// with row <= col (what CHOLMOD's symmetric mode reads).
  SparseAssembler(const MatX4i& tets, const VecXi& dof_map, int reduced_size, bool upper_only);

  /// out = sum_e (ca * A_e + cb * B_e) + diag(cdiag * d) on the pattern; B may be empty.
  /// d is indexed by global DOF.
  void assemble(const std::vector<Mat12>& A, double ca, const std::vector<Mat12>& B, double cb,
                const VecX& d, double cdiag, SpMat& out) const;
  /// out = sum_e c_e A_e + diag(d) with one coefficient per element; d is indexed by global DOF.
  void assemble_scaled(const std::vector<Mat12>& A, const VecX& c, const VecX& d, SpMat& out) const;
  const SpMat& pattern() const { return pattern_; }

 private:
  template <class Entry>
  void scatter(const Entry& entry, const VecX& d, double cdiag, SpMat& out) const;

  SpMat pattern_;
  /// Per element, the kept entries of its 12 x 12 block: (column-major local index, value slot).
  std::vector<int> entry_begin_;  // (#T + 1) offsets into local_/slot_
  std::vector<short> local_;
  std::vector<int> slot_;
  std::vector<int> diag_slot_;    // reduced index -> value index of its diagonal
  VecXi dof_map_;
};

}  // namespace matlearn::fem
