#pragma once
#include <pybind11/eigen.h>
#include <pybind11/functional.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "common/types.hpp"

namespace py = pybind11;

namespace matlearn::bindings {

void define_fem(py::module_& m);
void define_correction(py::module_& m);
void define_time(py::module_& m);
void define_mesh(py::module_& m);
void define_observation(py::module_& m);
void define_spacetime(py::module_& m);
void define_fit(py::module_& m);
void define_replay(py::module_& m);

/// Check a numpy array is (rows x cols) (rows < 0: any) and convert to a row-major double matrix.
template <int C>
Eigen::Matrix<double, Eigen::Dynamic, C, C == 1 ? Eigen::ColMajor : Eigen::RowMajor> as_matrix(
    const py::array& a, const char* name, long rows = -1) {
  auto arr = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(a);
  if (!arr) throw InvalidInput(std::string(name) + ": expected a float array");
  const bool ok = (C == 1 ? arr.ndim() == 1 : (arr.ndim() == 2 && arr.shape(1) == C)) &&
                  (rows < 0 || arr.shape(0) == rows);
  if (!ok) {
    std::string got = "(";
    for (int i = 0; i < arr.ndim(); ++i) got += (i ? ", " : "") + std::to_string(arr.shape(i));
    got += ")";
    std::string want = "(" + (rows < 0 ? std::string("N") : std::to_string(rows)) +
                       (C == 1 ? ")" : ", " + std::to_string(C) + ")");
    throw InvalidInput(std::string(name) + ": expected shape " + want + ", got " + got);
  }
  Eigen::Matrix<double, Eigen::Dynamic, C, C == 1 ? Eigen::ColMajor : Eigen::RowMajor> M(
      arr.shape(0), C);
  std::copy(arr.data(), arr.data() + arr.size(), M.data());
  return M;
}

/// Integer index arrays (any int dtype) -> Eigen, with a shape check.
template <int C>
Eigen::Matrix<int, Eigen::Dynamic, C, C == 1 ? Eigen::ColMajor : Eigen::RowMajor> as_index(
    const py::array& a, const char* name) {
  if (!py::isinstance<py::array>(a) || (a.dtype().kind() != 'i' && a.dtype().kind() != 'u' && a.size() > 0))
    throw InvalidInput(std::string(name) + ": expected an integer array");
  auto arr = py::array_t<long long, py::array::c_style | py::array::forcecast>::ensure(a);
  const bool ok = C == 1 ? arr.ndim() == 1 : (arr.ndim() == 2 && arr.shape(1) == C);
  if (!ok) throw InvalidInput(std::string(name) + ": expected shape (N" +
                              (C == 1 ? std::string(")") : ", " + std::to_string(C) + ")"));
  Eigen::Matrix<int, Eigen::Dynamic, C, C == 1 ? Eigen::ColMajor : Eigen::RowMajor> M(arr.shape(0), C);
  for (long i = 0; i < arr.size(); ++i) M.data()[i] = static_cast<int>(arr.data()[i]);
  return M;
}

/// Stacked (frames*n x 3) -> numpy (frames, n, 3).
inline py::array_t<double> to_frames(const MatX3& stacked, long n) {
  const long frames = stacked.rows() / n;
  py::array_t<double> out({frames, n, 3L});
  std::copy(stacked.data(), stacked.data() + stacked.size(), out.mutable_data());
  return out;
}

}  // namespace matlearn::bindings
