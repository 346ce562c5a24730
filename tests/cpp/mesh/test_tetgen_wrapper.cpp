// TetGen wrapper: the switch string is the same under any global C++ locale (a decimal comma must
// not reach TetGen's parser: an old build read "q1,5" as q1 and meshed a cube without end), its
// numbers are printf "%.6g" as before, and a unit cube tetrahedralised under
// such a locale has volume 1, positively oriented tets and tets within the volume bound.
#include <cstdio>
#include <locale>
#include <sstream>
#include <string>

#include "check.hpp"
#include "mesh/tetgen_wrapper.hpp"

using namespace matlearn;

namespace {

/// A numpunct facet with a decimal comma (as de_DE has), built in code so no system locale is needed.
struct CommaDecimal : std::numpunct<char> {
  char do_decimal_point() const override { return ','; }
};

/// Restores the classic global locale when a test leaves, whatever happens inside it.
struct CommaLocaleScope {
  CommaLocaleScope() { std::locale::global(std::locale(std::locale::classic(), new CommaDecimal)); }
  ~CommaLocaleScope() { std::locale::global(std::locale::classic()); }
};

void unit_cube(MatX3& V, MatX3i& F) {
  V.resize(8, 3);
  for (int i = 0; i < 8; ++i) V.row(i) << (i & 1), (i >> 1) & 1, (i >> 2) & 1;
  F.resize(12, 3);
  F << 0, 2, 1, 1, 2, 3,  // z = 0
      4, 5, 6, 5, 7, 6,   // z = 1
      0, 1, 4, 1, 5, 4,   // y = 0
      2, 6, 3, 3, 6, 7,   // y = 1
      0, 4, 2, 2, 4, 6,   // x = 0
      1, 3, 5, 3, 7, 5;   // x = 1
}

double tet_volume(const MatX3& V, const MatX4i& T, int e) {
  Mat3 D;
  for (int k = 0; k < 3; ++k) D.col(k) = (V.row(T(e, k + 1)) - V.row(T(e, 0))).transpose();
  return D.determinant() / 6.0;
}

}  // namespace

TEST_CASE(switches_ignore_a_decimal_comma_locale) {
  CommaLocaleScope comma;
  std::ostringstream probe;  // what the old iostream-built switches would have written
  probe << 1.5;
  CHECK_MSG(probe.str() == "1,5", "the test locale does not write a decimal comma: " + probe.str());
  const std::string s = mesh::tetgen_switches(0.001, 1.5);
  CHECK_MSG(s == "pzQq1.5a0.001", "switches under a decimal-comma locale: " + s);
  CHECK(mesh::tetgen_switches(0.0, 0.0) == "pzQ");
}

TEST_CASE(switch_numbers_are_printf_g6) {
  // The bounds are written as "%.6g" in the C locale (as the iostream that built them before did
  // under the classic locale), so a mesh built from the same bounds is the same mesh.
  const double volumes[] = {1.2345678901234567e-7, 0.01, 2.5e-5, 123456789.0};
  const double ratios[] = {1.4142135623730951, 1.5, 2.0, 1.1000004};
  for (double v : volumes)
    for (double r : ratios) {
      char want[128];
      std::snprintf(want, sizeof want, "pzQq%.6ga%.6g", r, v);
      const std::string got = mesh::tetgen_switches(v, r);
      CHECK_MSG(got == want, "switches " + got + " vs " + want);
    }
}

TEST_CASE(non_finite_bounds_are_rejected) {
  CHECK_THROWS(mesh::tetgen_switches(std::nan(""), 1.5), InvalidInput);
  CHECK_THROWS(mesh::tetgen_switches(0.01, INFINITY), InvalidInput);
}

TEST_CASE(bounds_tetgen_cannot_meet_are_rejected) {
  // a radius-edge bound of 1.0 or 0.5 made TetGen refine without end (a regular tet has 0.61)
  CHECK_THROWS(mesh::tetgen_switches(0.01, 1.0), InvalidInput);
  CHECK_THROWS(mesh::tetgen_switches(0.01, 0.5), InvalidInput);
  CHECK_THROWS(mesh::tetgen_switches(0.01, -1.5), InvalidInput);
  CHECK_THROWS(mesh::tetgen_switches(-0.01, 1.5), InvalidInput);
  CHECK(mesh::tetgen_switches(0.01, mesh::kMinRadiusEdgeRatio) == "pzQq1.1a0.01");
}

TEST_CASE(cube_under_a_decimal_comma_locale) {
  CommaLocaleScope comma;
  MatX3 V, outV;
  MatX3i F;
  MatX4i outT;
  unit_cube(V, F);
  const double max_volume = 0.01;
  mesh::tetrahedralize(V, F, max_volume, 1.5, outV, outT);
  CHECK(outT.rows() >= 100);  // at least 1 / 0.01 tets
  double total = 0, smallest = 1, largest = 0;
  for (int e = 0; e < outT.rows(); ++e) {
    const double vol = tet_volume(outV, outT, e);
    total += vol;
    smallest = std::min(smallest, vol);
    largest = std::max(largest, vol);
  }
  CHECK_CLOSE(total, 1.0, 1e-12, "cube volume");
  CHECK_MSG(smallest > 0, "a tet is not positively oriented");
  CHECK_MSG(largest <= max_volume * (1 + 1e-9), "a tet exceeds the volume bound");
}
