// Torch glue of the CUDA kabsch op (kernels: kabsch_kernels.cuh).
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "kabsch/kabsch.h"
#include "kabsch/kabsch_kernels.cuh"

namespace vrnet {
namespace {

LaunchConfig per_problem_warp(int64_t B) {
  return {dim3(blocks_for(B, kKabschWarpsPerBlock)), dim3(kKabschWarpsPerBlock * 32), 0};
}

at::Tensor compute_moments(const at::Tensor& src, const at::Tensor& tgt, const at::Tensor& weights) {
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor moments = at::empty({B, kMomentDoubles}, src.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_moments_cuda", [&] {
    launch<kabsch_moments_kernel<scalar_t>>(per_problem_warp(B), src, tgt, weights, B, N, moments);
  });
  return moments;
}

// Finite inputs, per problem non-negative weights with a positive sum (one synchronisation).
void check_forward_on_device(const at::Tensor& src, const at::Tensor& tgt, const at::Tensor& weights) {
  if (!device_values_checked()) return;
  check_on_device({finite_condition(src, "src"), finite_condition(tgt, "tgt"), finite_condition(weights, "weights"),
                   {weights.min().ge(0), "weights must be non-negative"},
                   {weights.sum(1).min().gt(0),
                    "weights of some batch sum to zero: at least one point per problem needs a positive weight"}});
}

std::tuple<at::Tensor, at::Tensor> kabsch_cuda(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                               const at::Tensor& weights_in) {
  check_kabsch_inputs(src_in, tgt_in, weights_in);
  VRNET_CUDA_GUARD(src_in);
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  const int64_t B = src.size(0);
  at::Tensor R = at::empty({B, 3, 3}, src.options()), t = at::empty({B, 3}, src.options());
  if (B == 0) return {R, t};
  check_forward_on_device(src, tgt, weights);
  const at::Tensor moments = compute_moments(src, tgt, weights);
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_cuda", [&] {
    launch<kabsch_solve_kernel<scalar_t>>(per_item(B, 128), moments, B, R, t);
  });
  return {R, t};
}

std::tuple<at::Tensor, at::Tensor> robust_kabsch_cuda(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                      const at::Tensor& weights_in, int64_t iterations,
                                                      c10::string_view kernel, double scale, double min_scale) {
  const RobustOptions options =
      check_robust_kabsch_inputs(src_in, tgt_in, weights_in, iterations, kernel, scale, min_scale);
  VRNET_CUDA_GUARD(src_in);
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor R = at::empty({B, 3, 3}, src.options()), t = at::empty({B, 3}, src.options());
  if (B == 0) return {R, t};
  check_forward_on_device(src, tgt, weights);
  const int64_t scratch_per_problem = options.iterations > 0 ? N : 0;
  at::Tensor residuals = at::empty({B, scratch_per_problem}, src.options().dtype(at::kDouble));
  at::Tensor robust_weights = at::empty({B, scratch_per_problem}, src.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "robust_kabsch_cuda", [&] {
    launch<robust_kabsch_kernel<scalar_t>>(LaunchConfig{dim3(blocks_for(B, 1)), dim3(kRobustThreads), 0}, src, tgt,
                                           weights, B, N, options, residuals, robust_weights, R, t);
  });
  return {R, t};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> kabsch_backward_cuda(const at::Tensor& gR_in, const at::Tensor& gt_in,
                                                                    const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                                    const at::Tensor& weights_in) {
  check_kabsch_backward_inputs(gR_in, gt_in, src_in, tgt_in, weights_in);
  VRNET_CUDA_GUARD(src_in);
  const at::Tensor gR = gR_in.contiguous(), gt = gt_in.contiguous();
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor g_src = at::empty_like(src), g_tgt = at::empty_like(tgt), g_w = at::empty_like(weights);
  if (B == 0) return {g_src, g_tgt, g_w};
  const at::Tensor moments = compute_moments(src, tgt, weights);
  at::Tensor grads = at::empty({B, kGradDoubles}, moments.options());
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_backward_cuda", [&] {
    launch<kabsch_solve_backward_kernel<scalar_t>>(per_item(B, 128), moments, gR, gt, B, grads);
    launch<kabsch_point_grad_kernel<scalar_t>>(per_problem_warp(B), moments, grads, src, tgt, weights, B, N, g_src,
                                               g_tgt, g_w);
  });
  return {g_src, g_tgt, g_w};
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("kabsch", &kabsch_cuda);
  m.impl("kabsch_backward", &kabsch_backward_cuda);
  m.impl("robust_kabsch", &robust_kabsch_cuda);
}

}  // namespace vrnet
