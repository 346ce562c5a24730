// Materials in principal stretches: zero stress at rest, stress = dEnergy/ds, tangent =
// dStress/ds by central differences, and the 9x9 dP/dF assembled from principal data against
// finite differences of P(F) = U diag(Ph(s)) V^T, on seeded random, near-repeated and inverted
// states, for every material (the designed one with tension and compression edits).
#include <algorithm>
#include <random>

#include "check.hpp"
#include "fem/material.hpp"
#include "fem/svd.hpp"
#include "fixtures.hpp"

using namespace matlearn;
using namespace matlearn::fem;

namespace {

const double kMu = 3.0e4, kLam = 1.2e5;
const std::vector<StretchEdit> kEdits = {{2.0e4, 1.3, 0.2}, {-1.5e4, 0.7, 0.2}};

struct Case {
  MaterialModel model;
  std::vector<StretchEdit> edits;
  const char* name;
};
std::vector<Case> cases() {
  return {{MaterialModel::Corotated, {}, "corotated"},
          {MaterialModel::NeoHookean, {}, "neo_hookean"},
          {MaterialModel::StVK, {}, "stvk"},
          {MaterialModel::Designed, kEdits, "designed"}};
}

/// ~10 seeded random states plus near-repeated, exactly repeated and inverted stretches.
std::vector<Vec3> states() {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(0.6, 1.5);
  std::vector<Vec3> S;
  for (int i = 0; i < 10; ++i) {
    Vec3 s(u(rng), u(rng), u(rng));
    std::sort(s.data(), s.data() + 3, std::greater<>());
    S.push_back(s);
  }
  S.emplace_back(1.2, 1.2 + 1e-9, 0.9);  // near-repeated (inside the limit branch)
  S.emplace_back(1.2, 1.2 + 1e-5, 0.9);  // near-repeated (outside it)
  S.emplace_back(1.25, 1.25, 1.25);      // exactly repeated, inside the tension edit
  S.emplace_back(1.35, 0.72, 0.72 - 1e-9); // inside both edit bumps, near-repeated
  S.emplace_back(1.1, 0.9, -0.3);        // inverted (neo-Hookean continued log)
  S.emplace_back(1.2, 0.7, -0.05);       // barely inverted
  return S;
}

std::string ctx(const char* name, const Vec3& s, int i, int j = -1) {
  char buf[160];
  std::snprintf(buf, sizeof buf, "%s s=(%.9g, %.9g, %.9g) entry (%d,%d)", name, s[0], s[1], s[2],
                i, j);
  return buf;
}

Mat3 world_stress(const Case& c, const Mat3& F) {
  Mat3 U, V;
  Vec3 s;
  rotation_variant_svd(F, U, s, V);
  return U * principal_stress(c.model, s, kMu, kLam, c.edits).asDiagonal() * V.transpose();
}

}  // namespace

TEST_CASE(zero_stress_and_energy_at_rest) {
  for (const auto& c : cases()) {
    const Vec3 P = principal_stress(c.model, Vec3::Ones(), kMu, kLam, c.edits);
    for (int i = 0; i < 3; ++i) CHECK_CLOSE(P[i], 0.0, 1e-12, ctx(c.name, Vec3::Ones(), i));
    CHECK_CLOSE(principal_energy(c.model, Vec3::Ones(), kMu, kLam, c.edits), 0.0, 1e-12, c.name);
    // Small-strain limit: every law linearises to 2 mu I + lambda 11^T at rest.
    const Mat3 H = principal_stress_derivative(c.model, Vec3::Ones(), kMu, kLam, c.edits);
    const Mat3 lin = 2 * kMu * Mat3::Identity() + kLam * Mat3::Ones();
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) CHECK_CLOSE(H(i, j), lin(i, j), 1e-9, ctx(c.name, Vec3::Ones(), i, j));
  }
}

TEST_CASE(stress_is_energy_gradient) {
  const double h = 1e-6;
  for (const auto& c : cases())
    for (const Vec3& s : states()) {
      const Vec3 P = principal_stress(c.model, s, kMu, kLam, c.edits);
      for (int i = 0; i < 3; ++i) {
        Vec3 sp = s, sm = s;
        sp[i] += h;
        sm[i] -= h;
        const double fd = (principal_energy(c.model, sp, kMu, kLam, c.edits) -
                           principal_energy(c.model, sm, kMu, kLam, c.edits)) / (2 * h);
        CHECK_CLOSE(P[i], fd, 1e-4, ctx(c.name, s, i));
      }
    }
}

