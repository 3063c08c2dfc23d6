// CUDA batched 3x3 SVD: one thread per matrix running the shared double-precision Jacobi routine
// (svd3x3/svd3x3.h), and its backward, likewise one thread per matrix.
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "svd3x3/svd3x3.h"

namespace vrnet {
namespace {

template <typename scalar_t>
__global__ void svd3x3_kernel(const scalar_t* __restrict__ A, int64_t B, scalar_t* __restrict__ U,
                              scalar_t* __restrict__ S, scalar_t* __restrict__ V) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b < B) svd3x3_one(A + 9 * b, U + 9 * b, S + 3 * b, V + 9 * b);
}

template <typename scalar_t>
__global__ void svd3x3_backward_kernel(const scalar_t* __restrict__ gU, const scalar_t* __restrict__ gS,
                                       const scalar_t* __restrict__ gV, const scalar_t* __restrict__ U,
                                       const scalar_t* __restrict__ S, const scalar_t* __restrict__ V, int64_t B,
                                       scalar_t* __restrict__ gA) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b < B) svd3x3_backward_one(gU + 9 * b, gS + 3 * b, gV + 9 * b, U + 9 * b, S + 3 * b, V + 9 * b, gA + 9 * b);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> svd3x3_cuda(const at::Tensor& A_in) {
  check_svd3x3_input(A_in);
  const c10::cuda::CUDAGuard guard(A_in.device());
  const at::Tensor A = A_in.contiguous();
  check_finite(A, "A");
  const int64_t B = A.size(0);
  at::Tensor U = at::empty({B, 3, 3}, A.options()), V = at::empty({B, 3, 3}, A.options());
  at::Tensor S = at::empty({B, 3}, A.options());
  if (B == 0) return {U, S, V};
  AT_DISPATCH_FLOATING_TYPES(A.scalar_type(), "svd3x3_cuda", [&] {
    svd3x3_kernel<scalar_t><<<blocks_for(B, 128), 128, 0, current_stream()>>>(
        A.const_data_ptr<scalar_t>(), B, U.mutable_data_ptr<scalar_t>(), S.mutable_data_ptr<scalar_t>(),
        V.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {U, S, V};
}

at::Tensor svd3x3_backward_cuda(const at::Tensor& gU_in, const at::Tensor& gS_in, const at::Tensor& gV_in,
                                const at::Tensor& U_in, const at::Tensor& S_in, const at::Tensor& V_in) {
  check_svd3x3_backward_inputs(gU_in, gS_in, gV_in, U_in, S_in, V_in);
  const c10::cuda::CUDAGuard guard(U_in.device());
  const at::Tensor gU = gU_in.contiguous(), gS = gS_in.contiguous(), gV = gV_in.contiguous();
  const at::Tensor U = U_in.contiguous(), S = S_in.contiguous(), V = V_in.contiguous();
  const int64_t B = U.size(0);
  at::Tensor gA = at::empty({B, 3, 3}, U.options());
  if (B == 0) return gA;
  AT_DISPATCH_FLOATING_TYPES(U.scalar_type(), "svd3x3_backward_cuda", [&] {
    svd3x3_backward_kernel<scalar_t><<<blocks_for(B, 128), 128, 0, current_stream()>>>(
        gU.const_data_ptr<scalar_t>(), gS.const_data_ptr<scalar_t>(), gV.const_data_ptr<scalar_t>(),
        U.const_data_ptr<scalar_t>(), S.const_data_ptr<scalar_t>(), V.const_data_ptr<scalar_t>(), B,
        gA.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return gA;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CUDA, m) {
  m.impl("svd3x3", &svd3x3_cuda);
  m.impl("svd3x3_backward", &svd3x3_backward_cuda);
}

}  // namespace vrnet
