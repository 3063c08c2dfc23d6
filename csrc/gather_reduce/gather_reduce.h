// gather_reduce pieces shared by the CPU and CUDA kernels: the reduction kind and argument checks.
#pragma once

#include <string>

#include "edge_features/edge_features.h"

namespace vrnet {

enum class Reduce { kMax, kMin, kSum, kMean };

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

}  // namespace vrnet
