#include "common.hpp"
#include "correction/correction.hpp"

namespace matlearn::bindings {

using correction::Correction;
using correction::CorrectionOutput;

/// A correction computed by a Python function fn(Fh (m,3), Fhdot (m,3)) returning
/// (dPh (m,3), d_dFh (m,3,3), d_dFhdot (m,3,3) or None, dalpha (m,) or None). For tests.
class PythonCorrection final : public Correction {
 public:
  explicit PythonCorrection(py::function fn) : fn_(std::move(fn)) {}
  ~PythonCorrection() override {
    py::gil_scoped_acquire gil;
    fn_ = py::function();
  }
  bool thread_safe() const override { return false; }
  void evaluate(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const override {
    py::gil_scoped_acquire gil;
    const long m = Fh.rows();
    py::tuple r = fn_(Fh, Fhdot);
    if (r.size() != 4) throw InvalidInput("python correction must return a 4-tuple");
    out.dPh = as_matrix<3>(r[0], "correction dPh", m);
    auto jac = [&](py::handle h, std::vector<Mat3>& J, const char* name) {
      J.assign(m, Mat3::Zero());
      if (h.is_none()) return;
      auto a = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(h);
      if (!a || a.ndim() != 3 || a.shape(0) != m || a.shape(1) != 3 || a.shape(2) != 3)
        throw InvalidInput(std::string(name) + ": expected shape (m, 3, 3)");
      for (long e = 0; e < m; ++e)
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) J[e](i, j) = a.at(e, i, j);
    };
    jac(r[1], out.d_dFh, "correction d_dFh");
    jac(r[2], out.d_dFhdot, "correction d_dFhdot");
    out.dalpha = r[3].is_none() ? VecX::Zero(m) : VecX(as_matrix<1>(r[3], "correction dalpha", m));
  }

 private:
  py::function fn_;
};

/// Fh and Fhdot checked as (m, 3) arrays, then evaluate (values_only: evaluate_values).
static CorrectionOutput evaluate_checked(const Correction& c, const py::array& Fh, const py::array& Fhdot,
                                         bool values_only) {
  const MatX3 a = as_matrix<3>(Fh, "Fh");
  const MatX3 b = as_matrix<3>(Fhdot, "Fhdot", a.rows());
  CorrectionOutput out;
  if (values_only)
    c.evaluate_values(a, b, out);
  else
    c.evaluate(a, b, out);
  return out;
}

void define_correction(py::module_& m) {
  py::class_<Correction, std::shared_ptr<Correction>>(m, "Correction")
      .def_property("tangent_damping", &Correction::tangent_damping, &Correction::set_tangent_damping,
                    "When True, the Model's stiffness-proportional Rayleigh damping acts on the "
                    "corrected tangent (nominal + this correction, projected to PSD) instead of the "
                    "nominal one. Default False.")
      .def(
          "evaluate",
          [](const Correction& c, const py::array& Fh, const py::array& Fhdot) {
            const CorrectionOutput out = evaluate_checked(c, Fh, Fhdot, false);
            const long n = out.dPh.rows();
            py::array_t<double> J({n, 3L, 3L}), Jd({n, 3L, 3L});
            auto Ju = J.mutable_unchecked<3>();  // shapes fixed just above
            auto Jdu = Jd.mutable_unchecked<3>();
            for (long e = 0; e < n; ++e)
              for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j) {
                  Ju(e, i, j) = out.d_dFh[e](i, j);
                  Jdu(e, i, j) = out.d_dFhdot[e](i, j);
                }
            return py::make_tuple(out.dPh, J, Jd, out.dalpha);
          },
          py::arg("Fh"), py::arg("Fhdot"),
          "Evaluate for m elements: returns (dPh (m,3) Pa, d/dFh (m,3,3), d/dFhdot (m,3,3), "
          "dalpha_K (m,) s).")
      .def(
          "evaluate_values",
          [](const Correction& c, const py::array& Fh, const py::array& Fhdot) {
            const CorrectionOutput out = evaluate_checked(c, Fh, Fhdot, true);
            return py::make_tuple(out.dPh, out.dalpha);
          },
          py::arg("Fh"), py::arg("Fhdot"),
          "Values only, as the force-only Model evaluation uses them: (dPh (m,3) Pa, dalpha_K (m,) "
          "s), equal to the first and last outputs of evaluate (the RBF skips its kernel gradients).");

