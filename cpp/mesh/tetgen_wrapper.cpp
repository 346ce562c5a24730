#include "mesh/tetgen_wrapper.hpp"

#include <tetgen.h>

#include <charconv>
#include <cmath>
#include <string>
#include <vector>

namespace matlearn::mesh {

namespace {
// printf's "%.6g" (what an iostream writes by default, so meshes stay as they were), but independent
// of any locale: std::to_chars never uses one, while an iostream takes the global C++ locale, whose
// decimal comma turned "q1.5" into "q1,5", which TetGen reads as q1 and then meshes without end.
void append_number(std::string& s, double x) {
  char buf[64];
  auto r = std::to_chars(buf, buf + sizeof buf, x, std::chars_format::general, 6);
  s.append(buf, r.ptr);
}
}  // namespace

std::string tetgen_switches(double max_volume, double min_ratio) {
  if (!std::isfinite(max_volume) || !std::isfinite(min_ratio))
    throw InvalidInput("tetrahedralize: max_volume and min_ratio must be finite");
  if (max_volume < 0)
    throw InvalidInput("tetrahedralize: max_volume (m^3) must be positive (0: no volume bound), got " +
                       std::to_string(max_volume));
  // TetGen's Delaunay refinement is guaranteed to end only for a bound of 2; in practice it ends
  // down to about 1.1 and runs without end below (1.0 and 0.5 never returned; a regular tet has
  // 0.61, so no mesh can meet a bound below that)
  if (min_ratio < 0 || (min_ratio > 0 && min_ratio < kMinRadiusEdgeRatio))
    throw InvalidInput("tetrahedralize: min_ratio (TetGen's radius-edge bound) must be at least 1.1, "
                       "or 0 for no quality bound; TetGen's refinement may never finish below it; got " +
                       std::to_string(min_ratio));
  std::string s = "pzQ";  // PLC, zero-based, quiet
  if (min_ratio > 0) {
    s += 'q';
    append_number(s, min_ratio);
  }
  if (max_volume > 0) {
    s += 'a';
    append_number(s, max_volume);
  }
  return s;
}

void tetrahedralize(const MatX3& V, const MatX3i& F, double max_volume, double min_ratio,
                    MatX3& out_V, MatX4i& out_T) {
  if (V.rows() < 4 || F.rows() < 4) throw InvalidInput("tetrahedralize: surface too small");
  if (!V.allFinite()) throw InvalidInput("tetrahedralize: vertices contain NaN or Inf");
  if (F.minCoeff() < 0 || F.maxCoeff() >= V.rows())
    throw InvalidInput("tetrahedralize: face index out of range");
  tetgenio in, out;
  in.firstnumber = 0;
  in.numberofpoints = V.rows();
  in.pointlist = new REAL[V.size()];
  for (int i = 0; i < V.rows(); ++i)
    for (int k = 0; k < 3; ++k) in.pointlist[3 * i + k] = V(i, k);
  in.numberoffacets = F.rows();
  in.facetlist = new tetgenio::facet[F.rows()];
  in.facetmarkerlist = nullptr;
  for (int f = 0; f < F.rows(); ++f) {
    tetgenio::facet& fc = in.facetlist[f];
    tetgenio::init(&fc);
    fc.numberofpolygons = 1;
    fc.polygonlist = new tetgenio::polygon[1];
    tetgenio::init(&fc.polygonlist[0]);
    fc.polygonlist[0].numberofvertices = 3;
    fc.polygonlist[0].vertexlist = new int[3];
    for (int k = 0; k < 3; ++k) fc.polygonlist[0].vertexlist[k] = F(f, k);
  }
  const std::string switches = tetgen_switches(max_volume, min_ratio);
  std::vector<char> buf(switches.begin(), switches.end());
  buf.push_back('\0');
  try {
    ::tetrahedralize(buf.data(), &in, &out);
  } catch (int code) {
    static const char* msgs[] = {"", "out of memory", "internal error",
                                 "self-intersecting or non-manifold surface",
                                 "a very small input feature size was detected",
                                 "two very close input facets", "", "", "", "",
                                 "an input error (e.g. a facet with fewer than 3 vertices)"};
    std::string why = (code >= 0 && code <= 10 && msgs[code][0]) ? msgs[code] : "unknown error";
    throw InvalidInput("TetGen failed (code " + std::to_string(code) + "): " + why +
                       "; the surface must be closed, manifold and not self-intersecting");
  }
  if (out.numberoftetrahedra == 0)
    throw InvalidInput("TetGen produced no tets: is the surface closed?");
  out_V.resize(out.numberofpoints, 3);
  for (int i = 0; i < out.numberofpoints; ++i)
    for (int k = 0; k < 3; ++k) out_V(i, k) = out.pointlist[3 * i + k];
  out_T.resize(out.numberoftetrahedra, 4);
  for (int e = 0; e < out.numberoftetrahedra; ++e) {
    for (int k = 0; k < 4; ++k) out_T(e, k) = out.tetrahedronlist[4 * e + k];
    Mat3 Dm;
    for (int k = 0; k < 3; ++k) Dm.col(k) = (out_V.row(out_T(e, k + 1)) - out_V.row(out_T(e, 0))).transpose();
    if (Dm.determinant() < 0) std::swap(out_T(e, 1), out_T(e, 2));
  }
  // Drop points not used by any tet (TetGen can keep unused input points).
  std::vector<int> remap(out_V.rows(), -1);
  int n = 0;
  for (int e = 0; e < out_T.rows(); ++e)
    for (int k = 0; k < 4; ++k)
      if (remap[out_T(e, k)] < 0) remap[out_T(e, k)] = 0;
  for (auto& r : remap)
    if (r == 0) r = n++;
  if (n != out_V.rows()) {
    MatX3 V2(n, 3);
    for (int i = 0; i < out_V.rows(); ++i)
      if (remap[i] >= 0) V2.row(remap[i]) = out_V.row(i);
    for (int e = 0; e < out_T.rows(); ++e)
      for (int k = 0; k < 4; ++k) out_T(e, k) = remap[out_T(e, k)];
    out_V = V2;
  }
}

}  // namespace matlearn::mesh
