// Torch glue of the CUDA pairwise_distance_loss op (kernels: pairwise_distance_loss_kernels.cuh).
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "pairwise_distance_loss/pairwise_distance_loss.h"
#include "pairwise_distance_loss/pairwise_distance_loss_kernels.cuh"

namespace vrnet {
namespace {

void check_batch(int64_t B) {
  TORCH_CHECK_VALUE(B <= 65535, "x must have at most 65535 clouds per call on CUDA, got ", B);
}

LaunchConfig row_blocks(int64_t N, int64_t B) {
  return {dim3(blocks_for(N, kPdlRowsPerBlock), static_cast<unsigned int>(B)), dim3(kPdlRowsPerBlock), 0};
}

at::Tensor pairwise_distance_loss_cuda(const at::Tensor& x_in, const at::Tensor& y_in) {
  check_pairwise_distance_loss_inputs(x_in, y_in);
  VRNET_CUDA_GUARD(x_in);
  const at::Tensor x = x_in.contiguous(), y = y_in.contiguous();
  const int64_t B = x.size(0), N = x.size(1);
  check_batch(B);
  if (B == 0) return at::empty({0}, x.options());
  if (device_values_checked()) check_on_device({finite_condition(x, "x"), finite_condition(y, "y")});
  const LaunchConfig config = row_blocks(N, B);
  at::Tensor partial = at::empty({B, config.grid.x}, x.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "pairwise_distance_loss_cuda", [&] {
    launch<pdl_forward_kernel<scalar_t>>(config, x, y, N, partial);
  });
  // Over ordered pairs (both i < j and j < i): the same mean as the CPU kernel's 2 * upper / N^2.
  return partial.sum(1).div(double(N) * double(N)).sqrt().to(x.scalar_type());
}

std::tuple<at::Tensor, at::Tensor> pairwise_distance_loss_backward_cuda(const at::Tensor& grad_in,
                                                                        const at::Tensor& x_in, const at::Tensor& y_in,
                                                                        const at::Tensor& loss_in) {
  check_pairwise_distance_loss_backward_inputs(grad_in, x_in, y_in, loss_in);
  VRNET_CUDA_GUARD(x_in);
  const at::Tensor grad = grad_in.contiguous(), x = x_in.contiguous(), y = y_in.contiguous();
  const at::Tensor loss = loss_in.contiguous();
  const int64_t B = x.size(0), N = x.size(1);
  check_batch(B);
  at::Tensor gx = at::empty_like(x), gy = at::empty_like(y);
  if (B == 0) return {gx, gy};
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "pairwise_distance_loss_backward_cuda", [&] {
    launch<pdl_backward_kernel<scalar_t>>(row_blocks(N, B), grad, x, y, loss, N, gx, gy);
  });
  return {gx, gy};
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("pairwise_distance_loss", &pairwise_distance_loss_cuda);
  m.impl("pairwise_distance_loss_backward", &pairwise_distance_loss_backward_cuda);
}

}  // namespace vrnet
