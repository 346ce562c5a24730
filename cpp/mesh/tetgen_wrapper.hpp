#pragma once
#include "common/types.hpp"

#include <string>

namespace matlearn::mesh {

/// The smallest radius-edge bound accepted: TetGen's refinement may run without end below it.
inline constexpr double kMinRadiusEdgeRatio = 1.1;

/// Tetrahedralise a closed, manifold triangle surface with TetGen.
/// max_volume > 0 bounds tet volume (m^3); min_ratio >= kMinRadiusEdgeRatio bounds the
/// radius-edge ratio (0 for either: no bound; a negative one or a ratio in (0, 1.1): InvalidInput).
/// Returns vertices (#V x 3) and positively oriented tets (#T x 4).
/// The TetGen switch string for these bounds ("pzQ" + "q<ratio>" + "a<volume>", numbers as
/// printf "%.6g" writes them in the C locale, whatever the global locale). Non-finite: InvalidInput.
std::string tetgen_switches(double max_volume, double min_ratio);

void tetrahedralize(const MatX3& vertices, const MatX3i& faces, double max_volume,
                    double min_ratio, MatX3& out_vertices, MatX4i& out_tets);

}  // namespace matlearn::mesh
