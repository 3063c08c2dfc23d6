// Double-precision 3x3 SVD (one-sided Jacobi) and its backward, shared by svd3x3 and kabsch and by
// the CPU and CUDA kernels; free of torch includes (the CUDA kernel headers use it). Matrices are
// row-major double[9]; A = U diag(S) V^T with S sorted descending, U and V orthogonal.
#pragma once

#include <math.h>

#include "common/host_device.h"

namespace vrnet {

VRNET_HOST_DEVICE inline void cross3(const double* a, const double* b, double* out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

VRNET_HOST_DEVICE inline double det3(const double* m) {
  return m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6]) +
         m[2] * (m[3] * m[7] - m[4] * m[6]);
}

// Unit vector orthogonal to unit vector a.
VRNET_HOST_DEVICE inline void any_orthogonal(const double* a, double* out) {
  const int i = fabs(a[0]) <= fabs(a[1]) && fabs(a[0]) <= fabs(a[2]) ? 0 : (fabs(a[1]) <= fabs(a[2]) ? 1 : 2);
  double e[3] = {0, 0, 0};
  e[i] = 1.0;
  cross3(a, e, out);
  const double n = sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2]);
  for (int r = 0; r < 3; ++r) out[r] /= n;
}

VRNET_HOST_DEVICE inline void svd3x3_double(const double* A, double* U, double* S, double* V) {
  double W[9];
  for (int i = 0; i < 9; ++i) W[i] = A[i];
  for (int i = 0; i < 9; ++i) V[i] = (i % 4 == 0) ? 1.0 : 0.0;
  for (int sweep = 0; sweep < 30; ++sweep) {
    bool rotated = false;
    for (int pair = 0; pair < 3; ++pair) {  // column pairs (0,1), (0,2), (1,2)
      const int p = pair == 2 ? 1 : 0, q = pair == 0 ? 1 : 2;
      double alpha = 0, beta = 0, gamma = 0;
      for (int r = 0; r < 3; ++r) {
        alpha += W[3 * r + p] * W[3 * r + p];
        beta += W[3 * r + q] * W[3 * r + q];
        gamma += W[3 * r + p] * W[3 * r + q];
      }
      if (gamma == 0.0 || fabs(gamma) <= 1e-15 * sqrt(alpha * beta)) continue;
      rotated = true;
      const double zeta = (beta - alpha) / (2.0 * gamma);
      const double t = (zeta >= 0 ? 1.0 : -1.0) / (fabs(zeta) + sqrt(1.0 + zeta * zeta));
      const double c = 1.0 / sqrt(1.0 + t * t), s = c * t;
      for (int r = 0; r < 3; ++r) {
        const double wp = W[3 * r + p], wq = W[3 * r + q];
        W[3 * r + p] = c * wp - s * wq;
        W[3 * r + q] = s * wp + c * wq;
        const double vp = V[3 * r + p], vq = V[3 * r + q];
        V[3 * r + p] = c * vp - s * vq;
        V[3 * r + q] = s * vp + c * vq;
      }
    }
    if (!rotated) break;
  }
  double norms[3];
  for (int c = 0; c < 3; ++c) norms[c] = sqrt(W[c] * W[c] + W[3 + c] * W[3 + c] + W[6 + c] * W[6 + c]);
  // Column order by descending norm; a stable 3-element sort (ties keep column order).
  int order[3] = {0, 1, 2};
  for (int i = 1; i < 3; ++i)
    for (int j = i; j > 0 && norms[order[j]] > norms[order[j - 1]]; --j) {
      const int tmp = order[j];
      order[j] = order[j - 1];
      order[j - 1] = tmp;
    }
  double Vs[9], cols[3][3];
  for (int c = 0; c < 3; ++c) {
    S[c] = norms[order[c]];
    for (int r = 0; r < 3; ++r) {
      Vs[3 * r + c] = V[3 * r + order[c]];
      cols[c][r] = W[3 * r + order[c]];
    }
  }
  for (int i = 0; i < 9; ++i) V[i] = Vs[i];
  // Columns of U: A v_i / s_i, completed to an orthonormal basis where s_i vanishes.
  const double tiny = 1e-13 * S[0];
  double u[3][3];
  for (int c = 0; c < 3; ++c) {
    if (S[c] > tiny && S[c] > 0) {
      for (int r = 0; r < 3; ++r) u[c][r] = cols[c][r] / S[c];
    } else if (c == 0) {
      u[0][0] = 1; u[0][1] = 0; u[0][2] = 0;
    } else if (c == 1) {
      any_orthogonal(u[0], u[1]);
    } else {
      cross3(u[0], u[1], u[2]);
    }
  }
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r) U[3 * r + c] = u[c][r];
}

