// MLP correction evaluator (cpp/correction/correction.*): the Jacobians d dPh / d Fh and
// d dPh / d Fhdot pass central finite differences on seeded random states, for the fixed-size
// 6-H-H fast path (H = 6, 16; with and without stretch-rate inputs) and the generic loop (H = 5,
// and 4 layers); the 4th output is dalpha; a net with zero Fhdot columns is exactly
// rate-independent; malformed networks throw InvalidInput.
#include <random>

#include "check.hpp"
#include "correction/correction.hpp"

using namespace matlearn;
using namespace matlearn::correction;

namespace {

std::vector<DenseLayer> random_layers(const std::vector<int>& widths, bool rate, std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 0.7);
  std::vector<DenseLayer> L;
  for (size_t l = 0; l + 1 < widths.size(); ++l) {
    DenseLayer d{MatX(widths[l + 1], widths[l]), VecX(widths[l + 1])};
    for (int i = 0; i < d.W.size(); ++i) d.W.data()[i] = n(rng);
    for (int i = 0; i < d.b.size(); ++i) d.b[i] = n(rng);
    if (l == 0 && !rate) d.W.rightCols(3).setZero();
    L.push_back(d);
  }
  return L;
}

MlpCorrection make(const std::vector<int>& widths, bool rate, unsigned seed) {
  std::mt19937 rng(seed);
  const int no = widths.back();
  VecX in_mean(6), in_std(6), out_mean = VecX::LinSpaced(no, -50, 50), out_std = VecX::Constant(no, 1e3);
  in_mean << 1, 1, 1, 0, 0, 0;
  in_std << 0.1, 0.1, 0.1, 0.5, 0.5, 0.5;
  if (no == 4) out_mean[3] = 0.002, out_std[3] = 0.01;
  return MlpCorrection(random_layers(widths, rate, rng), in_mean, in_std, out_mean, out_std);
}

void random_states(int m, unsigned seed, MatX3& Fh, MatX3& Fhd) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> n(0.0, 1.0);
  Fh.resize(m, 3);
  Fhd.resize(m, 3);
  for (int e = 0; e < m; ++e)
    for (int i = 0; i < 3; ++i) Fh(e, i) = 1 + 0.1 * n(rng), Fhd(e, i) = 0.5 * n(rng);
}

void check_jacobians(const MlpCorrection& c, bool rate, const char* name) {
  MatX3 Fh, Fhd;
  random_states(10, 3, Fh, Fhd);
  CorrectionOutput out, op, om;
  c.evaluate(Fh, Fhd, out);
  const double h = 1e-6;
  double scale = 0;
  for (auto& J : out.d_dFh) scale = std::max(scale, J.cwiseAbs().maxCoeff());
  CHECK(scale > 10.0);  // a non-trivial net
  for (int which = 0; which < 2; ++which)
    for (int j = 0; j < 3; ++j) {
      MatX3 Ap = which ? Fhd : Fh, Am = Ap;
      Ap.col(j).array() += h;
      Am.col(j).array() -= h;
      c.evaluate(which ? Fh : Ap, which ? Ap : Fhd, op);
      c.evaluate(which ? Fh : Am, which ? Am : Fhd, om);
      for (int e = 0; e < Fh.rows(); ++e)
        for (int i = 0; i < 3; ++i) {
          const double fd = (op.dPh(e, i) - om.dPh(e, i)) / (2 * h);
          const double an = which ? out.d_dFhdot[e](i, j) : out.d_dFh[e](i, j);
          CHECK_CLOSE(an / scale, fd / scale, 1e-5,
                      std::string(name) + (which ? " dFhdot" : " dFh") + " e=" + std::to_string(e) +
                          " (" + std::to_string(i) + "," + std::to_string(j) + ")");
        }
    }
  bool zero = true;
  for (auto& J : out.d_dFhdot) zero = zero && J.isZero(0.0);
  CHECK_MSG(zero == !rate, std::string(name) + ": d_dFhdot zero iff the Fhdot columns are zero");
}

}  // namespace

