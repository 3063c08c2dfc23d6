// Argument checks of pairwise_distance_loss shared by the CPU and CUDA kernels.
#pragma once

#include "common/common.h"

namespace vrnet {

inline void check_pairwise_distance_loss_inputs(const at::Tensor& x, const at::Tensor& y) {
  check_float(x, "x");
  check_float(y, "y");
  TORCH_CHECK_VALUE(x.dim() == 3 && x.size(2) == 3, "x must have shape (B, N, 3), got ", x.sizes());
  TORCH_CHECK_VALUE(y.sizes() == x.sizes(), "y must have the shape of x ", x.sizes(), ", got ", y.sizes());
  check_same_device(x, "x", y, "y");
  TORCH_CHECK_TYPE(x.scalar_type() == y.scalar_type(), "x and y must share a dtype");
  TORCH_CHECK_VALUE(x.size(1) >= 2, "x needs at least 2 points per cloud, got ", x.size(1));
}

// pairwise_distance_loss_backward(grad_loss, x, y, loss): grad_loss and loss are (B,).
inline void check_pairwise_distance_loss_backward_inputs(const at::Tensor& grad, const at::Tensor& x,
                                                         const at::Tensor& y, const at::Tensor& loss) {
  check_pairwise_distance_loss_inputs(x, y);
  check_like(grad, "grad_loss", {x.size(0)}, x, "x");
  check_like(loss, "loss", {x.size(0)}, x, "x");
}

}  // namespace vrnet
