// Argument checks of the kabsch op, and the Procrustes math shared by its CPU and CUDA kernels.
#pragma once

#include "common/common.h"
#include "kabsch/procrustes.h"
#include "kabsch/robust.h"

namespace vrnet {

inline void check_kabsch_inputs(const at::Tensor& src, const at::Tensor& tgt, const at::Tensor& weights) {
  check_float(src, "src");
  check_float(tgt, "tgt");
  check_float(weights, "weights");
  TORCH_CHECK_VALUE(src.dim() == 3 && src.size(2) == 3, "src must have shape (B, N, 3), got ", src.sizes());
  TORCH_CHECK_VALUE(tgt.sizes() == src.sizes(), "tgt must have the shape of src ", src.sizes(), ", got ", tgt.sizes());
  TORCH_CHECK_VALUE(weights.dim() == 2 && weights.size(0) == src.size(0) && weights.size(1) == src.size(1),
                    "weights must have shape (B, N) = (", src.size(0), ", ", src.size(1), "), got ", weights.sizes());
  check_same_device(src, "src", tgt, "tgt");
  check_same_device(src, "src", weights, "weights");
  TORCH_CHECK_TYPE(src.scalar_type() == tgt.scalar_type() && src.scalar_type() == weights.scalar_type(),
                   "src, tgt and weights must share a dtype");
  TORCH_CHECK_VALUE(src.size(1) >= 3, "src needs at least 3 points per cloud, got ", src.size(1));
}

// kabsch_backward(grad_R, grad_t, src, tgt, weights): the forward's inputs and gradients of its outputs.
inline void check_kabsch_backward_inputs(const at::Tensor& grad_R, const at::Tensor& grad_t, const at::Tensor& src,
                                         const at::Tensor& tgt, const at::Tensor& weights) {
  check_kabsch_inputs(src, tgt, weights);
  check_like(grad_R, "grad_R", {src.size(0), 3, 3}, src, "src");
  check_like(grad_t, "grad_t", {src.size(0), 3}, src, "src");
}

constexpr int64_t kMaxRobustIterations = 1000;

// robust_kabsch(src, tgt, weights, iterations, kernel, scale, min_scale): the kabsch inputs and the
// reweighting options, checked and parsed.
inline RobustOptions check_robust_kabsch_inputs(const at::Tensor& src, const at::Tensor& tgt, const at::Tensor& weights,
                                                int64_t iterations, c10::string_view kernel, double scale,
                                                double min_scale) {
  check_kabsch_inputs(src, tgt, weights);
  TORCH_CHECK_VALUE(iterations >= 0 && iterations <= kMaxRobustIterations, "iterations must be in [0, ",
                    kMaxRobustIterations, "], got ", iterations);
  TORCH_CHECK_VALUE(std::isfinite(scale) && scale > 0, "scale must be a positive finite number, got ", scale);
  TORCH_CHECK_VALUE(std::isfinite(min_scale) && min_scale > 0, "min_scale must be a positive finite number, got ",
                    min_scale);
  RobustKernel parsed;
  if (kernel == "cauchy") {
    parsed = RobustKernel::kCauchy;
  } else if (kernel == "geman_mcclure") {
    parsed = RobustKernel::kGemanMcClure;
  } else if (kernel == "welsch") {
    parsed = RobustKernel::kWelsch;
  } else {
    TORCH_CHECK_VALUE(false, "kernel must be one of cauchy, geman_mcclure, welsch, got ", kernel);
  }
  return {parsed, scale, min_scale, iterations};
}

}  // namespace vrnet
