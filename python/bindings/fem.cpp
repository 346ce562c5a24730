#include "common.hpp"
#include "fem/material.hpp"
#include "fem/model.hpp"
#include "fem/sparse_assembler.hpp"
#include "fem/svd.hpp"
#include "fem/tet_mesh.hpp"

namespace matlearn::bindings {

using fem::Model;
using fem::TetMesh;

static std::vector<fem::StretchEdit> to_edits(const std::vector<std::tuple<double, double, double>>& e) {
  std::vector<fem::StretchEdit> out;
  for (auto& [a, c, w] : e) out.push_back({a, c, w});
  return out;
}

static py::array_t<double> mats_to_numpy(const std::vector<Mat12>& M) {
  py::array_t<double> out({long(M.size()), 12L, 12L});
  auto o = out.mutable_unchecked<3>();
  for (size_t e = 0; e < M.size(); ++e)
    for (int i = 0; i < 12; ++i)
      for (int j = 0; j < 12; ++j) o(e, i, j) = M[e](i, j);
  return out;
}

void define_fem(py::module_& m) {
  py::class_<TetMesh, std::shared_ptr<TetMesh>>(m, "TetMesh")
      .def(py::init([](const py::array& V, const py::array& T) {
             return std::make_shared<TetMesh>(as_matrix<3>(V, "vertices"), as_index<4>(T, "tets"));
           }),
           py::arg("vertices"), py::arg("tets"))
      .def_property_readonly("vertices", &TetMesh::vertices)
      .def_property_readonly("tets", &TetMesh::tets)
      .def_property_readonly("rest_volumes", &TetMesh::volumes)
      .def_property_readonly("surface_faces", &TetMesh::surface_faces)
      .def_property_readonly("num_vertices", &TetMesh::num_vertices)
      .def_property_readonly("num_tets", &TetMesh::num_tets)
      .def_property_readonly("Bm",
                             [](const TetMesh& M) {
                               py::array_t<double> out({long(M.num_tets()), 3L, 3L});
                               auto o = out.mutable_unchecked<3>();
                               for (int e = 0; e < M.num_tets(); ++e)
                                 for (int i = 0; i < 3; ++i)
                                   for (int j = 0; j < 3; ++j) o(e, i, j) = M.Bm()[e](i, j);
                               return out;
                             })
      .def("lumped_mass",
           [](const TetMesh& M, const py::array& density) {
             return M.lumped_mass(as_matrix<1>(density, "density", M.num_tets()));
           },
           py::arg("density"), "Lumped vertex masses (kg) for per-tet density (kg/m^3).");

  auto batch = [](const char* name, auto fn) { return std::make_pair(name, fn); };
  (void)batch;
  m.def("principal_energy",
        [](const std::string& model, const py::array& s, const py::array& mu, const py::array& lam,
           const std::vector<std::tuple<double, double, double>>& edits) {
          const MatX3 S = as_matrix<3>(s, "stretches");
          const VecX Mu = as_matrix<1>(mu, "mu", S.rows()), L = as_matrix<1>(lam, "lam", S.rows());
          const auto mm = fem::material_model_from_string(model);
          const auto ed = to_edits(edits);
          VecX out(S.rows());
          for (int i = 0; i < S.rows(); ++i)
            out[i] = fem::principal_energy(mm, S.row(i).transpose(), Mu[i], L[i], ed);
          return out;
        },
        py::arg("model"), py::arg("stretches"), py::arg("mu"), py::arg("lam"),
        py::arg("edits") = std::vector<std::tuple<double, double, double>>{},
        "Energy density (J/m^3) for principal stretches (k,3).");
  m.def("principal_stress",
        [](const std::string& model, const py::array& s, const py::array& mu, const py::array& lam,
           const std::vector<std::tuple<double, double, double>>& edits) {
          const MatX3 S = as_matrix<3>(s, "stretches");
          const VecX Mu = as_matrix<1>(mu, "mu", S.rows()), L = as_matrix<1>(lam, "lam", S.rows());
          const auto mm = fem::material_model_from_string(model);
          const auto ed = to_edits(edits);
          MatX3 out(S.rows(), 3);
          for (int i = 0; i < S.rows(); ++i)
            out.row(i) = fem::principal_stress(mm, S.row(i).transpose(), Mu[i], L[i], ed).transpose();
          return out;
        },
        py::arg("model"), py::arg("stretches"), py::arg("mu"), py::arg("lam"),
        py::arg("edits") = std::vector<std::tuple<double, double, double>>{},
        "Principal first Piola stress (Pa), (k,3).");
  m.def("principal_stress_derivative",
        [](const std::string& model, const py::array& s, const py::array& mu, const py::array& lam,
           const std::vector<std::tuple<double, double, double>>& edits) {
          const MatX3 S = as_matrix<3>(s, "stretches");
          const VecX Mu = as_matrix<1>(mu, "mu", S.rows()), L = as_matrix<1>(lam, "lam", S.rows());
          const auto mm = fem::material_model_from_string(model);
          const auto ed = to_edits(edits);
          py::array_t<double> out({long(S.rows()), 3L, 3L});
          auto o = out.mutable_unchecked<3>();
          for (int k = 0; k < S.rows(); ++k) {
            const Mat3 H = fem::principal_stress_derivative(mm, S.row(k).transpose(), Mu[k], L[k], ed);
            for (int i = 0; i < 3; ++i)
              for (int j = 0; j < 3; ++j) o(k, i, j) = H(i, j);
          }
          return out;
        },
        py::arg("model"), py::arg("stretches"), py::arg("mu"), py::arg("lam"),
        py::arg("edits") = std::vector<std::tuple<double, double, double>>{});
  m.def("rotation_variant_svd", [](const Mat3& F) {
    Mat3 U, V;
    Vec3 s;
    fem::rotation_variant_svd(F, U, s, V);
    return py::make_tuple(U, s, V);
  });

  py::class_<Model, std::shared_ptr<Model>>(m, "Model")
      .def(py::init([](std::shared_ptr<const TetMesh> mesh, const std::string& material,
                       const py::array& mu, const py::array& lam, const py::array& density,
                       const std::vector<std::tuple<double, double, double>>& edits,
                       double alpha_mass, double alpha_stiffness, std::vector<double> mass_poly,
                       std::vector<double> stiffness_poly) {
             const long nt = mesh->num_tets();
             fem::DampingParams d{alpha_mass, alpha_stiffness, mass_poly, stiffness_poly};
             return std::make_shared<Model>(
                 mesh, fem::material_model_from_string(material), as_matrix<1>(mu, "mu", nt),
                 as_matrix<1>(lam, "lam", nt), as_matrix<1>(density, "density", nt), to_edits(edits), d);
           }),
           py::arg("mesh"), py::arg("material"), py::arg("mu"), py::arg("lam"), py::arg("density"),
           py::arg("edits") = std::vector<std::tuple<double, double, double>>{},
           py::arg("alpha_mass") = 0.0, py::arg("alpha_stiffness") = 0.0,
           py::arg("mass_poly") = std::vector<double>{},
           py::arg("stiffness_poly") = std::vector<double>{})
      .def_property_readonly("mesh", &Model::mesh_ptr)
      .def_property_readonly("material", [](const Model& M) { return fem::to_string(M.material()); })
      .def_property_readonly("mu", &Model::mu)
      .def_property_readonly("lam", &Model::lambda)
      .def_property_readonly("density", &Model::density)
      .def_property_readonly("vertex_mass", &Model::vertex_mass)
      .def_property("correction", &Model::correction,
                    [](Model& M, std::shared_ptr<const correction::Correction> c) {
                      M.set_correction(std::move(c));
                    })
      .def("forces",
           [](const Model& M, const py::array& x, const py::array& v) {
             const long n = M.mesh().num_vertices();
             const MatX3 X = as_matrix<3>(x, "x", n), Vv = as_matrix<3>(v, "v", n);
             py::gil_scoped_release r;
             VecX f = M.forces(X, Vv);
             return MatX3(Eigen::Map<MatX3>(f.data(), n, 3));
           },
           py::arg("x"), py::arg("v"), "Internal elastic + damping force (N), (#V,3).")
      .def("element_state",
           [](const Model& M, const py::array& x, const py::array& v, bool project_psd) {
             const long n = M.mesh().num_vertices();
             const MatX3 X = as_matrix<3>(x, "x", n), Vv = as_matrix<3>(v, "v", n);
             fem::ElementState st;
             {
               py::gil_scoped_release r;
               M.evaluate(X, Vv, fem::kForce | fem::kStiffness | fem::kDamping, project_psd, st);
             }
             py::dict d;
             d["Fh"] = st.Fh;
             d["Fhdot"] = st.Fhdot;
             d["Ph"] = st.Ph;
             d["dPh_correction"] = st.dPh_corr;
             d["alpha_K"] = st.alpha_K;
             d["alpha_M"] = st.alpha_M;
             d["K"] = mats_to_numpy(st.K);
             d["D"] = mats_to_numpy(st.D);
             return d;
           },
           py::arg("x"), py::arg("v"), py::arg("project_psd") = true,
           "Per-element principal stretches, rates, stresses, damping coefficients, 12x12 "
           "element stiffness K and damping D.")
      .def("principal_kinematics",
           [](const Model& M, const py::array& x, const py::array& v) {
             const long n = M.mesh().num_vertices();
             const MatX3 X = as_matrix<3>(x, "x", n), Vv = as_matrix<3>(v, "v", n);
             fem::ElementState st;
             {
               py::gil_scoped_release r;
               M.evaluate(X, Vv, 0, true, st);
             }
             return py::make_tuple(st.Fh, st.Fhdot, st.Ph, st.alpha_K);
           },
           py::arg("x"), py::arg("v"),
           "(Fh (#T,3), Fhdot (#T,3) 1/s, total Ph (#T,3) Pa, alpha_K (#T,) s).")
      .def("stiffness",
           [](const Model& M, const py::array& x, const py::array& v, bool project_psd) {
             const long n = M.mesh().num_vertices();
             const MatX3 X = as_matrix<3>(x, "x", n), Vv = as_matrix<3>(v, "v", n);
             py::gil_scoped_release r;
             return M.stiffness_matrix(X, Vv, project_psd);
           },
           py::arg("x"), py::arg("v"), py::arg("project_psd") = false,
           "Tangent stiffness K = -df/dx (3#V x 3#V, scipy CSC).")
      .def("damping_matrix",
           [](const Model& M, const py::array& x, const py::array& v) {
             const long n = M.mesh().num_vertices();
             const MatX3 X = as_matrix<3>(x, "x", n), Vv = as_matrix<3>(v, "v", n);
             py::gil_scoped_release r;
             return M.damping_matrix(X, Vv);
           },
           py::arg("x"), py::arg("v"), "Damping matrix D = -df/dv (3#V x 3#V, scipy CSC).")
      .def("reduced_tangents",
           [](const Model& M, const py::array& x, const py::array& phi) {
             const long n = M.mesh().num_vertices();
             const MatX3 X = as_matrix<3>(x, "x", n);
             auto P = py::array_t<double, py::array::f_style | py::array::forcecast>::ensure(phi);
             if (!P || P.ndim() != 2 || P.shape(0) != 3 * n)
               throw InvalidInput("phi: expected shape (3*#V, r) with #V = " + std::to_string(n));
             const MatX Phi = Eigen::Map<const MatX>(P.data(), P.shape(0), P.shape(1));
             MatX Kr, Dr;
             {
               py::gil_scoped_release r;
               M.reduced_tangents(X, Phi, Kr, Dr);
             }
             return py::make_tuple(Kr, Dr);
           },
           py::arg("x"), py::arg("phi"),
           "(Phi^T K Phi, Phi^T D Phi) of the model without its correction: K unprojected, D "
           "Rayleigh on the PSD-projected tangent (what the space-time Jacobian uses).")
      .def("force_map",
           [](const Model& M, const py::array& x) {
             const MatX3 X = as_matrix<3>(x, "x", M.mesh().num_vertices());
             py::gil_scoped_release r;
             return M.force_map(X);
           },
           py::arg("x"), "B (3#V x 3#T): elastic vertex forces = B @ principal stresses.")
      .def("stiffness_damping_map",
           [](const Model& M, const py::array& x, const py::array& v) {
             const long n = M.mesh().num_vertices();
             const MatX3 X = as_matrix<3>(x, "x", n), Vv = as_matrix<3>(v, "v", n);
             py::gil_scoped_release r;
             return M.stiffness_damping_map(X, Vv);
           },
           py::arg("x"), py::arg("v"), "(3#V x #T): column e = -K_e v_e (nominal tangent).")
      .def("mass_damping_map",
           [](const Model& M, const py::array& v) {
             const MatX3 Vv = as_matrix<3>(v, "v", M.mesh().num_vertices());
             return M.mass_damping_map(Vv);
           },
           py::arg("v"), "(3#V x #T): column e = -M_e v_e.");
}

}  // namespace matlearn::bindings
