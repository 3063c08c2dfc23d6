// CUDA weighted Kabsch in stages. (1) One warp per problem reduces the largest weight, then the sum of
// the scaled weights (w / max w, as the CPU kernel: weights of 1e300 do not overflow) and the
// centroids, then the centred covariance (double, fixed shuffle order: deterministic) into a Moments
// record. (2) One thread per problem solves the 3x3 problem with the routine shared with the CPU
// kernel (kabsch/procrustes.h) - and in the backward differentiates it. (3) Backward only: one warp
// per problem writes the per-point gradients; the weight gradient's terms stay in double (computed
// twice rather than kept in the output dtype). robust_kabsch runs (1) and (2) and every reweighting
// step in one block per problem, the residuals' median by a radix select in shared memory.
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

// The threads that reduce one problem: one warp (stages 1 and 3) ...
struct WarpGroup {
  int rank;  // the lane

  __device__ int size() const { return 32; }
  __device__ double max(double v) const { return warp_max(v); }
  __device__ void sum(double* values, int count) const {
    for (int i = 0; i < count; ++i) values[i] = warp_sum(values[i]);
  }
};

constexpr int kRobustThreads = 128;  // robust_kabsch: threads per problem (one block)
constexpr int kRobustWarps = kRobustThreads / 32;
constexpr int kMostSums = 9;  // values one BlockGroup::sum call reduces at most

// ... or a whole block (robust_kabsch): warp totals, then the warps' totals added in warp order by
// every thread (each gets the same bits). `scratch` holds kRobustWarps * kMostSums shared doubles.
struct BlockGroup {
  double* scratch;

  __device__ int size() const { return kRobustThreads; }
  __device__ void sum(double* values, int count) const {
    const int warp = threadIdx.x / 32;
    for (int i = 0; i < count; ++i) values[i] = warp_sum(values[i]);
    if (threadIdx.x % 32 == 0)
      for (int i = 0; i < count; ++i) scratch[warp * kMostSums + i] = values[i];
    __syncthreads();
    for (int i = 0; i < count; ++i) {
      double total = 0;
      for (int w = 0; w < kRobustWarps; ++w) total += scratch[w * kMostSums + i];
      values[i] = total;
    }
    __syncthreads();  // the scratch is free again
  }
  __device__ double max(double v) const {
    v = warp_max(v);
    if (threadIdx.x % 32 == 0) scratch[threadIdx.x / 32] = v;
    __syncthreads();
    double largest = scratch[0];
    for (int w = 1; w < kRobustWarps; ++w) largest = scratch[w] > largest ? scratch[w] : largest;
    __syncthreads();
    return largest;
  }
};

// One group's reduction of one problem's moments (x, y: N points; w: N weights of any floating type),
// each thread taking the points rank, rank + size, ... . Every thread of the group must call it and
// gets the record.
template <typename Group, typename scalar_t, typename weight_t>
__device__ Moments group_moments(const Group& group, int rank, const scalar_t* x, const scalar_t* y,
                                 const weight_t* w, int64_t N) {
  const int stride = group.size();
  double wmax = 0;
  for (int64_t i = rank; i < N; i += stride) wmax = double(w[i]) > wmax ? double(w[i]) : wmax;
  Moments m;
  m.wscale = group.max(wmax);
  double s[7] = {0, 0, 0, 0, 0, 0, 0};
  for (int64_t i = rank; i < N; i += stride) {
    const double wi = w[i] / m.wscale;
    s[0] += wi;
    for (int a = 0; a < 3; ++a) {
      s[1 + a] += wi * double(x[3 * i + a]);
      s[4 + a] += wi * double(y[3 * i + a]);
    }
  }
  group.sum(s, 7);
  m.wsum = s[0];
  for (int a = 0; a < 3; ++a) {
    m.src_c[a] = s[1 + a] / m.wsum;
    m.tgt_c[a] = s[4 + a] / m.wsum;
  }
  double h[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  for (int64_t i = rank; i < N; i += stride) {
    const double wi = w[i] / m.wscale / m.wsum;
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c) h[3 * a + c] += wi * (x[3 * i + a] - m.src_c[a]) * (y[3 * i + c] - m.tgt_c[c]);
  }
  group.sum(h, 9);
  for (int i = 0; i < 9; ++i) m.H[i] = h[i];
  return m;
}

template <typename scalar_t>
__global__ void kabsch_moments_kernel(const scalar_t* __restrict__ src, const scalar_t* __restrict__ tgt,
                                      const scalar_t* __restrict__ weights, int64_t B, int64_t N,
                                      Moments* __restrict__ moments) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * kKabschWarpsPerBlock + threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  if (b >= B) return;  // whole warps exit together
  const Moments m = group_moments(WarpGroup{lane}, lane, src + b * N * 3, tgt + b * N * 3, weights + b * N, N);
  if (lane == 0) moments[b] = m;
}

