// CUDA weighted Kabsch in stages. (1) One warp per problem reduces the weight sum and centroids, then
// the centred covariance (two passes, double, fixed shuffle order: deterministic) into 16 doubles.
// (2) One thread per problem solves the 3x3 problem with the routine shared with the CPU kernel
// (kabsch/kabsch.h) - and in the backward differentiates it. (3) Backward only: one warp per problem
// writes the per-point gradients.
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "kabsch/kabsch.h"

namespace vrnet {
namespace {

constexpr int kWarpsPerBlock = 8;

// What stage (1) hands to stages (2) and (3) per problem.
struct Moments {
  double wsum, src_c[3], tgt_c[3], H[9];

  __device__ Procrustes unsolved() const {
    Procrustes p;
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
static_assert(sizeof(Moments) == 16 * sizeof(double) && sizeof(ProcrustesGrad) == 15 * sizeof(double),
              "the stage buffers hold these structs as plain doubles");

template <typename scalar_t>
__global__ void moments_kernel(const scalar_t* __restrict__ src, const scalar_t* __restrict__ tgt,
                               const scalar_t* __restrict__ weights, int64_t B, int64_t N,
                               Moments* __restrict__ moments) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * kWarpsPerBlock + threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  if (b >= B) return;  // whole warps exit together
  const scalar_t *x = src + b * N * 3, *y = tgt + b * N * 3, *w = weights + b * N;
  double s[7] = {0, 0, 0, 0, 0, 0, 0};
  for (int64_t i = lane; i < N; i += 32) {
    const double wi = w[i];
    s[0] += wi;
    for (int a = 0; a < 3; ++a) {
      s[1 + a] += wi * double(x[3 * i + a]);
      s[4 + a] += wi * double(y[3 * i + a]);
    }
  }
  for (int i = 0; i < 7; ++i) s[i] = warp_sum(s[i]);
  Moments m;
  m.wsum = s[0];
  for (int a = 0; a < 3; ++a) {
    m.src_c[a] = s[1 + a] / m.wsum;
    m.tgt_c[a] = s[4 + a] / m.wsum;
  }
  double h[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  for (int64_t i = lane; i < N; i += 32) {
    const double wi = w[i] / m.wsum;
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c) h[3 * a + c] += wi * (x[3 * i + a] - m.src_c[a]) * (y[3 * i + c] - m.tgt_c[c]);
  }
  for (int i = 0; i < 9; ++i) m.H[i] = warp_sum(h[i]);
  if (lane == 0) moments[b] = m;
}

template <typename scalar_t>
__global__ void solve_kernel(const Moments* __restrict__ moments, int64_t B, scalar_t* __restrict__ R,
                             scalar_t* __restrict__ t) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= B) return;
  Procrustes p = moments[b].unsolved();
  p.solve_rotation();
  p.write(R + 9 * b, t + 3 * b);
}

template <typename scalar_t>
__global__ void solve_backward_kernel(const Moments* __restrict__ moments, const scalar_t* __restrict__ grad_R,
                                      const scalar_t* __restrict__ grad_t, int64_t B,
                                      ProcrustesGrad* __restrict__ grads) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= B) return;
  Procrustes p = moments[b].unsolved();
  p.solve_rotation();
  grads[b] = ProcrustesGrad(p, grad_R + 9 * b, grad_t + 3 * b);
}

template <typename scalar_t>
__global__ void point_grad_kernel(const Moments* __restrict__ moments, const ProcrustesGrad* __restrict__ grads,
                                  const scalar_t* __restrict__ src, const scalar_t* __restrict__ tgt,
                                  const scalar_t* __restrict__ weights, int64_t B, int64_t N,
                                  scalar_t* __restrict__ g_src, scalar_t* __restrict__ g_tgt,
                                  scalar_t* __restrict__ g_w) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * kWarpsPerBlock + threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  if (b >= B) return;  // whole warps exit together
  const Procrustes p = moments[b].unsolved();
  const ProcrustesGrad grad = grads[b];
  const scalar_t *x = src + b * N * 3, *y = tgt + b * N * 3, *w = weights + b * N;
  double weighted_mean = 0;
  for (int64_t i = lane; i < N; i += 32) {
    const double g_what = grad.point(p, x + 3 * i, y + 3 * i, w[i], g_src + (b * N + i) * 3, g_tgt + (b * N + i) * 3);
    g_w[b * N + i] = static_cast<scalar_t>(g_what);
    weighted_mean += w[i] / p.wsum * g_what;
  }
  weighted_mean = warp_sum(weighted_mean);
  for (int64_t i = lane; i < N; i += 32) g_w[b * N + i] = finish_weight_grad(g_w[b * N + i], weighted_mean, p.wsum);
}

