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

}  // namespace vrnet
