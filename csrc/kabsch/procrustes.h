// Weighted Procrustes pieces shared by the CPU and CUDA kabsch kernels: the 3x3 solve from
// accumulated moments, and the backward through centroids, covariance and the rotation's polar
// factor. A kernel accumulates the moments its own way (a loop on CPU, a warp on CUDA). Free of torch
// includes (the CUDA kernel header uses it).
#pragma once

#include "svd3x3/svd3x3_math.h"

namespace vrnet {

// One problem: weight sum, weighted centroids, weighted covariance H = sum_i w_i/W (x_i - xc)(y_i - yc)^T,
// and the solution R = V diag(1, 1, d) U^T of H = U S V^T.
// Weights may be scaled by `wscale` before they are summed (the CPU kernel divides them by their
// maximum, so weights of 1e300 do not overflow the sum): wsum is the sum of w_i / wscale, and the
// normalised weight of point i is w_i / wscale / wsum whatever the scale.
struct Procrustes {
  double wscale = 1, wsum = 0, src_c[3] = {0, 0, 0}, tgt_c[3] = {0, 0, 0};
  double H[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, U[9], S[3], V[9], R[9], det_sign = 1;

  // Call once wsum, src_c, tgt_c (normalised) and H (normalised) are filled.
  VRNET_HOST_DEVICE void solve_rotation() {
    svd3x3_double(H, U, S, V);
    det_sign = det3(U) * det3(V) < 0 ? -1.0 : 1.0;
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c)
        R[3 * a + c] = V[3 * a] * U[3 * c] + V[3 * a + 1] * U[3 * c + 1] + det_sign * V[3 * a + 2] * U[3 * c + 2];
  }

  // t = tgt_c - R src_c.
  template <typename scalar_t>
  VRNET_HOST_DEVICE void write(scalar_t* R_out, scalar_t* t_out) const {
    for (int a = 0; a < 3; ++a) {
      double ta = tgt_c[a];
      for (int c = 0; c < 3; ++c) {
        R_out[3 * a + c] = static_cast<scalar_t>(R[3 * a + c]);
        ta -= R[3 * a + c] * src_c[c];
      }
      t_out[a] = static_cast<scalar_t>(ta);
    }
  }
};

// Gradients of the moments from (gR, gt): gH (9), g_src_c (3), g_tgt_c (3).
// dR = Omega R with Omega = V (Atilde o K) V^T, K_ij = 1/(sigma_i + sigma_j), sigma = (s1, s2, d s3);
// the 1/(sigma_i + sigma_j) factors are damped so degenerate inputs stay finite.
struct ProcrustesGrad {
  double gH[9], g_src_c[3], g_tgt_c[3];

  ProcrustesGrad() = default;

  template <typename scalar_t>
  VRNET_HOST_DEVICE ProcrustesGrad(const Procrustes& p, const scalar_t* grad_R, const scalar_t* grad_t) {
    const double* R = p.R;
    double g_R[9];
    for (int a = 0; a < 3; ++a) {
      g_tgt_c[a] = grad_t[a];
      g_src_c[a] = 0;
      for (int c = 0; c < 3; ++c) {
        g_R[3 * a + c] = grad_R[3 * a + c] - double(grad_t[a]) * p.src_c[c];
        g_src_c[a] -= R[3 * c + a] * grad_t[c];
      }
    }
    const double sigma[3] = {p.S[0], p.S[1], p.det_sign * p.S[2]};
    const double eps = 1e-150 + 1e-9 * p.S[0];
    double G[9], Gt[9], Z[9], Y[9];
    for (int a = 0; a < 3; ++a)  // G = gR R^T
      for (int c = 0; c < 3; ++c) {
        double acc = 0;
        for (int r = 0; r < 3; ++r) acc += g_R[3 * a + r] * R[3 * c + r];
        G[3 * a + c] = acc;
      }
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
  }

  // Point i's gradients: writes d/dx_i and d/dy_i and returns the weight gradient before the
  // normalisation w_i / W is differentiated (see finish_weight_grad).
  template <typename scalar_t>
  VRNET_HOST_DEVICE double point(const Procrustes& p, const scalar_t* x, const scalar_t* y, scalar_t w, scalar_t* gx,
                                 scalar_t* gy) const {
    const double wi = w / p.wscale / p.wsum;
    double dx[3], dy[3], g_what = 0;
    for (int a = 0; a < 3; ++a) {
      dx[a] = x[a] - p.src_c[a];
      dy[a] = y[a] - p.tgt_c[a];
    }
    for (int a = 0; a < 3; ++a) {
      double hx = 0, hy = 0;
      for (int c = 0; c < 3; ++c) {
        hx += gH[3 * a + c] * dy[c];
        hy += gH[3 * c + a] * dx[c];
      }
      gx[a] = static_cast<scalar_t>(wi * (hx + g_src_c[a]));
      gy[a] = static_cast<scalar_t>(wi * (hy + g_tgt_c[a]));
      g_what += dx[a] * hx + g_src_c[a] * x[a] + g_tgt_c[a] * y[a];
    }
    return g_what;
  }
};

// d/dw_i of the normalised weights w_i / W: (g_i - sum_j (w_j/W) g_j) / W.
VRNET_HOST_DEVICE inline double finish_weight_grad(double g_what, double weighted_mean, double wsum) {
  return (g_what - weighted_mean) / wsum;
}

}  // namespace vrnet