// One SVD of a scalar_t matrix through the double routine.
template <typename scalar_t>
VRNET_HOST_DEVICE void svd3x3_one(const scalar_t* a, scalar_t* u, scalar_t* s, scalar_t* v) {
  double ad[9], ud[9], sd[3], vd[9];
  for (int i = 0; i < 9; ++i) ad[i] = a[i];
  svd3x3_double(ad, ud, sd, vd);
  for (int i = 0; i < 9; ++i) {
    u[i] = static_cast<scalar_t>(ud[i]);
    v[i] = static_cast<scalar_t>(vd[i]);
  }
  for (int i = 0; i < 3; ++i) s[i] = static_cast<scalar_t>(sd[i]);
}

// Smooth reciprocal x / (x^2 + eps^2): equals 1/x away from 0 and stays finite at 0.
VRNET_HOST_DEVICE inline double damped_inverse(double x, double eps) { return x / (x * x + eps * eps); }

// Backward of one SVD: gA = U [ (skew(U^T gU) S + S skew(V^T gV)) / (s_k^2 - s_j^2) + diag(gS) ] V^T,
// with both 1/(s_k -+ s_j) factors damped.
template <typename scalar_t>
VRNET_HOST_DEVICE void svd3x3_backward_one(const scalar_t* gu, const scalar_t* gs, const scalar_t* gv,
                                           const scalar_t* u, const scalar_t* s, const scalar_t* v, scalar_t* ga) {
  double utgu[9], vtgv[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      double a = 0, c = 0;
      for (int r = 0; r < 3; ++r) {
        a += double(u[3 * r + i]) * gu[3 * r + j];
        c += double(v[3 * r + i]) * gv[3 * r + j];
      }
      utgu[3 * i + j] = a;
      vtgv[3 * i + j] = c;
    }
  // Relative damping only (an absolute floor of 1e-12 spoilt the gradients of matrices whose
  // singular values are all below ~1e-10); 1e-150 keeps eps^2 a normal double for a zero matrix.
  const double eps = 1e-150 + 1e-9 * fabs(double(s[0]));
  double inner[9];
  for (int j = 0; j < 3; ++j)
    for (int k = 0; k < 3; ++k) {
      if (j == k) {
        inner[3 * j + k] = gs[j];
        continue;
      }
      const double sk_u = (utgu[3 * j + k] - utgu[3 * k + j]) * s[k];
      const double sj_v = s[j] * (vtgv[3 * j + k] - vtgv[3 * k + j]);
      inner[3 * j + k] = (sk_u + sj_v) * damped_inverse(double(s[k]) - s[j], eps) *
                         damped_inverse(double(s[k]) + s[j], eps);
    }
  for (int i = 0; i < 3; ++i)
    for (int l = 0; l < 3; ++l) {
      double acc = 0;
      for (int j = 0; j < 3; ++j)
        for (int k = 0; k < 3; ++k) acc += double(u[3 * i + j]) * inner[3 * j + k] * v[3 * l + k];
      ga[3 * i + l] = static_cast<scalar_t>(acc);
    }
}

}  // namespace vrnet
