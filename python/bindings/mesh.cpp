#include "common.hpp"
#include "mesh/tetgen_wrapper.hpp"

namespace matlearn::bindings {

void define_mesh(py::module_& m) {
  m.def(
      "tetrahedralize",
      [](const py::array& vertices, const py::array& faces, double max_volume, double min_ratio) {
        const MatX3 V = as_matrix<3>(vertices, "vertices");
        const auto F = as_index<3>(faces, "faces");
        MatX3 outV;
        MatX4i outT;
        {
          py::gil_scoped_release release;
          mesh::tetrahedralize(V, F, max_volume, min_ratio, outV, outT);
        }
        return py::make_tuple(outV, outT);
      },
      py::arg("vertices"), py::arg("faces"), py::arg("max_volume") = 0.0,
      py::arg("min_ratio") = 0.0,
      "Tetrahedralise a closed surface with TetGen; returns (vertices (#V,3), tets (#T,4)).");
}

}  // namespace matlearn::bindings
