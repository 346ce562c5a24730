#include "common.hpp"
#include "time/linearised_replay.hpp"

namespace matlearn::bindings {

using time::LinearisedReplay;

namespace {
/// Any 2-D float array -> column-major Eigen matrix (copy).
MatX as_dense(const py::array& a, const char* name) {
  auto arr = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(a);
  if (!arr || arr.ndim() != 2) throw InvalidInput(std::string(name) + ": expected a 2-D float array");
  Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> M(
      arr.data(), arr.shape(0), arr.shape(1));
  return M;
}

/// targets (steps, #prescribed, 3) or None -> (steps * #prescribed, 3); `have` says whether any.
MatX3 as_targets(const py::object& targets, long k, bool& have) {
  have = !targets.is_none();
  if (!have) return MatX3();
  auto t = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(targets);
  if (!t || t.ndim() != 3 || t.shape(1) != k || t.shape(2) != 3)
    throw InvalidInput("targets: expected shape (steps, " + std::to_string(k) + ", 3)");
  MatX3 T(t.shape(0) * k, 3);
  std::copy(t.data(), t.data() + t.size(), T.data());
  return T;
}
}  // namespace

void define_replay(py::module_& m) {
  py::class_<LinearisedReplay>(m, "LinearisedReplay",
                               "Linearised backward Euler (Integrator with max_newton=1) for many "
                               "models on one mesh and clamp: PCG with a reused Cholesky factor.")
      .def(py::init([](const fem::Model& model, const py::array& fixed, double h, const Vec3& gravity,
                       double tolerance, int refresh_iterations, int max_iterations, const py::object& prescribed) {
             const VecXi p = prescribed.is_none() ? VecXi() : as_index<1>(prescribed.cast<py::array>(), "prescribed");
             return std::make_unique<LinearisedReplay>(model, as_index<1>(fixed, "fixed"), h, gravity,
                                                       tolerance, refresh_iterations, max_iterations, p);
           }),
           py::arg("model"), py::arg("fixed"), py::arg("time_step"), py::arg("gravity"),
           py::arg("tolerance") = 1e-10, py::arg("refresh_iterations") = 10,
           py::arg("max_iterations") = 40, py::arg("prescribed") = py::none(),
           "prescribed: vertices that follow given targets (drive points; Integrator.set_prescribed); "
           "simulate() and tangent() then need targets (steps, #prescribed, 3).")
      .def("simulate",
           [](LinearisedReplay& R, const fem::Model& model, const py::array& x0, const py::array& v0,
              int steps, const py::array& f_ext, const py::object& targets) {
             const long n = model.mesh().num_vertices();
             const MatX3 x = as_matrix<3>(x0, "x0", n), v = as_matrix<3>(v0, "v0", n);
             const MatX3 f = as_matrix<3>(f_ext, "f_ext", n);
             bool have;
             const MatX3 T = as_targets(targets, R.prescribed().size(), have);
             MatX3 X, V;
             {
               py::gil_scoped_release r;
               X = R.simulate(model, x, v, steps, f, &V, have ? &T : nullptr);
             }
             return py::make_tuple(to_frames(X, n), to_frames(V, n));
           },
           py::arg("model"), py::arg("x0"), py::arg("v0"), py::arg("steps"), py::arg("f_ext"),
           py::arg("targets") = py::none(),
           "Simulate `steps` linearised steps of `model` from (x0, v0); returns (positions, "
           "velocities), each (steps+1, #V, 3), the initial state first. targets: positions of the "
           "prescribed vertices at the end of each step, (steps, #prescribed, 3).")
      .def("tangent",
           [](LinearisedReplay& R, const fem::Model& model, const py::array& x0, const py::array& v0,
              int steps, const py::array& f_ext, const py::array& dx0, const py::array& directions,
              const py::array& point_vertices, const py::array& point_weights, const py::object& targets) {
             const long n = model.mesh().num_vertices();
             const MatX3 x = as_matrix<3>(x0, "x0", n), v = as_matrix<3>(v0, "v0", n);
             const MatX3 f = as_matrix<3>(f_ext, "f_ext", n);
             const MatX D = as_dense(directions, "directions");
             const MatX dX0 = as_dense(dx0, "dx0");
             const MatX4i pv = as_index<4>(point_vertices, "point_vertices");
             const auto pw4 = as_dense(point_weights, "point_weights");
             if (pw4.cols() != 4) throw InvalidInput("point_weights: expected shape (P, 4)");
             const time::MatX4 pw = pw4;
             if (steps < 0) throw InvalidInput("steps must be >= 0");
             const long k = D.cols(), P = pv.rows();
             py::array_t<double> dP({static_cast<long>(steps) + 1, P, 3L, k});
             double* buf = dP.mutable_data();
             bool have;
             const MatX3 T = as_targets(targets, R.prescribed().size(), have);
             MatX3 X;
             {
               py::gil_scoped_release r;
               X = R.tangent(model, x, v, steps, f, dX0, D, pv, pw, buf, have ? &T : nullptr);
             }
             return py::make_tuple(to_frames(X, n), dP);
           },
           py::arg("model"), py::arg("x0"), py::arg("v0"), py::arg("steps"), py::arg("f_ext"),
           py::arg("dx0"), py::arg("directions"), py::arg("point_vertices"), py::arg("point_weights"),
           py::arg("targets") = py::none(),
           "Forward-mode sensitivities of simulate() for per-element log-stiffness directions "
           "(#T, k), all directions sharing one factorisation per step; dx0 (3 #V, k) is the "
           "derivative of the initial positions; targets as simulate() (prescribed vertices have "
           "zero derivative). Returns (positions (steps+1, #V, 3), derivative of "
           "the points sum_a w[p, a] x[vertices[p, a]]: (steps+1, P, 3, k)).")
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
