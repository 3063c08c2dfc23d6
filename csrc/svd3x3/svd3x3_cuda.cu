// Torch glue of the CUDA svd3x3 op (kernels: svd3x3_kernels.cuh).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "svd3x3/svd3x3.h"
#include "svd3x3/svd3x3_kernels.cuh"

namespace vrnet {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> svd3x3_cuda(const at::Tensor& A_in) {
  check_svd3x3_input(A_in);
  VRNET_CUDA_GUARD(A_in);
  const at::Tensor A = A_in.contiguous();
  check_finite(A, "A");
  const int64_t B = A.size(0);
  at::Tensor U = at::empty({B, 3, 3}, A.options()), V = at::empty({B, 3, 3}, A.options());
  at::Tensor S = at::empty({B, 3}, A.options());
  if (B == 0) return {U, S, V};
  AT_DISPATCH_FLOATING_TYPES(A.scalar_type(), "svd3x3_cuda", [&] {
    launch<svd3x3_kernel<scalar_t>>(per_item(B, 128), A, B, U, S, V);
  });
  return {U, S, V};
}

at::Tensor svd3x3_backward_cuda(const at::Tensor& gU_in, const at::Tensor& gS_in, const at::Tensor& gV_in,
                                const at::Tensor& U_in, const at::Tensor& S_in, const at::Tensor& V_in) {
  check_svd3x3_backward_inputs(gU_in, gS_in, gV_in, U_in, S_in, V_in);
  VRNET_CUDA_GUARD(U_in);
  const at::Tensor gU = gU_in.contiguous(), gS = gS_in.contiguous(), gV = gV_in.contiguous();
  const at::Tensor U = U_in.contiguous(), S = S_in.contiguous(), V = V_in.contiguous();
  const int64_t B = U.size(0);
  at::Tensor gA = at::empty({B, 3, 3}, U.options());
  if (B == 0) return gA;
  AT_DISPATCH_FLOATING_TYPES(U.scalar_type(), "svd3x3_backward_cuda", [&] {
    launch<svd3x3_backward_kernel<scalar_t>>(per_item(B, 128), gU, gS, gV, U, S, V, B, gA);
  });
  return gA;
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("svd3x3", &svd3x3_cuda);
  m.impl("svd3x3_backward", &svd3x3_backward_cuda);
}

}  // namespace vrnet
