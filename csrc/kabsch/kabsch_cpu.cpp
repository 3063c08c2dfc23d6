// Weighted Kabsch / Procrustes: R, t = argmin sum_i w_i |R x_i + t - y_i|^2 over proper rotations.
// Weights enter once (normalised to sum 1), centroids and covariance are fused, the 3x3 solve runs
// in double. The backward differentiates the rotation polar factor, whose only singular terms are
// 1/(sigma_i + sigma_j); they are damped so degenerate (collinear, duplicate) inputs stay finite.
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include "common/common.h"
#include "svd3x3/svd3x3.h"

namespace vrnet {
namespace {

// Per-problem pieces shared by forward and backward.
struct Procrustes {
  double wsum = 0, src_c[3] = {0, 0, 0}, tgt_c[3] = {0, 0, 0};
  double H[9] = {0}, U[9], S[3], V[9], R[9], det_sign = 1;

  template <typename scalar_t>
  void solve(const scalar_t* x, const scalar_t* y, const scalar_t* w, int64_t n) {
    for (int64_t i = 0; i < n; ++i) wsum += w[i];
    for (int64_t i = 0; i < n; ++i)
      for (int a = 0; a < 3; ++a) {
        src_c[a] += w[i] * double(x[3 * i + a]);
        tgt_c[a] += w[i] * double(y[3 * i + a]);
      }
    for (int a = 0; a < 3; ++a) { src_c[a] /= wsum; tgt_c[a] /= wsum; }
    for (int64_t i = 0; i < n; ++i) {
      const double wi = w[i] / wsum;
      for (int a = 0; a < 3; ++a)
        for (int c = 0; c < 3; ++c)
          H[3 * a + c] += wi * (x[3 * i + a] - src_c[a]) * (y[3 * i + c] - tgt_c[c]);
    }
    svd3x3_double(H, U, S, V);
    det_sign = det3(U) * det3(V) < 0 ? -1.0 : 1.0;
    for (int a = 0; a < 3; ++a)  // R = V diag(1, 1, d) U^T
      for (int c = 0; c < 3; ++c)
        R[3 * a + c] = V[3 * a] * U[3 * c] + V[3 * a + 1] * U[3 * c + 1] + det_sign * V[3 * a + 2] * U[3 * c + 2];
  }
};

template <typename scalar_t>
void check_weights(const scalar_t* w, int64_t n, int64_t b) {
  double total = 0;
  for (int64_t i = 0; i < n; ++i) {
    TORCH_CHECK_VALUE(w[i] >= 0, "weights must be non-negative (batch ", b, ", point ", i, " is ", double(w[i]), ")");
    total += w[i];
  }
  TORCH_CHECK_VALUE(total > 0, "weights of batch ", b, " sum to zero: at least one point needs a positive weight");
}

void check_inputs(const at::Tensor& src, const at::Tensor& tgt, const at::Tensor& weights) {
  check_float(src, "src");
  check_float(tgt, "tgt");
  check_float(weights, "weights");
  TORCH_CHECK_VALUE(src.dim() == 3 && src.size(2) == 3, "src must have shape (B, N, 3), got ", src.sizes());
  TORCH_CHECK_VALUE(tgt.sizes() == src.sizes(), "tgt must have the shape of src ", src.sizes(), ", got ", tgt.sizes());
  TORCH_CHECK_VALUE(weights.dim() == 2 && weights.size(0) == src.size(0) && weights.size(1) == src.size(1),
                    "weights must have shape (B, N) = (", src.size(0), ", ", src.size(1), "), got ", weights.sizes());
  TORCH_CHECK_TYPE(src.scalar_type() == tgt.scalar_type() && src.scalar_type() == weights.scalar_type(),
                   "src, tgt and weights must share a dtype");
  TORCH_CHECK_VALUE(src.size(1) >= 3, "src needs at least 3 points per cloud, got ", src.size(1));
}

std::tuple<at::Tensor, at::Tensor> kabsch_cpu(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                              const at::Tensor& weights_in) {
  check_inputs(src_in, tgt_in, weights_in);
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  check_finite(src, "src");
  check_finite(tgt, "tgt");
  check_finite(weights, "weights");
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor R = at::empty({B, 3, 3}, src.options()), t = at::empty({B, 3}, src.options());
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_cpu", [&] {
    const scalar_t *xp = src.const_data_ptr<scalar_t>(), *yp = tgt.const_data_ptr<scalar_t>();
    const scalar_t* wp = weights.const_data_ptr<scalar_t>();
    for (int64_t b = 0; b < B; ++b) check_weights(wp + b * N, N, b);
    scalar_t *rp = R.mutable_data_ptr<scalar_t>(), *tp = t.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, B, std::max<int64_t>(1, 4096 / N), [&](int64_t begin, int64_t end) {
      for (int64_t b = begin; b < end; ++b) {
        Procrustes p;
        p.solve(xp + b * N * 3, yp + b * N * 3, wp + b * N, N);
        for (int a = 0; a < 3; ++a) {
          double ta = p.tgt_c[a];
          for (int c = 0; c < 3; ++c) {
            rp[9 * b + 3 * a + c] = p.R[3 * a + c];
            ta -= p.R[3 * a + c] * p.src_c[c];
          }
          tp[3 * b + a] = ta;
        }
      }
    });
  });
  return {R, t};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> kabsch_backward_cpu(const at::Tensor& gR_in, const at::Tensor& gt_in,
                                                                   const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                                   const at::Tensor& weights_in) {
  const at::Tensor gR = gR_in.contiguous(), gt = gt_in.contiguous();
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor g_src = at::empty_like(src), g_tgt = at::empty_like(tgt), g_w = at::empty_like(weights);
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_backward_cpu", [&] {
    const scalar_t *xp = src.const_data_ptr<scalar_t>(), *yp = tgt.const_data_ptr<scalar_t>();
    const scalar_t *wp = weights.const_data_ptr<scalar_t>(), *grp = gR.const_data_ptr<scalar_t>();
    const scalar_t* gtp = gt.const_data_ptr<scalar_t>();
    scalar_t *gxp = g_src.mutable_data_ptr<scalar_t>(), *gyp = g_tgt.mutable_data_ptr<scalar_t>();
    scalar_t* gwp = g_w.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, B, std::max<int64_t>(1, 4096 / N), [&](int64_t begin, int64_t end) {
      for (int64_t b = begin; b < end; ++b) {
        const scalar_t *x = xp + b * N * 3, *y = yp + b * N * 3, *w = wp + b * N;
        Procrustes p;
        p.solve(x, y, w, N);
        const double* R = p.R;
        // t = tgt_c - R src_c.
        double g_R[9], g_src_c[3], g_tgt_c[3];
        for (int a = 0; a < 3; ++a) {
          g_tgt_c[a] = gtp[3 * b + a];
          g_src_c[a] = 0;
          for (int c = 0; c < 3; ++c) {
            g_R[3 * a + c] = grp[9 * b + 3 * a + c] - double(gtp[3 * b + a]) * p.src_c[c];
            g_src_c[a] -= R[3 * c + a] * gtp[3 * b + c];
          }
        }
        // dR = Omega R with Omega = V (Atilde o K) V^T, K_ij = 1/(sigma_i + sigma_j), sigma = (s1, s2, d s3).
        const double sigma[3] = {p.S[0], p.S[1], p.det_sign * p.S[2]};
        const double eps = 1e-30 + 1e-9 * p.S[0];
        double G[9], Gt[9], Z[9], Y[9], gH[9];
        for (int i = 0; i < 9; ++i) G[i] = 0;
        for (int a = 0; a < 3; ++a)  // G = gR R^T
          for (int c = 0; c < 3; ++c)
            for (int r = 0; r < 3; ++r) G[3 * a + c] += g_R[3 * a + r] * R[3 * c + r];
        for (int i = 0; i < 3; ++i)  // Gt = V^T G V
          for (int j = 0; j < 3; ++j) {
            double acc = 0;
            for (int a = 0; a < 3; ++a)
              for (int c = 0; c < 3; ++c) acc += p.V[3 * a + i] * G[3 * a + c] * p.V[3 * c + j];
            Gt[3 * i + j] = acc;
          }
        for (int i = 0; i < 3; ++i)  // Z = (Gt^T - Gt) o K
          for (int j = 0; j < 3; ++j)
            Z[3 * i + j] = i == j ? 0.0 : (Gt[3 * j + i] - Gt[3 * i + j]) * damped_inverse(sigma[i] + sigma[j], eps);
        for (int a = 0; a < 3; ++a)  // Y = V Z V^T  (this is Y^T - Y of the derivation)
          for (int c = 0; c < 3; ++c) {
            double acc = 0;
            for (int i = 0; i < 3; ++i)
              for (int j = 0; j < 3; ++j) acc += p.V[3 * a + i] * Z[3 * i + j] * p.V[3 * c + j];
            Y[3 * a + c] = acc;
          }
        for (int a = 0; a < 3; ++a)  // gH = R^T Y
          for (int c = 0; c < 3; ++c) {
            double acc = 0;
            for (int r = 0; r < 3; ++r) acc += R[3 * r + a] * Y[3 * r + c];
            gH[3 * a + c] = acc;
          }
        // H = sum_i w_i/W (x_i - xc)(y_i - yc)^T, xc = sum_i w_i/W x_i, yc likewise.
        double weighted_mean_gw = 0;
        for (int64_t i = 0; i < N; ++i) {
          const double wi = w[i] / p.wsum;
          double dx[3], dy[3], g_what = 0;
          for (int a = 0; a < 3; ++a) {
            dx[a] = x[3 * i + a] - p.src_c[a];
            dy[a] = y[3 * i + a] - p.tgt_c[a];
          }
          for (int a = 0; a < 3; ++a) {
            double hx = 0, hy = 0;
            for (int c = 0; c < 3; ++c) {
              hx += gH[3 * a + c] * dy[c];
              hy += gH[3 * c + a] * dx[c];
            }
            gxp[(b * N + i) * 3 + a] = wi * (hx + g_src_c[a]);
            gyp[(b * N + i) * 3 + a] = wi * (hy + g_tgt_c[a]);
            g_what += dx[a] * hx + g_src_c[a] * x[3 * i + a] + g_tgt_c[a] * y[3 * i + a];
          }
          gwp[b * N + i] = g_what;
          weighted_mean_gw += wi * g_what;
        }
        for (int64_t i = 0; i < N; ++i) gwp[b * N + i] = (gwp[b * N + i] - weighted_mean_gw) / p.wsum;
      }
    });
  });
  return {g_src, g_tgt, g_w};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("kabsch", &kabsch_cpu);
  m.impl("kabsch_backward", &kabsch_backward_cpu);
}

}  // namespace vrnet
