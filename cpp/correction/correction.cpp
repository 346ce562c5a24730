#include "correction/correction.hpp"

#include <cmath>

namespace matlearn::correction {

constexpr int kMaxWidth = 32;  ///< widest MLP layer (fixed-capacity temporaries)

static void resize_output(int m, CorrectionOutput& out) {
  out.dPh.setZero(m, 3);
  out.d_dFh.assign(m, Mat3::Zero());
  out.d_dFhdot.assign(m, Mat3::Zero());
  out.dalpha.setZero(m);
}

RbfCorrection::RbfCorrection(MatX3 centers, MatX3 weights, Mat3 linear, Vec3 bias,
                             VecX alpha_weights, double alpha_bias, double epsilon,
                             VecX lower, VecX upper)
    : c_(std::move(centers)), w_(std::move(weights)), A_(linear), b_(bias),
      wa_(std::move(alpha_weights)), a0_(alpha_bias), eps_(epsilon), lo_(std::move(lower)),
      hi_(std::move(upper)) {
  if (lo_.size() != hi_.size() || (lo_.size() != 0 && lo_.size() != 3))
    throw InvalidInput("RbfCorrection: lower/upper must both be empty or have 3 entries");
  if (lo_.size() == 3 && (!lo_.allFinite() || !hi_.allFinite() || (lo_.array() > hi_.array()).any()))
    throw InvalidInput("RbfCorrection: need finite lower <= upper");
  if (w_.rows() != c_.rows())
    throw InvalidInput("RbfCorrection: weights must have one row per centre");
  if (wa_.size() != 0 && wa_.size() != c_.rows())
    throw InvalidInput("RbfCorrection: alpha_weights must be empty or have one entry per centre");
  if (!(eps_ > 0)) throw InvalidInput("RbfCorrection: epsilon must be > 0");
  if (!c_.allFinite() || !w_.allFinite() || !A_.allFinite() || !wa_.allFinite())
    throw InvalidInput("RbfCorrection: parameters contain NaN or Inf");
}

void RbfCorrection::evaluate(const MatX3& Fh, const MatX3&, CorrectionOutput& out) const {
  const int m = Fh.rows();
  resize_output(m, out);
  const bool damp = wa_.size() > 0, box = lo_.size() == 3;
#pragma omp parallel for schedule(static)
  for (int e = 0; e < m; ++e) {
    const Vec3 s = Fh.row(e).transpose();
    Vec3 p = A_ * (s - Vec3::Ones()) + b_;
    Mat3 J = A_;
    double da = a0_;
    const Vec3 sc = box ? Vec3(s.cwiseMax(lo_).cwiseMin(hi_)) : s;
    Vec3 g;
    double phi_c = 0;
    for (int k = 0; k < c_.rows(); ++k) {
      const Vec3 w = w_.row(k).transpose();
      p += w * extended_kernel(s, sc, c_.row(k).transpose(), eps_, &g, &phi_c);
      J += w * g.transpose();
      if (damp) da += wa_[k] * phi_c;
    }
    out.dPh.row(e) = p.transpose();
    out.d_dFh[e] = J;
    out.dalpha[e] = da;
  }
}

MlpCorrection::MlpCorrection(std::vector<DenseLayer> layers, VecX in_mean, VecX in_std,
                             VecX out_mean, VecX out_std)
    : layers_(std::move(layers)), in_mean_(std::move(in_mean)), in_std_(std::move(in_std)),
      out_mean_(std::move(out_mean)), out_std_(std::move(out_std)) {
  if (layers_.empty()) throw InvalidInput("MlpCorrection: no layers");
  int width = 6;
  for (size_t l = 0; l < layers_.size(); ++l) {
    if (layers_[l].W.cols() != width || layers_[l].b.size() != layers_[l].W.rows())
      throw InvalidInput("MlpCorrection: layer " + std::to_string(l) + " has inconsistent shape");
    width = layers_[l].W.rows();
    if (width > kMaxWidth)
      throw InvalidInput("MlpCorrection: layers wider than " + std::to_string(kMaxWidth) + " are not supported");
  }
  if (width != 3) throw InvalidInput("MlpCorrection: last layer must have 3 outputs");
  if (in_mean_.size() != 6 || in_std_.size() != 6 || out_mean_.size() != 3 || out_std_.size() != 3)
    throw InvalidInput("MlpCorrection: normalisation vectors must have sizes 6, 6, 3, 3");
  if ((in_std_.array() <= 0).any() || (out_std_.array() <= 0).any())
    throw InvalidInput("MlpCorrection: normalisation std must be positive");
}

void MlpCorrection::evaluate(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const {
  const int m = Fh.rows();
  resize_output(m, out);
  // Fixed-capacity temporaries (no heap allocation per element): layers are at most kMaxWidth wide.
  using SmallV = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxWidth, 1>;
  using SmallM = Eigen::Matrix<double, Eigen::Dynamic, 6, 0, kMaxWidth, 6>;
#pragma omp parallel for schedule(static)
  for (int e = 0; e < m; ++e) {
    SmallV a(6);
    a << Fh.row(e).transpose(), Fhdot.row(e).transpose();
    a = (a - in_mean_).cwiseQuotient(in_std_);
    SmallM Ja = in_std_.cwiseInverse().asDiagonal();  // d a / d input (6 x 6)
    for (size_t l = 0; l < layers_.size(); ++l) {
      SmallV z = layers_[l].W * a + layers_[l].b;
      SmallM Jz = layers_[l].W * Ja;
      if (l + 1 < layers_.size()) {
        for (int i = 0; i < z.size(); ++i) {
          const double d = z[i] > 0 ? 1.0 : std::exp(z[i]);
          z[i] = z[i] > 0 ? z[i] : std::expm1(z[i]);
          Jz.row(i) *= d;
        }
      }
      a = z;
      Ja = Jz;
    }
    const Vec3 y = a.cwiseProduct(out_std_) + out_mean_;
    const Eigen::Matrix<double, 3, 6> Jy = out_std_.asDiagonal() * Ja;
    out.dPh.row(e) = y.transpose();
    out.d_dFh[e] = Jy.leftCols<3>();
    out.d_dFhdot[e] = Jy.rightCols<3>();
  }
}

}  // namespace matlearn::correction
