// Argument checks of the svd3x3 op, and the math shared by its CPU and CUDA kernels.
#pragma once

#include "common/common.h"
#include "svd3x3/svd3x3_math.h"

namespace vrnet {

inline void check_svd3x3_input(const at::Tensor& A) {
  check_float(A, "A");
  TORCH_CHECK_VALUE(A.dim() == 3 && A.size(1) == 3 && A.size(2) == 3, "A must have shape (B, 3, 3), got ", A.sizes());
}

// svd3x3_backward(grad_U, grad_S, grad_V, U, S, V): the forward's outputs and their gradients.
inline void check_svd3x3_backward_inputs(const at::Tensor& gU, const at::Tensor& gS, const at::Tensor& gV,
                                         const at::Tensor& U, const at::Tensor& S, const at::Tensor& V) {
  check_svd3x3_input(U);
  const int64_t B = U.size(0);
  check_like(V, "V", {B, 3, 3}, U, "U");
  check_like(S, "S", {B, 3}, U, "U");
  check_like(gU, "grad_U", {B, 3, 3}, U, "U");
  check_like(gV, "grad_V", {B, 3, 3}, U, "U");
  check_like(gS, "grad_S", {B, 3}, U, "U");
}

}  // namespace vrnet