TEST_CASE(tangent_is_stress_gradient) {
  const double h = 1e-6;
  for (const auto& c : cases())
    for (const Vec3& s : states()) {
      const Mat3 H = principal_stress_derivative(c.model, s, kMu, kLam, c.edits);
      for (int j = 0; j < 3; ++j) {
        Vec3 sp = s, sm = s;
        sp[j] += h;
        sm[j] -= h;
        const Vec3 fd = (principal_stress(c.model, sp, kMu, kLam, c.edits) -
                         principal_stress(c.model, sm, kMu, kLam, c.edits)) / (2 * h);
        for (int i = 0; i < 3; ++i) CHECK_CLOSE(H(i, j), fd[i], 1e-4, ctx(c.name, s, i, j));
      }
      // Hyperelastic laws have a symmetric principal tangent.
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < i; ++j) CHECK_CLOSE(H(i, j), H(j, i), 1e-10, ctx(c.name, s, i, j));
    }
}

TEST_CASE(rotation_variant_svd_reconstructs) {
  std::mt19937 rng(3);
  for (const Vec3& s : states()) {
    const Mat3 F = mltest::random_rotation(rng) * s.asDiagonal() * mltest::random_rotation(rng).transpose();
    Mat3 U, V;
    Vec3 sh;
    rotation_variant_svd(F, U, sh, V);
    CHECK_CLOSE(U.determinant(), 1.0, 1e-12, "det U");
    CHECK_CLOSE(V.determinant(), 1.0, 1e-12, "det V");
    const Mat3 R = U * sh.asDiagonal() * V.transpose();
    for (int k = 0; k < 9; ++k) CHECK_CLOSE(R.data()[k], F.data()[k], 1e-12, ctx("svd", s, k));
    Vec3 sorted = s;  // descending, the negative (inverted) one last
    std::sort(sorted.data(), sorted.data() + 3, std::greater<>());
    for (int k = 0; k < 3; ++k) CHECK_CLOSE(sh[k], sorted[k], 1e-8, ctx("svd values", s, k));
  }
}

TEST_CASE(svd_lanes_equal_the_scalar_svd_bitwise) {
  // Batches mixing every kind of state the scalar path meets: random and near-repeated
  // stretches, pure rotations (its robust fallback), exact identity (no sweep), inverted,
  // rank-deficient, zero and NaN matrices, so lanes converge after different sweep counts.
  std::mt19937 rng(17);
  std::normal_distribution<double> nrm(0.0, 1.0);
  std::vector<Mat3> Fs;
  for (const Vec3& s : states())
    Fs.push_back(mltest::random_rotation(rng) * s.asDiagonal() * mltest::random_rotation(rng).transpose());
  for (double eps : {0.0, 1e-12, 1e-8, 1e-4, 1e-2, 0.3})
    for (int i = 0; i < 12; ++i) {
      Mat3 M;
      for (int k = 0; k < 9; ++k) M.data()[k] = nrm(rng);
      Fs.push_back(mltest::random_rotation(rng) * (Mat3::Identity() + eps * M));
    }
  Fs.push_back(Mat3::Identity());
  Fs.push_back(Mat3::Zero());
  Fs.push_back(Vec3(1.0, 2.0, 0.0).asDiagonal());  // rank-deficient
  Fs.push_back(Vec3(1.0, 1.0, -1.0).asDiagonal());  // inverted, repeated
  Mat3 bad = Mat3::Identity();
  bad(1, 2) = std::nan("");
  Fs.push_back(bad);
  std::shuffle(Fs.begin(), Fs.end(), rng);
  if (Fs.size() % kSvdLanes == 0) Fs.push_back(Mat3::Identity());  // a last, partial block
  const int n = int(Fs.size());
  std::vector<Mat3> U(n), V(n);
  std::vector<Vec3> S(n);
  for (int i = 0; i < n; i += kSvdLanes)
    rotation_variant_svd_lanes(&Fs[i], &U[i], &S[i], &V[i], std::min(kSvdLanes, n - i));
  int differ = 0;
  for (int i = 0; i < n; ++i) {
    if (!Fs[i].allFinite()) continue;  // (its output is meaningless; it must not disturb the others)
    Mat3 U1, V1;
    Vec3 s1;
    rotation_variant_svd(Fs[i], U1, s1, V1);
    auto same = [](const double* a, const double* b, int k) {
      for (int j = 0; j < k; ++j)
        if (!(a[j] == b[j] || (std::isnan(a[j]) && std::isnan(b[j])))) return false;
      return true;
    };
    if (!same(U1.data(), U[i].data(), 9) || !same(V1.data(), V[i].data(), 9) || !same(s1.data(), S[i].data(), 3))
      ++differ;
  }
  CHECK(differ == 0);
  if (differ) std::fprintf(stderr, "  %d of %d matrices differ\n", differ, n);
}

