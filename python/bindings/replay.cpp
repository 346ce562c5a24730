#include "common.hpp"
#include "time/linearised_replay.hpp"

namespace matlearn::bindings {

using time::LinearisedReplay;

void define_replay(py::module_& m) {
  py::class_<LinearisedReplay>(m, "LinearisedReplay",
                               "Linearised backward Euler (Integrator with max_newton=1) for many "
                               "models on one mesh and clamp: PCG with a reused Cholesky factor.")
      .def(py::init([](const fem::Model& model, const py::array& fixed, double h, const Vec3& gravity,
                       double tolerance, int refresh_iterations, int max_iterations) {
             return std::make_unique<LinearisedReplay>(model, as_index<1>(fixed, "fixed"), h, gravity,
                                                       tolerance, refresh_iterations, max_iterations);
           }),
           py::arg("model"), py::arg("fixed"), py::arg("time_step"), py::arg("gravity"),
           py::arg("tolerance") = 1e-10, py::arg("refresh_iterations") = 10,
           py::arg("max_iterations") = 40)
      .def("simulate",
           [](LinearisedReplay& R, const fem::Model& model, const py::array& x0, const py::array& v0,
              int steps, const py::array& f_ext) {
             const long n = model.mesh().num_vertices();
             const MatX3 x = as_matrix<3>(x0, "x0", n), v = as_matrix<3>(v0, "v0", n);
             const MatX3 f = as_matrix<3>(f_ext, "f_ext", n);
             MatX3 X, V;
             {
               py::gil_scoped_release r;
               X = R.simulate(model, x, v, steps, f, &V);
             }
             return py::make_tuple(to_frames(X, n), to_frames(V, n));
           },
           py::arg("model"), py::arg("x0"), py::arg("v0"), py::arg("steps"), py::arg("f_ext"),
           "Simulate `steps` linearised steps of `model` from (x0, v0); returns (positions, "
           "velocities), each (steps+1, #V, 3), the initial state first.")
      .def_property_readonly("stats", [](const LinearisedReplay& R) {
        const auto& s = R.stats();
        py::dict d;
        d["steps"] = s.steps;
        d["factorizations"] = s.factorizations;
        d["pcg_iterations"] = s.pcg_iterations;
        d["direct_fallbacks"] = s.direct_fallbacks;
        return d;
      });
}

}  // namespace matlearn::bindings
