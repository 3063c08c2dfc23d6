// CUDA weighted Kabsch in stages. (1) One warp per problem reduces the largest weight, then the sum of
// the scaled weights (w / max w, as the CPU kernel: weights of 1e300 do not overflow) and the
// centroids, then the centred covariance (double, fixed shuffle order: deterministic) into a Moments
// record. (2) One thread per problem solves the 3x3 problem with the routine shared with the CPU
// kernel (kabsch/procrustes.h) - and in the backward differentiates it. (3) Backward only: one warp
// per problem writes the per-point gradients; the weight gradient's terms stay in double (computed
// twice rather than kept in the output dtype). robust_kabsch runs (1) and (2) and its reweighting
// steps in one warp per problem.
#pragma once

#include "common/cuda_device.cuh"
#include "kabsch/procrustes.h"
#include "kabsch/robust.h"

namespace vrnet {

constexpr int kKabschWarpsPerBlock = 8;

// What stage (1) hands to stages (2) and (3) per problem, as plain doubles.
struct Moments {
  double wscale, wsum, src_c[3], tgt_c[3], H[9];

  __device__ Procrustes unsolved() const {
    Procrustes p;
    p.wscale = wscale;
    p.wsum = wsum;
    for (int a = 0; a < 3; ++a) {
      p.src_c[a] = src_c[a];
      p.tgt_c[a] = tgt_c[a];
    }
    for (int i = 0; i < 9; ++i) p.H[i] = H[i];
    return p;
  }
};
constexpr int64_t kMomentDoubles = sizeof(Moments) / sizeof(double);
constexpr int64_t kGradDoubles = sizeof(ProcrustesGrad) / sizeof(double);
static_assert(sizeof(Moments) == 17 * sizeof(double) && sizeof(ProcrustesGrad) == 15 * sizeof(double),
              "the stage buffers hold these structs as plain doubles");

// One warp's reduction of one problem's moments (x, y: N points; w: N weights of any floating type).
// All 32 lanes must call it; every lane gets the record.
template <typename scalar_t, typename weight_t>
__device__ Moments warp_moments(const scalar_t* x, const scalar_t* y, const weight_t* w, int64_t N, int lane) {
  double wmax = 0;
  for (int64_t i = lane; i < N; i += 32) wmax = double(w[i]) > wmax ? double(w[i]) : wmax;
  Moments m;
  m.wscale = warp_max(wmax);
  double s[7] = {0, 0, 0, 0, 0, 0, 0};
  for (int64_t i = lane; i < N; i += 32) {
    const double wi = w[i] / m.wscale;
    s[0] += wi;
    for (int a = 0; a < 3; ++a) {
      s[1 + a] += wi * double(x[3 * i + a]);
      s[4 + a] += wi * double(y[3 * i + a]);
    }
  }
  for (int i = 0; i < 7; ++i) s[i] = warp_sum(s[i]);
  m.wsum = s[0];
  for (int a = 0; a < 3; ++a) {
    m.src_c[a] = s[1 + a] / m.wsum;
    m.tgt_c[a] = s[4 + a] / m.wsum;
  }
  double h[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  for (int64_t i = lane; i < N; i += 32) {
    const double wi = w[i] / m.wscale / m.wsum;
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c) h[3 * a + c] += wi * (x[3 * i + a] - m.src_c[a]) * (y[3 * i + c] - m.tgt_c[c]);
  }
  for (int i = 0; i < 9; ++i) m.H[i] = warp_sum(h[i]);
  return m;
}

template <typename scalar_t>
__global__ void kabsch_moments_kernel(const scalar_t* __restrict__ src, const scalar_t* __restrict__ tgt,
                                      const scalar_t* __restrict__ weights, int64_t B, int64_t N,
                                      Moments* __restrict__ moments) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * kKabschWarpsPerBlock + threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  if (b >= B) return;  // whole warps exit together
  const Moments m = warp_moments(src + b * N * 3, tgt + b * N * 3, weights + b * N, N, lane);
  if (lane == 0) moments[b] = m;
}

// The k-th smallest (0-based) of one problem's N non-negative values `v`, exactly: a bisection over
// their bit patterns (ordered as the values for non-negative doubles), counting with the warp.
__device__ inline double warp_select(const double* v, int64_t N, int64_t k, int lane) {
  double largest = 0;
  for (int64_t i = lane; i < N; i += 32) largest = v[i] > largest ? v[i] : largest;
  long long lo = 0, hi = __double_as_longlong(warp_max(largest));
  while (lo < hi) {
    const long long mid = lo + (hi - lo) / 2;
    double at_most = 0;
    for (int64_t i = lane; i < N; i += 32) at_most += __double_as_longlong(v[i]) <= mid ? 1.0 : 0.0;
    if (warp_sum(at_most) >= double(k + 1)) {
      hi = mid;
    } else {
      lo = mid + 1;
    }
  }
  return __longlong_as_double(lo);
}