  py::class_<correction::RbfCorrection, Correction, std::shared_ptr<correction::RbfCorrection>>(
      m, "RbfCorrection")
      .def(py::init([](const py::array& centers, const py::array& weights, const Mat3& linear,
                       const Vec3& bias, const py::array& alpha_weights, double alpha_bias,
                       double epsilon, const py::object& lower, const py::object& upper,
                       double isotropic_width) {
             const MatX3 c = as_matrix<3>(centers, "centers");
             const VecX lo = lower.is_none() ? VecX() : VecX(as_matrix<1>(lower, "lower"));
             const VecX hi = upper.is_none() ? VecX() : VecX(as_matrix<1>(upper, "upper"));
             return std::make_shared<correction::RbfCorrection>(
                 c, as_matrix<3>(weights, "weights", c.rows()), linear, bias,
                 as_matrix<1>(alpha_weights, "alpha_weights"), alpha_bias, epsilon, lo, hi,
                 isotropic_width);
           }),
           py::arg("centers"), py::arg("weights"), py::arg("linear"), py::arg("bias"),
           py::arg("alpha_weights"), py::arg("alpha_bias"), py::arg("epsilon"),
           py::arg("lower") = py::none(), py::arg("upper") = py::none(),
           py::arg("isotropic_width") = 0.0,
           "lower, upper: optional (3,) box the kernels clamp the stretches to (None: no clamp). "
           "isotropic_width (stretch units): dPh blended to be equal at coincident principal "
           "stretches as MlpCorrection's (a fitted RBF is not exactly isotropic), unchanged where "
           "every gap is >= the width; < 0: 0.1 x the mean per-axis std of the centres; 0 "
           "(default): off, the raw RBF.")
      .def_property_readonly("isotropic_width", &correction::RbfCorrection::isotropic_width);

  py::class_<correction::MlpCorrection, Correction, std::shared_ptr<correction::MlpCorrection>>(
      m, "MlpCorrection")
      .def(py::init([](const std::vector<std::pair<MatX, VecX>>& layers, const VecX& in_mean,
                       const VecX& in_std, const VecX& out_mean, const VecX& out_std,
                       double isotropic_width) {
             std::vector<correction::DenseLayer> L;
             for (auto& [W, b] : layers) L.push_back({W, b});
             return std::make_shared<correction::MlpCorrection>(L, in_mean, in_std, out_mean, out_std,
                                                                isotropic_width);
           }),
           py::arg("layers"), py::arg("in_mean"), py::arg("in_std"), py::arg("out_mean"),
           py::arg("out_std"), py::arg("isotropic_width") = -1.0,
           "layers: list of (W (out x in), b (out)); ELU between layers; 6 inputs (Fh, Fhdot), "
           "3 outputs (dPh, Pa) or 4 (dPh, dalpha_K in s: the change of the element's "
           "stiffness-damping coefficient, clamped like the RBF's so alpha_K stays >= 0); "
           "out_mean/out_std have one entry per output. isotropic_width (stretch units): the "
           "stress outputs are blended to be equal at coincident principal stretches (a network "
           "is not exactly isotropic; without this the stress jumps there and Newton cycles), "
           "unchanged where every gap is >= the width; < 0: 0.1 x the mean stretch input std, 0: "
           "the raw network.")
      .def_property_readonly("isotropic_width", &correction::MlpCorrection::isotropic_width);

  py::class_<PythonCorrection, Correction, std::shared_ptr<PythonCorrection>>(m, "PythonCorrection")
      .def(py::init<py::function>(), py::arg("fn"));
}

}  // namespace matlearn::bindings