// The k-th smallest (0-based) of one problem's N non-negative values `v`, exactly: a radix select
// over their bit patterns (ordered as the values for non-negative doubles), 8 bits a pass from the
// top. Each pass counts, in `histogram` (256 shared counters), the digits of the values that share
// the digits chosen so far; the first warp scans the counts and picks the digit holding the k-th,
// handing it and the rank left within it over through `chosen` (2 shared words). Every thread of
// the block calls it and gets the value.
__device__ inline double block_select(const double* v, int64_t N, int64_t k, unsigned int* histogram,
                                      unsigned long long* chosen) {
  unsigned long long prefix = 0, mask = 0, rank = static_cast<unsigned long long>(k);
  for (int shift = 56; shift >= 0; shift -= 8) {
    for (int i = threadIdx.x; i < 256; i += kRobustThreads) histogram[i] = 0;
    __syncthreads();
    for (int64_t i = threadIdx.x; i < N; i += kRobustThreads) {
      const unsigned long long key = static_cast<unsigned long long>(__double_as_longlong(v[i]));
      if ((key & mask) == prefix) atomicAdd(&histogram[(key >> shift) & 255u], 1u);
    }
    __syncthreads();
    if (threadIdx.x < 32) {  // lane l scans the digits 8 l .. 8 l + 7
      const int lane = threadIdx.x;
      unsigned int counts[8], own = 0;
      for (int j = 0; j < 8; ++j) own += counts[j] = histogram[8 * lane + j];
      unsigned int through = own;  // inclusive prefix sum over the lanes
      for (int offset = 1; offset < 32; offset <<= 1) {
        const unsigned int below = __shfl_up_sync(kFullWarp, through, offset);
        if (lane >= offset) through += below;
      }
      const unsigned long long before = through - own;
      if (before <= rank && rank < through) {  // exactly one lane: the k-th lies in its digits
        unsigned long long left = rank - before;
        int digit = 8 * lane;
        for (int j = 0; j < 8 && left >= counts[j]; ++j, ++digit) left -= counts[j];
        chosen[0] = static_cast<unsigned long long>(digit);
        chosen[1] = left;
      }
    }
    __syncthreads();  // the next pass writes `chosen` only after its own two barriers
    prefix |= chosen[0] << shift;
    mask |= 255ull << shift;
    rank = chosen[1];
  }
  return __longlong_as_double(static_cast<long long>(prefix));
}

// robust_kabsch: one block per problem runs the weighted solve and every reweighting step (as the
// CPU kernel's robust_solve); each thread keeps its own points' residuals and weights in the (B, N)
// double buffers, every thread solves the 3x3 problem itself (the same inputs: the same result).
template <typename scalar_t>
__global__ void robust_kabsch_kernel(const scalar_t* __restrict__ src, const scalar_t* __restrict__ tgt,
                                     const scalar_t* __restrict__ weights, int64_t B, int64_t N,
                                     RobustOptions options, double* __restrict__ residuals,
                                     double* __restrict__ robust_weights, scalar_t* __restrict__ R,
                                     scalar_t* __restrict__ t) {
  VRNET_SHARED(double, scratch, kRobustWarps * kMostSums);
  VRNET_SHARED(unsigned int, histogram, 256);
  VRNET_SHARED(unsigned long long, chosen, 2);
  const int64_t b = blockIdx.x;
  const int rank = threadIdx.x;
  const BlockGroup block{scratch};
  const scalar_t *x = src + b * N * 3, *y = tgt + b * N * 3, *w = weights + b * N;
  double *residual = residuals + b * N, *weight = robust_weights + b * N;
  Procrustes p = group_moments(block, rank, x, y, w, N).unsolved();
  p.solve_rotation();
  for (int64_t step = 0; step < options.iterations; ++step) {
    for (int64_t i = rank; i < N; i += kRobustThreads) residual[i] = procrustes_residual(p, x + 3 * i, y + 3 * i);
    const double median = block_select(residual, N, (N - 1) / 2, histogram, chosen);
    const double pair_scale = robust_pair_scale(options, median);
    double largest = 0;
    for (int64_t i = rank; i < N; i += kRobustThreads) {
      weight[i] = double(w[i]) * robust_weight(options.kernel, residual[i] / pair_scale);
      largest = weight[i] > largest ? weight[i] : largest;
    }
    if (!(block.max(largest) > 0)) break;
    p = group_moments(block, rank, x, y, weight, N).unsolved();
    p.solve_rotation();
  }
  if (rank == 0) p.write(R + 9 * b, t + 3 * b);
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