// robust_kabsch: one warp per problem runs the weighted solve and every reweighting step (as the
// CPU kernel's robust_solve); each lane keeps its own points' residuals and weights in the (B, N)
// double buffers, every lane solves the 3x3 problem itself (the same inputs: the same result).
template <typename scalar_t>
__global__ void robust_kabsch_kernel(const scalar_t* __restrict__ src, const scalar_t* __restrict__ tgt,
                                     const scalar_t* __restrict__ weights, int64_t B, int64_t N,
                                     RobustOptions options, double* __restrict__ residuals,
                                     double* __restrict__ robust_weights, scalar_t* __restrict__ R,
                                     scalar_t* __restrict__ t) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * kKabschWarpsPerBlock + threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  if (b >= B) return;  // whole warps exit together
  const scalar_t *x = src + b * N * 3, *y = tgt + b * N * 3, *w = weights + b * N;
  double *residual = residuals + b * N, *weight = robust_weights + b * N;
  Procrustes p = warp_moments(x, y, w, N, lane).unsolved();
  p.solve_rotation();
  for (int64_t step = 0; step < options.iterations; ++step) {
    for (int64_t i = lane; i < N; i += 32) residual[i] = procrustes_residual(p, x + 3 * i, y + 3 * i);
    const double pair_scale = robust_pair_scale(options, warp_select(residual, N, (N - 1) / 2, lane));
    double largest = 0;
    for (int64_t i = lane; i < N; i += 32) {
      weight[i] = double(w[i]) * robust_weight(options.kernel, residual[i] / pair_scale);
      largest = weight[i] > largest ? weight[i] : largest;
    }
    if (!(warp_max(largest) > 0)) break;
    p = warp_moments(x, y, weight, N, lane).unsolved();
    p.solve_rotation();
  }
  if (lane == 0) p.write(R + 9 * b, t + 3 * b);
}

template <typename scalar_t>
__global__ void kabsch_solve_kernel(const Moments* __restrict__ moments, int64_t B, scalar_t* __restrict__ R,
                                    scalar_t* __restrict__ t) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= B) return;
  Procrustes p = moments[b].unsolved();
  p.solve_rotation();
  p.write(R + 9 * b, t + 3 * b);
}

template <typename scalar_t>
__global__ void kabsch_solve_backward_kernel(const Moments* __restrict__ moments, const scalar_t* __restrict__ grad_R,
                                             const scalar_t* __restrict__ grad_t, int64_t B,
                                             ProcrustesGrad* __restrict__ grads) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= B) return;
  Procrustes p = moments[b].unsolved();
  p.solve_rotation();
  grads[b] = ProcrustesGrad(p, grad_R + 9 * b, grad_t + 3 * b);
}

template <typename scalar_t>
__global__ void kabsch_point_grad_kernel(const Moments* __restrict__ moments,
                                         const ProcrustesGrad* __restrict__ grads, const scalar_t* __restrict__ src,
                                         const scalar_t* __restrict__ tgt, const scalar_t* __restrict__ weights,
                                         int64_t B, int64_t N, scalar_t* __restrict__ g_src,
                                         scalar_t* __restrict__ g_tgt, scalar_t* __restrict__ g_w) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * kKabschWarpsPerBlock + threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  if (b >= B) return;  // whole warps exit together
  const Procrustes p = moments[b].unsolved();
  const ProcrustesGrad grad = grads[b];
  const scalar_t *x = src + b * N * 3, *y = tgt + b * N * 3, *w = weights + b * N;
  double weighted_mean = 0;
  for (int64_t i = lane; i < N; i += 32) {
    scalar_t unused[6];
    weighted_mean += w[i] / p.wscale / p.wsum * grad.point(p, x + 3 * i, y + 3 * i, w[i], unused, unused + 3);
  }
  weighted_mean = warp_sum(weighted_mean);
  const double total_weight = p.wscale * p.wsum;  // may overflow to inf: the gradient is then ~0
  for (int64_t i = lane; i < N; i += 32) {
    const double g_what = grad.point(p, x + 3 * i, y + 3 * i, w[i], g_src + (b * N + i) * 3, g_tgt + (b * N + i) * 3);
    g_w[b * N + i] = static_cast<scalar_t>(finish_weight_grad(g_what, weighted_mean, total_weight));
  }
}

}  // namespace vrnet
