// CUDA edge tensor out[b, :, n, j] = [x_idx - x_n ; x_n] (one thread per output element) and its
// backward, which gathers through the inverse graph (one thread per input element, no atomics:
// deterministic).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "edge_features/edge_features.h"

namespace vrnet {
namespace {

template <typename scalar_t>
__global__ void edge_features_kernel(const scalar_t* __restrict__ x, const int64_t* __restrict__ idx, int64_t B,
                                     int64_t C, int64_t N, int64_t k, scalar_t* __restrict__ out) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * N * k) return;
  const int64_t nj = t % (N * k), bc = t / (N * k), b = bc / C, c = bc % C, n = nj / k;
  const scalar_t centre = x[bc * N + n];
  out[(b * 2 * C + c) * N * k + nj] = x[bc * N + idx[b * N * k + nj]] - centre;
  out[(b * 2 * C + C + c) * N * k + nj] = centre;
}

// grad_x[b, c, m] = sum over edges (n, j) into m of g_diff[c, n, j] + sum_j (g_centre[c, m, j] - g_diff[c, m, j]).
template <typename scalar_t>
__global__ void edge_features_backward_kernel(const scalar_t* __restrict__ grad, const int64_t* __restrict__ order,
                                              const int64_t* __restrict__ row_ptr, int64_t B, int64_t C, int64_t N,
                                              int64_t k, scalar_t* __restrict__ grad_x) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * N) return;
  const int64_t m = t % N, bc = t / N, b = bc / C, c = bc % C;
  const scalar_t* g_diff = grad + (b * 2 * C + c) * N * k;
  const scalar_t* g_centre = grad + (b * 2 * C + C + c) * N * k;
  const int64_t* edges = order + b * N * k;
  scalar_t acc = 0;
  for (int64_t e = row_ptr[b * (N + 1) + m]; e < row_ptr[b * (N + 1) + m + 1]; ++e) acc += g_diff[edges[e]];
  for (int64_t j = 0; j < k; ++j) acc += g_centre[m * k + j] - g_diff[m * k + j];
  grad_x[t] = acc;
}

at::Tensor edge_features_cuda(const at::Tensor& x_in, const at::Tensor& idx_in) {
  check_edge_features_inputs(x_in, idx_in);
  const c10::cuda::CUDAGuard guard(x_in.device());
  const at::Tensor x = x_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = x.size(0), C = x.size(1), N = x.size(2), k = idx.size(2);
  at::Tensor out = at::empty({B, 2 * C, N, k}, x.options());
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "edge_features_cuda", [&] {
    edge_features_kernel<scalar_t><<<blocks_for(B * C * N * k), kThreads, 0, current_stream()>>>(
        x.const_data_ptr<scalar_t>(), idx.const_data_ptr<int64_t>(), B, C, N, k, out.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

at::Tensor edge_features_backward_cuda(const at::Tensor& grad_in, const at::Tensor& idx_in, int64_t num_points) {
  check_edge_features_backward_inputs(grad_in, idx_in, num_points);
  const c10::cuda::CUDAGuard guard(grad_in.device());
  const at::Tensor grad = grad_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = grad.size(0), C = grad.size(1) / 2, N = num_points, k = idx.size(2);
  at::Tensor grad_x = at::empty({B, C, N}, grad.options());
  if (grad_x.numel() == 0) return grad_x;
  const Incidence inc = build_incidence(idx, N);
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "edge_features_backward_cuda", [&] {
    edge_features_backward_kernel<scalar_t><<<blocks_for(B * C * N), kThreads, 0, current_stream()>>>(
        grad.const_data_ptr<scalar_t>(), inc.order.const_data_ptr<int64_t>(), inc.row_ptr.const_data_ptr<int64_t>(),
        B, C, N, k, grad_x.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return grad_x;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CUDA, m) {
  m.impl("edge_features", &edge_features_cuda);
  m.impl("edge_features_backward", &edge_features_backward_cuda);
}

}  // namespace vrnet
