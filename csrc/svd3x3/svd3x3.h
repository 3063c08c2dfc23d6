// Double-precision 3x3 SVD (one-sided Jacobi) shared by svd3x3 and kabsch.
// Matrices are row-major double[9]; A = U diag(S) V^T with S sorted descending, U and V orthogonal.
#pragma once

#include <algorithm>
#include <cmath>
#include <utility>

namespace vrnet {

inline void cross3(const double* a, const double* b, double* out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

inline double det3(const double* m) {
  return m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6]) +
         m[2] * (m[3] * m[7] - m[4] * m[6]);
}

// Unit vector orthogonal to unit vector a.
inline void any_orthogonal(const double* a, double* out) {
  const int i = std::fabs(a[0]) <= std::fabs(a[1]) && std::fabs(a[0]) <= std::fabs(a[2]) ? 0
                : (std::fabs(a[1]) <= std::fabs(a[2]) ? 1 : 2);
  double e[3] = {0, 0, 0};
  e[i] = 1.0;
  cross3(a, e, out);
  const double n = std::sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2]);
  for (int r = 0; r < 3; ++r) out[r] /= n;
}

inline void svd3x3_double(const double* A, double* U, double* S, double* V) {
  double W[9];
  std::copy(A, A + 9, W);
  for (int i = 0; i < 9; ++i) V[i] = (i % 4 == 0) ? 1.0 : 0.0;
  static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
  for (int sweep = 0; sweep < 30; ++sweep) {
    bool rotated = false;
    for (const auto& pq : pairs) {
      const int p = pq[0], q = pq[1];
      double alpha = 0, beta = 0, gamma = 0;
      for (int r = 0; r < 3; ++r) {
        alpha += W[3 * r + p] * W[3 * r + p];
        beta += W[3 * r + q] * W[3 * r + q];
        gamma += W[3 * r + p] * W[3 * r + q];
      }
      if (gamma == 0.0 || std::fabs(gamma) <= 1e-15 * std::sqrt(alpha * beta)) continue;
      rotated = true;
      const double zeta = (beta - alpha) / (2.0 * gamma);
      const double t = (zeta >= 0 ? 1.0 : -1.0) / (std::fabs(zeta) + std::sqrt(1.0 + zeta * zeta));
      const double c = 1.0 / std::sqrt(1.0 + t * t), s = c * t;
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
  int order[3] = {0, 1, 2};
  double norms[3];
  for (int c = 0; c < 3; ++c)
    norms[c] = std::sqrt(W[c] * W[c] + W[3 + c] * W[3 + c] + W[6 + c] * W[6 + c]);
  std::sort(order, order + 3, [&](int a, int b) { return norms[a] > norms[b]; });
  double Vs[9], cols[3][3];
  for (int c = 0; c < 3; ++c) {
    S[c] = norms[order[c]];
    for (int r = 0; r < 3; ++r) {
      Vs[3 * r + c] = V[3 * r + order[c]];
      cols[c][r] = W[3 * r + order[c]];
    }
  }
  std::copy(Vs, Vs + 9, V);
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

// Smooth reciprocal x / (x^2 + eps^2): equals 1/x away from 0 and stays finite at 0.
inline double damped_inverse(double x, double eps) { return x / (x * x + eps * eps); }

}  // namespace vrnet
