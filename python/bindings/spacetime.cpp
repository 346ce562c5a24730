#include "common.hpp"
#include "spacetime/spacetime_problem.hpp"

namespace matlearn::bindings {

using spacetime::MatXr;
using spacetime::SpaceTimeProblem;

/// numpy (rows, cols) or (frames, n, 3) -> row-major (rows x cols) with a shape check.
static MatXr as_rowmajor(const py::array& a, const char* name, long cols, long rows = -1) {
  auto arr = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(a);
  if (!arr) throw InvalidInput(std::string(name) + ": expected a float array");
  long r = 0, c = 0;
  if (arr.ndim() == 3) {
    r = arr.shape(0);
    c = arr.shape(1) * arr.shape(2);
  } else if (arr.ndim() == 2 && arr.shape(1) == 3 && 3 * arr.shape(0) == cols && cols != 3) {
    r = 1;  // a single (#V, 3) state for all frames
    c = cols;
  } else if (arr.ndim() == 2) {
    r = arr.shape(0);
    c = arr.shape(1);
  } else if (arr.ndim() == 1) {
    r = 1;
    c = arr.shape(0);
  }
  if (c != cols || (rows >= 0 && r != rows) || r < 1) {
    std::string got = "(";
    for (int i = 0; i < arr.ndim(); ++i) got += (i ? ", " : "") + std::to_string(arr.shape(i));
    throw InvalidInput(std::string(name) + ": expected " + std::to_string(cols) +
                       " values per row" + (rows >= 0 ? " and " + std::to_string(rows) + " rows" : "") +
                       ", got shape " + got + ")");
  }
  MatXr M(r, c);
  std::copy(arr.data(), arr.data() + arr.size(), M.data());
  return M;
}

void define_spacetime(py::module_& m) {
  py::class_<SpaceTimeProblem>(m, "SpaceTimeProblem",
                               "Sparse reduced space-time problem (method.md section 5); see "
                               "cpp/spacetime/spacetime_problem.hpp.")
      .def(py::init([](std::shared_ptr<const fem::Model> model, const py::array& phi,
                       const py::array& base, const py::array& fext, double h,
                       const py::array& S_phi, const py::array& S_base, const py::array& frame,
                       const py::array& weight, const py::array& targets, double lam,
                       bool nominal_tangent) {
             if (!model) throw InvalidInput("model is None");
             const long n = model->mesh().num_vertices();
             auto P = py::array_t<double, py::array::f_style | py::array::forcecast>::ensure(phi);
             if (!P || P.ndim() != 2 || P.shape(0) != 3 * n)
               throw InvalidInput("phi: expected shape (3*#V, r) with #V = " + std::to_string(n));
             MatX Phi(P.shape(0), P.shape(1));
             std::copy(P.data(), P.data() + P.size(), Phi.data());
             spacetime::Observations obs;
             auto sp = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(S_phi);
             if (!sp || sp.ndim() != 2 || sp.shape(1) != Phi.cols())
               throw InvalidInput("S_phi: expected shape (3K, r)");
             const long rows = sp.shape(0);
             obs.S_phi = as_rowmajor(S_phi, "S_phi", Phi.cols(), rows);
             const VecXi fr = as_index<1>(frame, "frame");
             obs.frame = fr;
             obs.weight = as_matrix<1>(weight, "weight", fr.size());
             if (fr.size() > 0) {
               obs.S_base = as_rowmajor(S_base, "S_base", rows);
               obs.targets = as_rowmajor(targets, "targets", rows, fr.size());
             } else {
               obs.S_base = MatXr::Zero(1, rows);
               obs.targets = MatXr::Zero(0, rows);
             }
             return std::make_unique<SpaceTimeProblem>(
                 model, std::move(Phi), as_rowmajor(base, "base", 3 * n),
                 as_rowmajor(fext, "fext", 3 * n), h, std::move(obs), lam, nominal_tangent);
           }),
           py::arg("model"), py::arg("phi"), py::arg("base"), py::arg("fext"), py::arg("time_step"),
           py::arg("S_phi"), py::arg("S_base"), py::arg("frame"), py::arg("weight"),
           py::arg("targets"), py::arg("lam"), py::arg("nominal_tangent") = true,
           "phi (3#V, r); base, fext (frames, #V, 3) or (#V, 3); S_phi (3K, r); S_base (frames, "
           "3K) or (3K,); frame, weight (T,); targets (T, 3K) with NaN where unseen.")
      .def_property_readonly("frames", &SpaceTimeProblem::frames)
      .def_property_readonly("modes", &SpaceTimeProblem::modes)
      .def_property_readonly("num_unknowns", &SpaceTimeProblem::num_unknowns)
      .def_property_readonly("num_residuals", &SpaceTimeProblem::num_residuals)
      .def_property("tangent_stride", &SpaceTimeProblem::tangent_stride,
                    &SpaceTimeProblem::set_tangent_stride,
                    "Frames sharing one tangent evaluation in the Jacobian blocks (1: every frame).")
      .def_property_readonly("num_physics_rows", &SpaceTimeProblem::num_physics_rows)
      .def("positions",
           [](const SpaceTimeProblem& P, const py::array& Z) {
             const MatXr z = as_rowmajor(Z, "Z", P.modes(), P.frames());
             MatX3 X;
             {
               py::gil_scoped_release r;
               X = P.positions(z);
             }
             return to_frames(X, X.rows() / P.frames());
           },
           py::arg("Z"), "Positions (frames, #V, 3) for modal coordinates Z (frames, r).")
      .def("residual",
           [](const SpaceTimeProblem& P, const py::array& Z) {
             const MatXr z = as_rowmajor(Z, "Z", P.modes(), P.frames());
             py::gil_scoped_release r;
             return P.residual(z);
           },
           py::arg("Z"))
      .def("linearize",
           [](SpaceTimeProblem& P, const py::array& Z) {
             const MatXr z = as_rowmajor(Z, "Z", P.modes(), P.frames());
             py::gil_scoped_release r;
             P.linearize(z);
           },
           py::arg("Z"))
      .def("jvp",
           [](const SpaceTimeProblem& P, const py::array& p) {
             const VecX v = as_matrix<1>(p, "p", P.num_unknowns());
             py::gil_scoped_release r;
             return P.jvp(v);
           },
           py::arg("p"), "J p at the last linearisation (p frame-major, length frames*r).")
      .def("vjp",
           [](const SpaceTimeProblem& P, const py::array& q) {
             const VecX v = as_matrix<1>(q, "q", P.num_residuals());
             py::gil_scoped_release r;
             return P.vjp(v);
           },
           py::arg("q"), "J^T q at the last linearisation.")
      .def("solve_linear",
           [](const SpaceTimeProblem& P, const std::string& solver, int cg_iterations,
              double cg_tolerance) {
             spacetime::SolveOptions o;
             o.solver = solver;
             o.cg_iterations = cg_iterations;
             o.cg_tolerance = cg_tolerance;
             int it = 0;
             VecX dz;
             {
               py::gil_scoped_release r;
               dz = P.solve_linear(o, &it);
             }
             return py::make_tuple(dz, it);
           },
           py::arg("solver") = "pcgls", py::arg("cg_iterations") = 300,
           py::arg("cg_tolerance") = 1e-6,
           "One Gauss-Newton step: argmin |J dz + C| at the last linearisation; (dz, iterations).")
      .def("solve",
           [](SpaceTimeProblem& P, const py::array& Z0, int max_iterations, int cg_iterations,
              double cg_tolerance, double tolerance, const std::string& solver, py::object progress,
              int jacobian_every) {
             MatXr z = as_rowmajor(Z0, "Z0", P.modes(), P.frames());
             spacetime::SolveOptions o;
             o.max_iterations = max_iterations;
             o.cg_iterations = cg_iterations;
             o.cg_tolerance = cg_tolerance;
             o.tolerance = tolerance;
             o.solver = solver;
             o.jacobian_every = jacobian_every;
             spacetime::ProgressFn cb = [progress](int done, int total) {
               py::gil_scoped_acquire gil;
               if (PyErr_CheckSignals() != 0) throw py::error_already_set();
               if (!progress.is_none()) progress(done, total);
             };
             spacetime::SolveReport rep;
             {
               py::gil_scoped_release r;
               rep = P.solve(z, o, cb);
             }
             py::dict d;
             d["Z"] = py::array_t<double>({long(z.rows()), long(z.cols())}, z.data());
             d["cost"] = rep.cost;
             d["physics_cost"] = rep.physics_cost;
             d["cg_iterations"] = rep.cg_iterations;
             d["step_length"] = rep.step_length;
             return d;
           },
           py::arg("Z0"), py::arg("max_iterations") = 10, py::arg("cg_iterations") = 300,
           py::arg("cg_tolerance") = 1e-6, py::arg("tolerance") = 1e-5, py::arg("solver") = "pcgls",
           py::arg("progress") = py::none(), py::arg("jacobian_every") = 1,
           "Gauss-Newton from Z0; returns dict(Z, cost, physics_cost, cg_iterations, step_length). "
           "jacobian_every k > 1: the Jacobian blocks are re-evaluated at every k-th step and after "
           "a shortened step only (chord steps in between).")
      .def("control_forces",
           [](const SpaceTimeProblem& P, const py::array& Z) {
             const MatXr z = as_rowmajor(Z, "Z", P.modes(), P.frames());
             MatX3 F;
             {
               py::gil_scoped_release r;
               F = P.control_forces(z);
             }
             return to_frames(F, F.rows() / (P.frames() - 2));
           },
           py::arg("Z"),
           "Control forces (frames-2, #V, 3) for frames 2..N (N); zero on constrained vertices.");
}

}  // namespace matlearn::bindings
