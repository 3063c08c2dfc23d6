// Torch glue of the CUDA edge_features op (kernels: edge_features_kernels.cuh).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "edge_features/edge_features.h"
#include "edge_features/edge_features_kernels.cuh"

namespace vrnet {
namespace {

at::Tensor edge_features_cuda(const at::Tensor& x_in, const at::Tensor& idx_in) {
  check_edge_features_inputs(x_in, idx_in);
  VRNET_CUDA_GUARD(x_in);
  const at::Tensor x = x_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = x.size(0), C = x.size(1), N = x.size(2), k = idx.size(2);
  at::Tensor out = at::empty({B, 2 * C, N, k}, x.options());
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "edge_features_cuda", [&] {
    launch<edge_features_kernel<scalar_t>>(per_item(B * C * N * k), x, idx, B, C, N, k, out);
  });
  return out;
}

at::Tensor edge_features_backward_cuda(const at::Tensor& grad_in, const at::Tensor& idx_in, int64_t num_points) {
  check_edge_features_backward_inputs(grad_in, idx_in, num_points);
  VRNET_CUDA_GUARD(grad_in);
  const at::Tensor grad = grad_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = grad.size(0), C = grad.size(1) / 2, N = num_points, k = idx.size(2);
  at::Tensor grad_x = at::empty({B, C, N}, grad.options());
  if (grad_x.numel() == 0) return grad_x;
  const Incidence inc = build_incidence(idx, N);
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "edge_features_backward_cuda", [&] {
    launch<edge_features_backward_kernel<scalar_t>>(per_item(B * C * N), grad, inc.order, inc.row_ptr, B, C, N, k,
                                                    grad_x);
  });
  return grad_x;
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("edge_features", &edge_features_cuda);
  m.impl("edge_features_backward", &edge_features_backward_cuda);
}

}  // namespace vrnet