TEST_CASE(jacobians_pass_finite_differences) {
  check_jacobians(make({6, 6, 6, 4}, true, 1), true, "6-6-6-4 rate");
  check_jacobians(make({6, 6, 6, 4}, false, 2), false, "6-6-6-4 no rate");
  check_jacobians(make({6, 16, 16, 4}, true, 3), true, "6-16-16-4 rate");
  check_jacobians(make({6, 16, 16, 3}, false, 4), false, "6-16-16-3 no rate");
  check_jacobians(make({6, 5, 5, 4}, true, 5), true, "6-5-5-4 (generic)");
  check_jacobians(make({6, 6, 6, 6, 4}, false, 6), false, "6-6-6-6-4 (generic)");
}

TEST_CASE(dalpha_is_the_fourth_output_and_rate_masked_net_ignores_rates) {
  // The same first three layers with 3 and with 4 outputs: identical dPh; dalpha = 4th output.
  std::mt19937 rng(9);
  auto L4 = random_layers({6, 6, 6, 4}, false, rng);
  auto L3 = L4;
  L3.back().W = L4.back().W.topRows(3);
  L3.back().b = L4.back().b.head(3);
  VecX im(6), is(6);
  im << 1, 1, 1, 0, 0, 0;
  is << 0.1, 0.1, 0.1, 0.5, 0.5, 0.5;
  VecX om4(4), os4(4);
  om4 << 1, 2, 3, 0.004;
  os4 << 100, 200, 300, 0.02;
  MlpCorrection c4(L4, im, is, om4, os4), c3(L3, im, is, om4.head(3), os4.head(3));
  MatX3 Fh, Fhd;
  random_states(20, 4, Fh, Fhd);
  CorrectionOutput o4, o3, oz;
  c4.evaluate(Fh, Fhd, o4);
  c3.evaluate(Fh, Fhd, o3);
  c4.evaluate(Fh, MatX3::Zero(Fh.rows(), 3), oz);
  CHECK(o3.dalpha.isZero(0.0));
  for (int e = 0; e < Fh.rows(); ++e) {
    for (int i = 0; i < 3; ++i) {
      CHECK_CLOSE(o4.dPh(e, i), o3.dPh(e, i), 1e-14, "dPh 4 vs 3 outputs");
      CHECK(o4.dPh(e, i) == oz.dPh(e, i));  // no stretch-rate dependence at all
    }
    // Reference forward of the 4th output by hand.
    VecX a(6);
    a << Fh.row(e).transpose(), Fhd.row(e).transpose();
    a = (a - im).cwiseQuotient(is);
    for (int l = 0; l < 2; ++l) {
      a = L4[l].W * a + L4[l].b;
      for (int i = 0; i < a.size(); ++i) a[i] = a[i] > 0 ? a[i] : std::expm1(a[i]);
    }
    const double want = (L4[2].W.row(3).dot(a) + L4[2].b[3]) * os4[3] + om4[3];
    CHECK_CLOSE(o4.dalpha[e], want, 1e-13, "dalpha e=" + std::to_string(e));
  }
}

TEST_CASE(malformed_networks_throw) {
  std::mt19937 rng(1);
  VecX im = VecX::Zero(6), is = VecX::Ones(6);
  CHECK_THROWS(MlpCorrection(random_layers({6, 6, 5}, true, rng), im, is, VecX::Zero(5), VecX::Ones(5)),
               InvalidInput);
  CHECK_THROWS(MlpCorrection(random_layers({6, 6, 4}, true, rng), im, is, VecX::Zero(3), VecX::Ones(3)),
               InvalidInput);
  CHECK_THROWS(MlpCorrection(random_layers({6, 40, 3}, true, rng), im, is, VecX::Zero(3), VecX::Ones(3)),
               InvalidInput);
  auto bad = random_layers({6, 6, 4}, true, rng);
  bad[0].W(0, 0) = std::nan("");
  CHECK_THROWS(MlpCorrection(bad, im, is, VecX::Zero(4), VecX::Ones(4)), InvalidInput);
  CHECK_THROWS(MlpCorrection(random_layers({6, 6, 4}, true, rng), im, VecX::Zero(6), VecX::Zero(4),
                             VecX::Ones(4)),
               InvalidInput);
}
