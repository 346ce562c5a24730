#include "correction/correction.hpp"

#include <cmath>
#include <type_traits>

namespace matlearn::correction {

constexpr int kMaxWidth = 32;  ///< widest MLP layer (fixed-capacity temporaries)

/// Zeroed outputs for m elements; without `jacobians` (the values-only paths) no Jacobians.
static void resize_output(int m, CorrectionOutput& out, bool jacobians = true) {
  out.dPh.setZero(m, 3);
  if (jacobians) {
    out.d_dFh.assign(m, Mat3::Zero());
    out.d_dFhdot.assign(m, Mat3::Zero());
  } else {
    out.d_dFh.clear();
    out.d_dFhdot.clear();
  }
  out.dalpha.setZero(m);
}

RbfCorrection::RbfCorrection(MatX3 centers, MatX3 weights, Mat3 linear, Vec3 bias,
                             VecX alpha_weights, double alpha_bias, double epsilon,
                             VecX lower, VecX upper, double isotropic_width)
    : c_(std::move(centers)), w_(std::move(weights)), A_(linear), b_(bias),
      wa_(std::move(alpha_weights)), a0_(alpha_bias), eps_(epsilon), lo_(std::move(lower)),
      hi_(std::move(upper)), width_(isotropic_width) {
  if (!std::isfinite(width_)) throw InvalidInput("RbfCorrection: isotropic_width must be finite");
  if (width_ < 0) {  // 0.1 x the mean per-axis (population) std of the centres
    double sd = 0;
    for (int j = 0; j < 3; ++j) {
      const double m = c_.col(j).mean();
      sd += std::sqrt((c_.col(j).array() - m).square().mean());
    }
    width_ = c_.rows() > 0 ? 0.1 * sd / 3.0 : 0.0;
  }
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

void RbfCorrection::element(const Vec3& s, Vec3& p, double& da, Mat3* J) const {
  const Vec3 sc = lo_.size() == 3 ? Vec3(s.cwiseMax(lo_).cwiseMin(hi_)) : s;
  // All centres at once on per-axis contiguous columns (Eigen packet sqrt and dot products).
  // The values of the full and the values-only (J == nullptr) evaluation share every operation,
  // so they are bitwise equal. Inside the box the extension term is not formed at all (it is
  // an exact +0 there): the kernel is phi.
  thread_local Eigen::ArrayXd d[3], phi, g, dd, gi;
  for (int i = 0; i < 3; ++i) d[i] = sc[i] - c_.col(i).array();
  phi = (d[0].square() + d[1].square() + d[2].square() + eps_ * eps_).sqrt();
  const bool inside = sc == s;
  const Vec3 delta = s - sc;
  if (!inside) {
    dd = d[0] * delta[0] + d[1] * delta[1] + d[2] * delta[2];
    g = phi + dd / phi;  // the extended kernel values
  }
  const Eigen::ArrayXd& kv = inside ? phi : g;
  p = A_ * (s - Vec3::Ones()) + b_;
  for (int j = 0; j < 3; ++j) p[j] += w_.col(j).dot(kv.matrix());
  da = a0_ + (wa_.size() > 0 ? wa_.dot(phi.matrix()) : 0.0);
  if (J) {
    *J = A_;
    for (int i = 0; i < 3; ++i) {
      // d g_k / d s_i: d_i / phi inside the box and along the axes where s is clamped, and
      // d_i / phi (1 - dd / phi^2) along the others (extended_kernel)
      if (inside || delta[i] != 0.0)
        gi = d[i] / phi;
      else
        gi = d[i] / phi * (1.0 - dd / phi.square());
      for (int j = 0; j < 3; ++j) (*J)(j, i) += w_.col(j).dot(gi.matrix());
    }
  }
  if (width_ > 0) isotropic_blend(s, width_, p, J, nullptr);
}

void RbfCorrection::evaluate(const MatX3& Fh, const MatX3&, CorrectionOutput& out) const {
  const int m = Fh.rows();
  resize_output(m, out);
#pragma omp parallel for schedule(static)
  for (int e = 0; e < m; ++e) {
    Vec3 p;
    element(Fh.row(e).transpose(), p, out.dalpha[e], &out.d_dFh[e]);
    out.dPh.row(e) = p.transpose();
  }
}

void RbfCorrection::evaluate_values(const MatX3& Fh, const MatX3&, CorrectionOutput& out) const {
  const int m = Fh.rows();
  resize_output(m, out, false);
#pragma omp parallel for schedule(static)
  for (int e = 0; e < m; ++e) {
    Vec3 p;
    element(Fh.row(e).transpose(), p, out.dalpha[e], nullptr);
    out.dPh.row(e) = p.transpose();
  }
}

MlpCorrection::MlpCorrection(std::vector<DenseLayer> layers, VecX in_mean, VecX in_std,
                             VecX out_mean, VecX out_std, double isotropic_width)
    : layers_(std::move(layers)), in_mean_(std::move(in_mean)), in_std_(std::move(in_std)),
      out_mean_(std::move(out_mean)), out_std_(std::move(out_std)), width_(isotropic_width) {
  if (layers_.empty()) throw InvalidInput("MlpCorrection: no layers");
  int width = 6;
  for (size_t l = 0; l < layers_.size(); ++l) {
    if (layers_[l].W.cols() != width || layers_[l].b.size() != layers_[l].W.rows())
      throw InvalidInput("MlpCorrection: layer " + std::to_string(l) + " has inconsistent shape");
    width = layers_[l].W.rows();
    if (width > kMaxWidth)
      throw InvalidInput("MlpCorrection: layers wider than " + std::to_string(kMaxWidth) + " are not supported");
  }
  if (width != 3 && width != 4)
    throw InvalidInput("MlpCorrection: last layer must have 3 outputs (dPh) or 4 (dPh, dalpha), got " +
                       std::to_string(width));
  outputs_ = width;
  if (in_mean_.size() != 6 || in_std_.size() != 6 || out_mean_.size() != width || out_std_.size() != width)
    throw InvalidInput("MlpCorrection: normalisation vectors must have sizes 6, 6, " + std::to_string(width) +
                       ", " + std::to_string(width) + " (inputs, outputs of the last layer)");
  if ((in_std_.array() <= 0).any() || (out_std_.array() <= 0).any())
    throw InvalidInput("MlpCorrection: normalisation std must be positive");
  for (const auto& L : layers_)
    if (!L.W.allFinite() || !L.b.allFinite())
      throw InvalidInput("MlpCorrection: weights contain NaN or Inf");
  if (!std::isfinite(width_)) throw InvalidInput("MlpCorrection: isotropic_width must be finite");
  if (width_ < 0) width_ = 0.1 * in_std_.head<3>().mean();
}

namespace {

inline double elu(double z, double* slope) {
  if (z > 0) {
    *slope = 1.0;
    return z;
  }
  const double y = std::expm1(z);
  *slope = y + 1.0;
  return y;
}

/// Fast path of MlpCorrection::evaluate for the distillation architecture 6 -> H -> H -> 3|4
/// with fixed-size Eigen types; NC = 3 propagates only the Fh Jacobian (a net whose first-layer
/// Fhdot columns are zero), NC = 6 both, NC = 0 none (values only: the same value arithmetic,
/// so bitwise the values of NC = 3 or 6). Same arithmetic as the generic loop.
template <int H, int NC>
void mlp_fixed(const std::vector<DenseLayer>& L, const VecX& in_mean, const VecX& in_std,
               const VecX& out_mean, const VecX& out_std, double width, const MatX3& Fh,
               const MatX3& Fhdot, CorrectionOutput& out) {
  using VH = Eigen::Matrix<double, H, 1>;
  const int m = Fh.rows(), no = L[2].W.rows();
  const Eigen::Matrix<double, H, 6> W0 = L[0].W;
  constexpr int NJ = NC > 0 ? NC : 1;  // Jacobian columns carried (unused when NC = 0)
  Eigen::Matrix<double, H, NJ> W0J = Eigen::Matrix<double, H, NJ>::Zero();
  if constexpr (NC > 0)
    W0J = W0.template leftCols<NC>() * in_std.head<NC>().cwiseInverse().asDiagonal();
  const Eigen::Matrix<double, H, H> W1 = L[1].W;
  Eigen::Matrix<double, 4, H> W2 = Eigen::Matrix<double, 4, H>::Zero();
  W2.topRows(no) = L[2].W;
  const VH b0 = L[0].b, b1 = L[1].b;
  Eigen::Vector4d b2 = Eigen::Vector4d::Zero(), om = Eigen::Vector4d::Zero(), os = Eigen::Vector4d::Zero();
  b2.head(no) = L[2].b;
  om.head(no) = out_mean;
  os.head(no) = out_std;
  using Vec6 = Eigen::Matrix<double, 6, 1>;
  const Vec6 im = in_mean, is = in_std.cwiseInverse();
#pragma omp parallel for schedule(static)
  for (int e = 0; e < m; ++e) {
    Vec6 a;
    a << Fh.row(e).transpose(), Fhdot.row(e).transpose();
    a = (a - im).cwiseProduct(is);
    VH z = W0 * a + b0;
    Eigen::Matrix<double, H, NJ> J = W0J;
    for (int i = 0; i < H; ++i) {
      double d;
      z[i] = elu(z[i], &d);
      if constexpr (NC > 0) J.row(i) *= d;
    }
    VH z1 = W1 * z + b1;
    Eigen::Matrix<double, H, NJ> J1;
    if constexpr (NC > 0) J1.noalias() = W1 * J;
    for (int i = 0; i < H; ++i) {
      double d;
      z1[i] = elu(z1[i], &d);
      if constexpr (NC > 0) J1.row(i) *= d;
    }
    const Eigen::Vector4d y = (W2 * z1 + b2).cwiseProduct(os) + om;
    Vec3 p = y.head<3>();
    Mat3 Js, Jd = Mat3::Zero();
    if constexpr (NC > 0) {
      const Eigen::Matrix<double, 3, NC> Jy = os.head<3>().asDiagonal() * (W2.template topRows<3>() * J1);
      Js = Jy.template leftCols<3>();
      if constexpr (NC == 6) Jd = Jy.template rightCols<3>();
    }
    if (width > 0)
      isotropic_blend(Fh.row(e).transpose(), width, p, NC > 0 ? &Js : nullptr, NC == 6 ? &Jd : nullptr);
    if constexpr (NC > 0) out.d_dFh[e] = Js;
    if constexpr (NC == 6) out.d_dFhdot[e] = Jd;
    out.dPh.row(e) = p.transpose();
    if (no == 4) out.dalpha[e] = y[3];
  }
}

}  // namespace

void MlpCorrection::evaluate(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const {
  run(Fh, Fhdot, true, out);
}

void MlpCorrection::evaluate_values(const MatX3& Fh, const MatX3& Fhdot, CorrectionOutput& out) const {
  run(Fh, Fhdot, false, out);
}

void MlpCorrection::run(const MatX3& Fh, const MatX3& Fhdot, bool jacobians, CorrectionOutput& out) const {
  const int m = Fh.rows();
  resize_output(m, out, jacobians);
  if (layers_.size() == 3 && layers_[0].W.rows() == layers_[1].W.rows()) {
    const int H = layers_[0].W.rows();
    const bool rate = !layers_[0].W.rightCols<3>().isZero(0.0);
    const auto fixed = [&](auto h, auto nc) {
      mlp_fixed<decltype(h)::value, decltype(nc)::value>(layers_, in_mean_, in_std_, out_mean_,
                                                         out_std_, width_, Fh, Fhdot, out);
    };
    using I0 = std::integral_constant<int, 0>;
    using I3 = std::integral_constant<int, 3>;
    using I6 = std::integral_constant<int, 6>;
    using I16 = std::integral_constant<int, 16>;
    if (H == 6) return !jacobians ? fixed(I6{}, I0{}) : rate ? fixed(I6{}, I6{}) : fixed(I6{}, I3{});
    if (H == 16) return !jacobians ? fixed(I16{}, I0{}) : rate ? fixed(I16{}, I6{}) : fixed(I16{}, I3{});
  }
  // Fixed-capacity temporaries (no heap allocation per element): layers are at most kMaxWidth wide.
  using SmallV = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxWidth, 1>;
  using SmallM = Eigen::Matrix<double, Eigen::Dynamic, 6, 0, kMaxWidth, 6>;
#pragma omp parallel for schedule(static)
  for (int e = 0; e < m; ++e) {
    SmallV a(6);
    a << Fh.row(e).transpose(), Fhdot.row(e).transpose();
    a = (a - in_mean_).cwiseQuotient(in_std_);
    SmallM Ja;  // d a / d input (6 x 6)
    if (jacobians) Ja = in_std_.cwiseInverse().asDiagonal();
    for (size_t l = 0; l < layers_.size(); ++l) {
      SmallV z = layers_[l].W * a + layers_[l].b;
      SmallM Jz;
      if (jacobians) Jz = layers_[l].W * Ja;
      if (l + 1 < layers_.size()) {
        for (int i = 0; i < z.size(); ++i) {
          double d;
          z[i] = elu(z[i], &d);
          if (jacobians) Jz.row(i) *= d;
        }
      }
      a = z;
      if (jacobians) Ja = Jz;
    }
    const SmallV y = a.cwiseProduct(out_std_) + out_mean_;
    Vec3 p = y.head<3>();
    Mat3 Js, Jd;
    if (jacobians) {
      const Eigen::Matrix<double, 3, 6> Jy = out_std_.head<3>().asDiagonal() * Ja.topRows<3>();
      Js = Jy.leftCols<3>();
      Jd = Jy.rightCols<3>();
    }
    if (width_ > 0)
      isotropic_blend(Fh.row(e).transpose(), width_, p, jacobians ? &Js : nullptr, jacobians ? &Jd : nullptr);
    if (jacobians) {
      out.d_dFh[e] = Js;
      out.d_dFhdot[e] = Jd;
    }
    out.dPh.row(e) = p.transpose();
    // The Model uses dalpha's value only (its stretch derivative is left out of the tangent, as
    // for RbfCorrection).
    if (outputs_ == 4) out.dalpha[e] = y[3];
  }
}

}  // namespace matlearn::correction
