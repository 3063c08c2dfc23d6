// gather_reduce pieces shared by the CPU and CUDA kernels: the reduction kind and argument checks.
#pragma once

#include <string>

#include "edge_features/edge_features.h"
#include "gather_reduce/reduce.h"

namespace vrnet {

inline Reduce parse_reduce(c10::string_view name) {
  if (name == "max") return Reduce::kMax;
  if (name == "min") return Reduce::kMin;
  if (name == "sum") return Reduce::kSum;
  if (name == "mean") return Reduce::kMean;
  TORCH_CHECK_VALUE(false, "reduce must be one of 'max', 'min', 'sum', 'mean', got '", std::string(name), "'");
}

inline void check_gather_reduce_inputs(const at::Tensor& values, const at::Tensor& idx) {
  check_graph(values, idx, "values");
  check_index_range(idx, values.size(2), "idx");
}

// gather_reduce_backward(grad_out, idx, arg, reduce, num_values): grad_out (B, C, N) of a graph
// idx (B, N, k) into num_values points; for max/min, arg (B, C, N) holds the winning slot in [0, k).
inline void check_gather_reduce_backward_inputs(const at::Tensor& grad, const at::Tensor& idx, const at::Tensor& arg,
                                                Reduce reduce, int64_t num_values) {
  check_float(grad, "grad_out");
  check_index(idx, "idx");
  check_dim(idx, 3, "idx", "(B, N, k)");
  check_dim(grad, 3, "grad_out", "(B, C, N)");
  check_same_device(grad, "grad_out", idx, "idx");
  TORCH_CHECK_VALUE(num_values >= 1, "num_values must be >= 1, got ", num_values);
  TORCH_CHECK_VALUE(grad.size(0) == idx.size(0) && grad.size(2) == idx.size(1),
                    "grad_out must have shape (B, C, N) with (B, N) = (", idx.size(0), ", ", idx.size(1), "), got ",
                    grad.sizes());
  check_index_range(idx, num_values, "idx");
  if (reduce == Reduce::kMax || reduce == Reduce::kMin) {
    check_index(arg, "arg");
    check_same_device(grad, "grad_out", arg, "arg");
    TORCH_CHECK_VALUE(arg.sizes() == grad.sizes(), "arg must have the shape of grad_out ", grad.sizes(), ", got ",
                      arg.sizes());
    check_index_range(arg, idx.size(2), "arg");
  }
}

}  // namespace vrnet