const Moments* moments_of(const at::Tensor& moments) {
  return reinterpret_cast<const Moments*>(moments.const_data_ptr<double>());
}

at::Tensor compute_moments(const at::Tensor& src, const at::Tensor& tgt, const at::Tensor& weights) {
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor moments = at::empty({B, kMomentDoubles}, src.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_moments_cuda", [&] {
    moments_kernel<scalar_t><<<blocks_for(B, kWarpsPerBlock), kWarpsPerBlock * 32, 0, current_stream()>>>(
        src.const_data_ptr<scalar_t>(), tgt.const_data_ptr<scalar_t>(), weights.const_data_ptr<scalar_t>(), B, N,
        reinterpret_cast<Moments*>(moments.mutable_data_ptr<double>()));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return moments;
}

std::tuple<at::Tensor, at::Tensor> kabsch_cuda(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                               const at::Tensor& weights_in) {
  check_kabsch_inputs(src_in, tgt_in, weights_in);
  const c10::cuda::CUDAGuard guard(src_in.device());
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  const int64_t B = src.size(0);
  at::Tensor R = at::empty({B, 3, 3}, src.options()), t = at::empty({B, 3}, src.options());
  if (B == 0) return {R, t};
  check_on_device({finite_condition(src, "src"), finite_condition(tgt, "tgt"), finite_condition(weights, "weights"),
                   {weights.min().ge(0), "weights must be non-negative"},
                   {weights.sum(1).min().gt(0),
                    "weights of some batch sum to zero: at least one point per problem needs a positive weight"}});
  const at::Tensor moments = compute_moments(src, tgt, weights);
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_cuda", [&] {
    solve_kernel<scalar_t><<<blocks_for(B, 128), 128, 0, current_stream()>>>(
        moments_of(moments), B, R.mutable_data_ptr<scalar_t>(), t.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {R, t};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> kabsch_backward_cuda(const at::Tensor& gR_in, const at::Tensor& gt_in,
                                                                    const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                                    const at::Tensor& weights_in) {
  check_kabsch_backward_inputs(gR_in, gt_in, src_in, tgt_in, weights_in);
  const c10::cuda::CUDAGuard guard(src_in.device());
  const at::Tensor gR = gR_in.contiguous(), gt = gt_in.contiguous();
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor g_src = at::empty_like(src), g_tgt = at::empty_like(tgt), g_w = at::empty_like(weights);
  if (B == 0) return {g_src, g_tgt, g_w};
  const at::Tensor moments = compute_moments(src, tgt, weights);
  at::Tensor grads = at::empty({B, kGradDoubles}, moments.options());
  ProcrustesGrad* grads_ptr = reinterpret_cast<ProcrustesGrad*>(grads.mutable_data_ptr<double>());
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_backward_cuda", [&] {
    solve_backward_kernel<scalar_t><<<blocks_for(B, 128), 128, 0, current_stream()>>>(
        moments_of(moments), gR.const_data_ptr<scalar_t>(), gt.const_data_ptr<scalar_t>(), B, grads_ptr);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    point_grad_kernel<scalar_t><<<blocks_for(B, kWarpsPerBlock), kWarpsPerBlock * 32, 0, current_stream()>>>(
        moments_of(moments), grads_ptr, src.const_data_ptr<scalar_t>(),
        tgt.const_data_ptr<scalar_t>(), weights.const_data_ptr<scalar_t>(), B, N, g_src.mutable_data_ptr<scalar_t>(),
        g_tgt.mutable_data_ptr<scalar_t>(), g_w.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {g_src, g_tgt, g_w};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CUDA, m) {
  m.impl("kabsch", &kabsch_cuda);
  m.impl("kabsch_backward", &kabsch_backward_cuda);
}

}  // namespace vrnet
