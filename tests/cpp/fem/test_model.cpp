// Assembled operators of a Model: directional finite differences of the internal force against
// the stiffness (K = -df/dx) and of the damping force against D = -df/dv, symmetry of K, rigid
// motions in the null space at rest, zero net force and torque, and mass sums.
#include <random>

#include "check.hpp"
#include "fem/model.hpp"
#include "fem/sparse_assembler.hpp"
#include "fixtures.hpp"

using namespace matlearn;
using namespace matlearn::fem;

namespace {

const double kL = 0.2, kW = 0.04, kRho = 1100.0;

std::shared_ptr<Model> make_model(MaterialModel m, DampingParams d = {},
                                  std::vector<StretchEdit> edits = {}) {
  auto mesh = mltest::grid_mesh(4, 2, 2, kL, kW, kW);
  const int nt = mesh->num_tets();
  // Heterogeneous parameters so per-element indexing is exercised.
  VecX mu(nt), lam(nt);
  for (int e = 0; e < nt; ++e) {
    mu[e] = 3e4 * (1.0 + 0.5 * (e % 3));
    lam[e] = 1e5 * (1.0 + 0.25 * (e % 2));
  }
  return std::make_shared<Model>(mesh, m, mu, lam, VecX::Constant(nt, kRho), edits, d);
}

SpMat assemble(const Model& M, const std::vector<Mat12>& blocks) {
  const int n = 3 * M.mesh().num_vertices();
  SparseAssembler a(M.mesh().tets(), VecXi::LinSpaced(n, 0, n - 1), n, false);
  SpMat out;
  a.assemble(blocks, 1.0, {}, 0.0, VecX(), 0.0, out);
  return out;
}

MatX3 deformed(const Model& M, unsigned seed, double amp) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  MatX3 x = M.mesh().vertices();
  // A smooth bend-and-stretch plus noise: large enough to leave the linear regime.
  for (int i = 0; i < x.rows(); ++i) {
    const double t = x(i, 0) / kL;
    x(i, 0) *= 1.1;
    x(i, 2) += 0.3 * kL * t * t;
    for (int k = 0; k < 3; ++k) x(i, k) += amp * kW * u(rng);
  }
  return x;
}

const char* name(MaterialModel m) {
  static std::string s;
  s = to_string(m);
  return s.c_str();
}

}  // namespace

TEST_CASE(force_directional_derivative_matches_stiffness) {
  for (auto mm : {MaterialModel::Corotated, MaterialModel::NeoHookean, MaterialModel::StVK,
                  MaterialModel::Designed}) {
    auto M = make_model(mm, {}, mm == MaterialModel::Designed
                                    ? std::vector<StretchEdit>{{2e4, 1.25, 0.2}, {-1e4, 0.75, 0.2}}
                                    : std::vector<StretchEdit>{});
    const MatX3 x = deformed(*M, 1, 0.05), v = MatX3::Zero(x.rows(), 3);
    ElementState st;
    M->evaluate(x, v, kStiffness, false, st);
    const SpMat K = assemble(*M, st.K);
    std::mt19937 rng(2);
    std::normal_distribution<double> n(0, 1);
    for (int trial = 0; trial < 3; ++trial) {
      MatX3 d(x.rows(), 3);
      for (int i = 0; i < d.size(); ++i) d.data()[i] = n(rng);
      const double h = 1e-7;
      const VecX fd = (M->forces(x + h * d, v) - M->forces(x - h * d, v)) / (2 * h);
      const VecX Kd = -(K * as_dofs(d));
      const double scale = Kd.cwiseAbs().maxCoeff();
      for (int i = 0; i < fd.size(); ++i)
        CHECK_CLOSE(Kd[i] / scale, fd[i] / scale, 1e-5, std::string(name(mm)) + " dof " + std::to_string(i));
    }
    // Hyperelastic: the exact tangent is symmetric.
    const SpMat asym = K - SpMat(K.transpose());
    CHECK_MSG(asym.norm() <= 1e-10 * K.norm(), std::string(name(mm)) + ": K not symmetric");
  }
}

TEST_CASE(damping_matrix_is_velocity_derivative_of_force) {
  DampingParams d;
  d.alpha_mass = 0.7;
  d.alpha_stiffness = 0.02;
  auto M = make_model(MaterialModel::NeoHookean, d);
  const MatX3 x = deformed(*M, 4, 0.03);
  std::mt19937 rng(9);
  std::normal_distribution<double> n(0, 1);
  MatX3 v(x.rows(), 3), dv(x.rows(), 3);
  for (int i = 0; i < v.size(); ++i) {
    v.data()[i] = 0.1 * n(rng);
    dv.data()[i] = n(rng);
  }
  ElementState st;
  M->evaluate(x, v, kDamping, true, st);
  const SpMat D = assemble(*M, st.D);
  const double h = 1e-4;  // the damping force is linear in v: FD is exact up to round-off
  const VecX fd = (M->forces(x, v + h * dv) - M->forces(x, v - h * dv)) / (2 * h);
  const VecX Dd = -(D * as_dofs(dv));
  const double scale = Dd.cwiseAbs().maxCoeff();
  for (int i = 0; i < fd.size(); ++i) CHECK_CLOSE(Dd[i] / scale, fd[i] / scale, 1e-7, "dof " + std::to_string(i));
  // D is symmetric positive semi-definite (Rayleigh on the projected tangent).
  CHECK(SpMat(D - SpMat(D.transpose())).norm() <= 1e-10 * D.norm());
}