TEST_CASE(dPdF_matches_finite_differences_of_world_stress) {
  std::mt19937 rng(11);
  const double h = 1e-6;
  for (const auto& c : cases())
    for (const Vec3& s : states()) {
      if (std::abs(s[1] + s[2]) < 0.2) continue;  // (Ph_i+Ph_j)/(s_i+s_j) is singular there
      const Mat3 F =
          mltest::random_rotation(rng) * s.asDiagonal() * mltest::random_rotation(rng).transpose();
      Mat3 U, V;
      Vec3 sh;
      rotation_variant_svd(F, U, sh, V);
      const Vec3 Ph = principal_stress(c.model, sh, kMu, kLam, c.edits);
      const Mat3 dPh = principal_stress_derivative(c.model, sh, kMu, kLam, c.edits);
      const Eigen::Matrix<double, 9, 9> A = stress_derivative_from_principal(U, sh, V, Ph, dPh, false);
      for (int k = 0; k < 9; ++k) {
        Mat3 Fp = F, Fm = F;
        Fp.data()[k] += h;
        Fm.data()[k] -= h;
        const Mat3 fd = (world_stress(c, Fp) - world_stress(c, Fm)) / (2 * h);
        for (int r = 0; r < 9; ++r) CHECK_CLOSE(A(r, k), fd.data()[r], 1e-4, ctx(c.name, s, r, k));
      }
      // Major symmetry of a hyperelastic tangent.
      for (int r = 0; r < 9; ++r)
        for (int k = 0; k < r; ++k) CHECK_CLOSE(A(r, k), A(k, r), 1e-8, ctx(c.name, s, r, k));
    }
}

TEST_CASE(projected_dPdF_is_psd_and_exact_when_already_psd) {
  std::mt19937 rng(5);
  for (const auto& c : cases())
    for (const Vec3& s : states()) {
      if (std::abs(s[1] + s[2]) < 0.2) continue;
      const Mat3 U = mltest::random_rotation(rng), V = mltest::random_rotation(rng);
      const Vec3 Ph = principal_stress(c.model, s, kMu, kLam, c.edits);
      const Mat3 dPh = principal_stress_derivative(c.model, s, kMu, kLam, c.edits);
      const Eigen::Matrix<double, 9, 9> A = stress_derivative_from_principal(U, s, V, Ph, dPh, true);
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 9, 9>> es(0.5 * (A + A.transpose()));
      CHECK_MSG(es.eigenvalues().minCoeff() >= -1e-9 * es.eigenvalues().cwiseAbs().maxCoeff(),
                ctx(c.name, s, 0) + ": projected tangent has a negative eigenvalue");
    }
  // At rest nothing needs projecting: the projected and exact tangents agree.
  for (const auto& c : cases()) {
    const Mat3 U = mltest::random_rotation(rng), V = mltest::random_rotation(rng);
    const Vec3 s = Vec3::Ones();
    const Vec3 Ph = principal_stress(c.model, s, kMu, kLam, c.edits);
    const Mat3 dPh = principal_stress_derivative(c.model, s, kMu, kLam, c.edits);
    const auto A = stress_derivative_from_principal(U, s, V, Ph, dPh, true);
    const auto B = stress_derivative_from_principal(U, s, V, Ph, dPh, false);
    for (int k = 0; k < 81; ++k) CHECK_CLOSE(A.data()[k], B.data()[k], 1e-10, ctx(c.name, s, k));
  }
}

TEST_CASE(bad_material_names_throw) {
  CHECK_THROWS(material_model_from_string("rubber"), InvalidInput);
  CHECK(material_model_from_string("neo_hookean") == MaterialModel::NeoHookean);
}
