#include <cstdlib>

#include "common.hpp"
#include "solvers/blas_threads.hpp"

PYBIND11_MODULE(_core, m) {
  m.doc() = "matlearn C++ core: FEM, materials, implicit stepping, corrections (private API)";
  // Dependency order: corrections are used by the FEM model, which the integrator steps.
  auto corr = m.def_submodule("correction", "learned stress corrections (RBF, MLP, callback)");
  matlearn::bindings::define_correction(corr);
  auto fem = m.def_submodule("fem", "tet meshes, materials, assembly");
  matlearn::bindings::define_fem(fem);
  auto time = m.def_submodule("time", "backward Euler, constrained stepping, statics");
  matlearn::bindings::define_time(time);
  matlearn::bindings::define_replay(time);
  // Space-time optimisation builds on the FEM model (forces and nominal tangents).
  auto st = m.def_submodule("spacetime", "sparse reduced space-time optimisation, control forces");
  matlearn::bindings::define_spacetime(st);
  auto fit = m.def_submodule("fit", "normal equations of the stress-correction fit over all frames");
  matlearn::bindings::define_fit(fit);
  auto obs = m.def_submodule("observation", "point-cloud correspondences and observation residuals");
  matlearn::bindings::define_observation(obs);
  auto mesh = m.def_submodule("mesh", "TetGen tetrahedralisation");
  matlearn::bindings::define_mesh(mesh);
  // One OpenBLAS thread unless the user asked for more (solvers/blas_threads.hpp: OpenBLAS
  // threads spinning between CHOLMOD calls starve the OpenMP element loops).
  if (!std::getenv("OPENBLAS_NUM_THREADS") && !std::getenv("GOTO_NUM_THREADS"))
    matlearn::solvers::set_blas_threads(1);
  m.def("blas_threads", &matlearn::solvers::blas_threads,
        "OpenBLAS's thread count (the BLAS under CHOLMOD), -1 if the BLAS is not OpenBLAS. matlearn "
        "sets 1 when loaded unless OPENBLAS_NUM_THREADS is set.");
  m.def("set_blas_threads", &matlearn::solvers::set_blas_threads, py::arg("n"),
        "Set OpenBLAS's thread count; False if the BLAS is not OpenBLAS.");
  m.def("build_info", []() {
    py::dict d;
#ifdef _OPENMP
    d["openmp"] = true;
#else
    d["openmp"] = false;
#endif
    d["eigen"] = std::to_string(EIGEN_WORLD_VERSION) + "." + std::to_string(EIGEN_MAJOR_VERSION) +
                 "." + std::to_string(EIGEN_MINOR_VERSION);
    d["index_type"] = "int32";
    return d;
  });
}
