#include "common.hpp"
#include "fem/model.hpp"
#include "learning/fit_normal_equations.hpp"

namespace matlearn::bindings {

/// (frames, #V, 3) numpy -> stacked (frames*#V x 3).
static MatX3 as_stacked(const py::array& a, const char* name, long n) {
  auto arr = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(a);
  if (!arr || arr.ndim() != 3 || arr.shape(1) != n || arr.shape(2) != 3 || arr.shape(0) < 1)
    throw InvalidInput(std::string(name) + ": expected shape (frames, " + std::to_string(n) + ", 3)");
  MatX3 M(arr.shape(0) * n, 3);
  std::copy(arr.data(), arr.data() + arr.size(), M.data());
  return M;
}

static learning::RbfFeatures features(const py::array& centers, double epsilon,
                                      const py::object& lower, const py::object& upper) {
  learning::RbfFeatures f;
  f.centers = as_matrix<3>(centers, "centers");
  f.epsilon = epsilon;
  if (!lower.is_none()) f.lower = as_matrix<1>(lower, "lower", 3);
  if (!upper.is_none()) f.upper = as_matrix<1>(upper, "upper", 3);
  return f;
}

void define_fit(py::module_& m) {
  m.def(
      "normal_equations",
      [](std::shared_ptr<const fem::Model> nominal, std::shared_ptr<const fem::Model> current,
         const py::array& X, const py::array& V, const py::array& FC, const py::object& phi,
         const py::object& free_dofs, const py::array& centers, double epsilon,
         const py::object& lower, const py::object& upper, bool damping, bool tangent_damping) {
        if (!nominal) throw InvalidInput("nominal model is None");
        const long n = nominal->mesh().num_vertices();
        const MatX3 x = as_stacked(X, "X", n), v = as_stacked(V, "V", n),
                    fc = as_stacked(FC, "FC", n);
        if (v.rows() != x.rows() || fc.rows() != x.rows())
          throw InvalidInput("X, V and FC must have the same number of frames");
        MatX Phi;
        Eigen::Matrix<bool, Eigen::Dynamic, 1> keep;
        if (!phi.is_none()) {
          auto P = py::array_t<double, py::array::f_style | py::array::forcecast>::ensure(phi);
          if (!P || P.ndim() != 2 || P.shape(0) != 3 * n || P.shape(1) < 1)
            throw InvalidInput("phi: expected shape (3*#V, r) with #V = " + std::to_string(n));
          Phi.resize(P.shape(0), P.shape(1));
          std::copy(P.data(), P.data() + P.size(), Phi.data());
        } else {
          keep.setOnes(3 * n);
          if (!free_dofs.is_none()) {
            auto F = py::array_t<bool, py::array::c_style | py::array::forcecast>::ensure(free_dofs);
            if (!F || F.ndim() != 1 || F.shape(0) != 3 * n)
              throw InvalidInput("free_dofs: expected a boolean array of length 3*#V");
            for (long i = 0; i < 3 * n; ++i) keep[i] = F.data()[i];
          }
        }
        const auto rbf = features(centers, epsilon, lower, upper);
        learning::NormalEquations ne;
        {
          py::gil_scoped_release r;
          ne = learning::fit_normal_equations(*nominal, current.get(), x, v, fc, Phi, keep, rbf,
                                              damping, tangent_damping);
        }
        return py::make_tuple(ne.N, ne.rhs, ne.yy, ne.frames);
      },
      py::arg("nominal"), py::arg("current"), py::arg("X"), py::arg("V"), py::arg("FC"),
      py::arg("phi"), py::arg("free_dofs"), py::arg("centers"), py::arg("epsilon"),
      py::arg("lower") = py::none(), py::arg("upper") = py::none(), py::arg("damping") = true,
      py::arg("tangent_damping") = false,
      "Normal equations (N (p,p), rhs (p,), y^T y, frames) of the correction fit over all frames "
      "of X, V, FC (frames, #V, 3); current: model with the current correction or None; phi "
      "(3#V, r) basis or None (then free_dofs, bool (3#V,), selects rows). See "
      "cpp/learning/fit_normal_equations.hpp for the unknown layout. tangent_damping: the fitted "
      "correction's elastic part also enters the stiffness-proportional damping (the current "
      "model's correction must then have tangent_damping on).");
  m.def(
      "principal_stretches",
      [](std::shared_ptr<const fem::Model> model, const py::array& X) {
        if (!model) throw InvalidInput("model is None");
        const MatX3 x = as_stacked(X, "X", model->mesh().num_vertices());
        py::gil_scoped_release r;
        return learning::principal_stretches(*model, x);
      },
      py::arg("model"), py::arg("X"),
      "Principal stretches (frames*#T, 3) of all frames X (frames, #V, 3), frame-major.");
}

}  // namespace matlearn::bindings