TEST_CASE(rigid_motions_are_in_the_null_space_at_rest) {
  for (auto mm : {MaterialModel::Corotated, MaterialModel::NeoHookean, MaterialModel::StVK}) {
    auto M = make_model(mm);
    const MatX3& X = M->mesh().vertices();
    const MatX3 v = MatX3::Zero(X.rows(), 3);
    for (bool psd : {false, true}) {
      ElementState st;
      M->evaluate(X, v, kStiffness | kForce, psd, st);
      const SpMat K = assemble(*M, st.K);
      const VecX f0 = M->gather_forces(st);
      CHECK_MSG(f0.cwiseAbs().maxCoeff() < 1e-9, std::string(name(mm)) + ": force at rest != 0");
      const double kscale = K.coeffs().cwiseAbs().maxCoeff();
      for (int k = 0; k < 6; ++k) {
        MatX3 r = MatX3::Zero(X.rows(), 3);
        for (int i = 0; i < X.rows(); ++i) {
          if (k < 3)
            r(i, k) = 1.0;  // translation
          else
            r.row(i) = Vec3::Unit(k - 3).cross(Vec3(X.row(i).transpose())).transpose();  // rotation
        }
        const VecX Kr = K * as_dofs(r);
        CHECK_MSG(Kr.cwiseAbs().maxCoeff() <= 1e-9 * kscale,
                  std::string(name(mm)) + ": rigid mode " + std::to_string(k) + " not in null space");
      }
    }
  }
}

TEST_CASE(internal_forces_have_no_net_force_or_torque) {
  // Elastic forces of an isotropic law are internal: P F^T is symmetric, so they balance in
  // force and torque. (Rayleigh damping forces are not torque-free in general, so none here.)
  auto M = make_model(MaterialModel::NeoHookean);
  const MatX3 x = deformed(*M, 6, 0.05);
  std::mt19937 rng(12);
  std::normal_distribution<double> n(0, 0.1);
  MatX3 v(x.rows(), 3);
  for (int i = 0; i < v.size(); ++i) v.data()[i] = n(rng);
  const VecX f = M->forces(x, v);
  Vec3 F = Vec3::Zero(), T = Vec3::Zero();
  for (int i = 0; i < x.rows(); ++i) {
    F += f.segment<3>(3 * i);
    T += Vec3(x.row(i).transpose()).cross(Vec3(f.segment<3>(3 * i)));
  }
  const double scale = f.cwiseAbs().maxCoeff() * x.rows();
  CHECK(scale > 0);
  CHECK_MSG(F.norm() <= 1e-12 * scale, "net force " + std::to_string(F.norm()));
  CHECK_MSG(T.norm() <= 1e-12 * scale * kL, "net torque " + std::to_string(T.norm()));
}

TEST_CASE(masses_and_volumes_sum_to_the_body) {
  auto M = make_model(MaterialModel::Corotated);
  const double vol = kL * kW * kW;
  CHECK_CLOSE(M->mesh().volumes().sum(), vol, 1e-12, "total volume");
  CHECK_CLOSE(M->vertex_mass().sum(), kRho * vol, 1e-12, "total mass");
  CHECK_CLOSE(M->dof_mass().sum(), 3 * kRho * vol, 1e-12, "dof mass");
  CHECK((M->vertex_mass().array() > 0).all());
  // Each element's lumped mass is rho W / 4 per corner: rebuild from volumes.
  VecX m = VecX::Zero(M->mesh().num_vertices());
  for (int e = 0; e < M->mesh().num_tets(); ++e)
    for (int a = 0; a < 4; ++a) m[M->mesh().tets()(e, a)] += kRho * M->mesh().volumes()[e] / 4;
  for (int i = 0; i < m.size(); ++i) CHECK_CLOSE(M->vertex_mass()[i], m[i], 1e-12, "vertex " + std::to_string(i));
}

TEST_CASE(force_map_reproduces_elastic_forces) {
  auto M = make_model(MaterialModel::StVK);
  const MatX3 x = deformed(*M, 8, 0.05), v = MatX3::Zero(x.rows(), 3);
  ElementState st;
  M->evaluate(x, v, kForce, true, st);
  const SpMat B = M->force_map(x);
  const VecX ph = Eigen::Map<const VecX>(st.Ph.data(), st.Ph.size());
  const VecX f = B * ph, g = M->gather_forces(st);
  const double scale = g.cwiseAbs().maxCoeff();
  for (int i = 0; i < f.size(); ++i) CHECK_CLOSE(f[i] / scale, g[i] / scale, 1e-12, "dof " + std::to_string(i));
}

TEST_CASE(bad_model_inputs_throw) {
  auto mesh = mltest::grid_mesh(1, 1, 1, 1, 1, 1);
  const int nt = mesh->num_tets();
  const VecX one = VecX::Ones(nt);
  CHECK_THROWS(Model(mesh, MaterialModel::Corotated, -one, one, one, {}, {}), InvalidInput);
  CHECK_THROWS(Model(mesh, MaterialModel::Corotated, one, one, VecX::Ones(nt + 1), {}, {}), InvalidInput);
  CHECK_THROWS(Model(mesh, MaterialModel::Designed, one, one, one, {{1.0, 1.1, 0.2}}, {}), InvalidInput);
  Model M(mesh, MaterialModel::Corotated, one, one, one, {}, {});
  MatX3 x = mesh->vertices();
  x(0, 0) = std::nan("");
  CHECK_THROWS(M.forces(x, MatX3::Zero(x.rows(), 3)), InvalidInput);
  CHECK_THROWS(M.forces(MatX3::Zero(3, 3), MatX3::Zero(3, 3)), InvalidInput);
  MatX4i T = mesh->tets();
  std::swap(T(0, 1), T(0, 2));
  CHECK_THROWS(fem::TetMesh(mesh->vertices(), T), InvalidInput);  // inverted
  T = mesh->tets();
  T(0, 3) = 99;
  CHECK_THROWS(fem::TetMesh(mesh->vertices(), T), InvalidInput);  // out of range
}
