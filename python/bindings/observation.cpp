#include "common.hpp"
#include "observation/cloud_observation.hpp"

namespace matlearn::bindings {

namespace ob = matlearn::observation;

void define_observation(py::module_& m) {
  // All functions take S (#K, 3) surface points, C (#N, 3) cloud points and the candidate pairs
  // (pair_point (#P,), pair_cloud (#P,)) indexing into S and C; see cloud_observation.hpp.
  m.def(
      "cloud_weights",
      [](const py::array& S, const py::array& C, const py::array& pk, const py::array& pn,
         double sigma, double threshold) {
        const MatX3 s = as_matrix<3>(S, "S"), c = as_matrix<3>(C, "C");
        const VecXi k = as_index<1>(pk, "pair_point"), n = as_index<1>(pn, "pair_cloud");
        py::gil_scoped_release r;
        return VecX(ob::cloud_weights(s, c, k, n, sigma, threshold));
      },
      py::arg("S"), py::arg("C"), py::arg("pair_point"), py::arg("pair_cloud"), py::arg("sigma"),
      py::arg("threshold") = 0.0,
      "Gaussian correspondence weight of each pair, exp(-|c-s|^2/(2 sigma^2)), 0 below threshold.");
  m.def(
      "cloud_weight_gradients",
      [](const py::array& S, const py::array& C, const py::array& pk, const py::array& pn,
         double sigma, double threshold) {
        const MatX3 s = as_matrix<3>(S, "S"), c = as_matrix<3>(C, "C");
        const VecXi k = as_index<1>(pk, "pair_point"), n = as_index<1>(pn, "pair_cloud");
        py::gil_scoped_release r;
        return MatX3(ob::cloud_weight_gradients(s, c, k, n, sigma, threshold));
      },
      py::arg("S"), py::arg("C"), py::arg("pair_point"), py::arg("pair_cloud"), py::arg("sigma"),
      py::arg("threshold") = 0.0, "d p / d s_k of each pair, (#P, 3).");
  m.def(
      "cloud_residual",
      [](const py::array& S, const py::array& C, const py::array& pk, const py::array& pn,
         double sigma, double threshold) {
        const MatX3 s = as_matrix<3>(S, "S"), c = as_matrix<3>(C, "C");
        const VecXi k = as_index<1>(pk, "pair_point"), n = as_index<1>(pn, "pair_cloud");
        py::gil_scoped_release r;
        return MatX3(ob::cloud_residual(s, c, k, n, sigma, threshold));
      },
      py::arg("S"), py::arg("C"), py::arg("pair_point"), py::arg("pair_cloud"), py::arg("sigma"),
      py::arg("threshold") = 0.0, "r_k = sum_n p_kn (c_n - s_k) / sigma^2, (#K, 3).");
  m.def(
      "cloud_residual_blocks",
      [](const py::array& S, const py::array& C, const py::array& pk, const py::array& pn,
         double sigma, double threshold, bool full) {
        const MatX3 s = as_matrix<3>(S, "S"), c = as_matrix<3>(C, "C");
        const VecXi k = as_index<1>(pk, "pair_point"), n = as_index<1>(pn, "pair_cloud");
        Eigen::Matrix<double, Eigen::Dynamic, 9, Eigen::RowMajor> J;
        {
          py::gil_scoped_release r;
          J = ob::cloud_residual_blocks(s, c, k, n, sigma, threshold, full);
        }
        py::array_t<double> out({static_cast<long>(J.rows()), 3L, 3L});
        std::copy(J.data(), J.data() + J.size(), out.mutable_data());
        return out;
      },
      py::arg("S"), py::arg("C"), py::arg("pair_point"), py::arg("pair_cloud"), py::arg("sigma"),
      py::arg("threshold") = 0.0, py::arg("full") = false,
      "dr_k/ds_k as (#K, 3, 3) blocks; full=False holds the weights fixed (Gauss-Newton/EM).");
  m.def(
      "cloud_targets",
      [](const py::array& S, const py::array& C, const py::array& pk, const py::array& pn,
         double sigma, double threshold) {
        const MatX3 s = as_matrix<3>(S, "S"), c = as_matrix<3>(C, "C");
        const VecXi k = as_index<1>(pk, "pair_point"), n = as_index<1>(pn, "pair_cloud");
        MatX3 mean;
        VecX W;
        {
          py::gil_scoped_release r;
          ob::cloud_targets(s, c, k, n, sigma, threshold, mean, W);
        }
        return py::make_tuple(mean, W);
      },
      py::arg("S"), py::arg("C"), py::arg("pair_point"), py::arg("pair_cloud"), py::arg("sigma"),
      py::arg("threshold") = 0.0,
      "(mean (#K, 3) p-weighted cloud mean, NaN without pairs; W (#K,) total weight).");
}

}  // namespace matlearn::bindings
