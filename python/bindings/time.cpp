#include "common.hpp"
#include "time/integrator.hpp"

namespace matlearn::bindings {

using time::Integrator;

static time::ProgressFn wrap_progress(py::object cb) {
  if (cb.is_none()) {
    // Still let Ctrl-C interrupt long runs.
    return [](int, int) {
      py::gil_scoped_acquire gil;
      if (PyErr_CheckSignals() != 0) throw py::error_already_set();
    };
  }
  return [cb](int done, int total) {
    py::gil_scoped_acquire gil;
    if (PyErr_CheckSignals() != 0) throw py::error_already_set();
    cb(done, total);
  };
}

void define_time(py::module_& m) {
  py::class_<Integrator>(m, "Integrator")
      .def(py::init([](std::shared_ptr<const fem::Model> model, const py::array& fixed, double h,
                       const Vec3& gravity, int max_newton, double tolerance,
                       bool reuse_factorization, double reuse_ratio, bool extrapolate) {
             time::StepOptions o;
             o.max_newton = max_newton;
             o.tolerance = tolerance;
             o.reuse_factorization = reuse_factorization;
             o.reuse_ratio = reuse_ratio;
             o.extrapolate = extrapolate;
             return std::make_unique<Integrator>(model, as_index<1>(fixed, "fixed"), h, gravity, o);
           }),
           py::arg("model"), py::arg("fixed"), py::arg("time_step"), py::arg("gravity"),
           py::arg("max_newton") = 8, py::arg("tolerance") = 1e-7,
           py::arg("reuse_factorization") = true, py::arg("reuse_ratio") = 0.25,
           py::arg("extrapolate") = true,
           "reuse_factorization: iterate with the last factorised step matrix while it contracts "
           "(chord iterations, same fixed point and stopping test) while |dv| shrinks by reuse_ratio "
           "per iteration; ignored when max_newton = 1. extrapolate: start each step's iteration "
           "from v_n + (v_n - v_{n-1}).")
      .def_property_readonly("x", &Integrator::x)
      .def_property_readonly("v", &Integrator::v)
      .def_property_readonly("time_step", &Integrator::time_step)
      .def_property_readonly("steps_taken", &Integrator::steps_taken)
      .def_property_readonly("last_iterations", &Integrator::last_iterations)
      .def_property_readonly(
          "unconverged_steps", &Integrator::unconverged_steps,
          "Steps since construction or set_state() whose Newton iteration hit its limit without "
          "meeting the tolerance (kept as they were: inaccurate, possibly unstable); never counted "
          "with max_newton = 1.")
      .def_property_readonly(
          "last_timings",
          [](const Integrator& I) {
            const auto& t = I.last_timings();
            py::dict d;
            d["evaluate_s"] = t.evaluate_s;
            d["assemble_s"] = t.assemble_s;
            d["factorize_s"] = t.factorize_s;
            d["solve_s"] = t.solve_s;
            d["iterations"] = t.iterations;
            d["factorizations"] = t.factorizations;
            d["updates"] = t.updates;
            return d;
          },
          "Wall-clock seconds per phase of the last step, summed over its Newton iterations.")
      .def_property_readonly(
          "last_static_iterations",
          [](const Integrator& I) {
            const auto& t = I.last_static_timings();
            py::dict d;
            d["iterations"] = t.iterations;
            d["factorizations"] = t.factorizations;
            return d;
          },
          "Steps (chord and fresh-tangent) and tangent factorisations of the last static_solve.")
      .def_property_readonly("fixed", &Integrator::fixed)
      .def_property_readonly("prescribed", &Integrator::prescribed)
      .def("set_state",
           [](Integrator& I, const py::array& x, const py::array& v) {
             const long n = I.model().mesh().num_vertices();
             I.set_state(as_matrix<3>(x, "x", n), as_matrix<3>(v, "v", n));
           },
           py::arg("x"), py::arg("v"))
      .def("set_prescribed",
           [](Integrator& I, const py::array& idx) { I.set_prescribed(as_index<1>(idx, "vertices")); },
           py::arg("vertices"))
      .def("step",
           [](Integrator& I, const py::array& f_ext, py::object targets) {
             const long n = I.model().mesh().num_vertices();
             const MatX3 f = as_matrix<3>(f_ext, "f_ext", n);
             if (targets.is_none()) {
               py::gil_scoped_release r;
               I.step(f);
             } else {
               const MatX3 t = as_matrix<3>(targets, "targets", I.prescribed().size());
               py::gil_scoped_release r;
               I.step(f, &t);
             }
           },
           py::arg("f_ext"), py::arg("targets") = py::none())
      .def("simulate",
           [](Integrator& I, int steps, const py::array& f_ext, int record_every,
              py::object progress) {
             const long n = I.model().mesh().num_vertices();
             const MatX3 f = as_matrix<3>(f_ext, "f_ext", n);
             auto cb = wrap_progress(progress);
             MatX3 X, V;
             {
               py::gil_scoped_release r;
               X = I.simulate(steps, f, record_every, cb, &V);
             }
             return py::make_tuple(to_frames(X, n), to_frames(V, n));
           },
           py::arg("steps"), py::arg("f_ext"), py::arg("record_every") = 1,
           py::arg("progress") = py::none(),
           "Simulate `steps` steps; returns (positions, velocities), each (frames, #V, 3), "
           "the initial state first.")
      .def("simulate_constrained",
           [](Integrator& I, const py::array& targets, const py::array& f_ext, py::object progress) {
             const long n = I.model().mesh().num_vertices();
             const long k = I.prescribed().size();
             auto t = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(targets);
             if (!t || t.ndim() != 3 || t.shape(1) != k || t.shape(2) != 3)
               throw InvalidInput("targets: expected shape (steps, " + std::to_string(k) + ", 3)");
             MatX3 T(t.shape(0) * k, 3);
             std::copy(t.data(), t.data() + t.size(), T.data());
             const MatX3 f = as_matrix<3>(f_ext, "f_ext", n);
             auto cb = wrap_progress(progress);
             MatX3 X, V;
             {
               py::gil_scoped_release r;
               X = I.simulate_constrained(T, f, cb, &V);
             }
             return py::make_tuple(to_frames(X, n), to_frames(V, n));
           },
           py::arg("targets"), py::arg("f_ext"), py::arg("progress") = py::none())
      .def("static_solve",
           [](Integrator& I, const py::array& f_ext, int load_steps, int max_iterations, double tol) {
             const MatX3 f = as_matrix<3>(f_ext, "f_ext", I.model().mesh().num_vertices());
             py::gil_scoped_release r;
             I.static_solve(f, load_steps, max_iterations, tol);
           },
           py::arg("f_ext"), py::arg("load_steps") = 1, py::arg("max_iterations") = 50,
           py::arg("tolerance") = 1e-9);
}

}  // namespace matlearn::bindings
