// Argument checks of edge_features shared by the CPU and CUDA kernels.
#pragma once

#include "common/common.h"

namespace vrnet {

// Shapes, dtypes and devices of a feature tensor (B, C, N) and its neighbour graph idx (B, N', k).
inline void check_graph(const at::Tensor& x, const at::Tensor& idx, const char* x_name) {
  check_float(x, x_name);
  check_index(idx, "idx");
  check_dim(x, 3, x_name, "(B, C, N)");
  check_dim(idx, 3, "idx", "(B, N, k)");
  check_same_device(x, x_name, idx, "idx");
  TORCH_CHECK_VALUE(idx.size(0) == x.size(0), "idx batch (", idx.size(0), ") must match ", x_name, " batch (",
                    x.size(0), ")");
  TORCH_CHECK_VALUE(idx.size(2) >= 1, "idx must have k >= 1 neighbours");
  TORCH_CHECK_VALUE(x.size(2) > 0 && idx.size(1) > 0, "empty cloud: ", x_name, " has ", x.size(2), " points");
}

inline void check_edge_features_inputs(const at::Tensor& x, const at::Tensor& idx) {
  check_graph(x, idx, "x");
  TORCH_CHECK_VALUE(idx.size(1) == x.size(2), "idx must have shape (B, N, k) with N = ", x.size(2), ", got ",
                    idx.sizes());
  check_index_range(idx, x.size(2), "idx");
}

// edge_features_backward(grad_out, idx, num_points): grad_out (B, 2C, N, k) of a graph idx (B, N, k).
inline void check_edge_features_backward_inputs(const at::Tensor& grad, const at::Tensor& idx, int64_t num_points) {
  check_float(grad, "grad_out");
  check_index(idx, "idx");
  check_dim(idx, 3, "idx", "(B, N, k)");
  check_dim(grad, 4, "grad_out", "(B, 2C, N, k)");
  check_same_device(grad, "grad_out", idx, "idx");
  TORCH_CHECK_VALUE(num_points == idx.size(1), "num_points must equal the N of idx (", idx.size(1), "), got ",
                    num_points);
  TORCH_CHECK_VALUE(grad.size(1) % 2 == 0 && grad.size(0) == idx.size(0) && grad.size(2) == idx.size(1) &&
                        grad.size(3) == idx.size(2),
                    "grad_out must have shape (B, 2C, N, k) with (B, N, k) = ", idx.sizes(), ", got ", grad.sizes());
  check_index_range(idx, num_points, "idx");
}

}  // namespace vrnet
