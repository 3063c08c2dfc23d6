// edge_norm_max: EdgeConv's tail after its one projection, as one op.
//
// projections (B, 2O, N): channels [0, O) hold a = W1 x (the neighbour term), channels [O, 2O)
// b = (W2 - W1) x (the centre term), so edge (n, j) of the graph idx (B, N, k) has the value
// z = a[idx[n, j]] + b[n]. The op returns
//   out[b, o, n] = leaky_relu(max_j (scale_o * (z - mean_o) + bias_o)),   scale_o = weight_o / sqrt(var_o + eps),
// i.e. BatchNorm over the (B, N, k) edges of each channel, LeakyReLU, max over the neighbours, without
// the (B, O, N, k) edge tensor: the normalisation and the LeakyReLU are monotone per channel, so the max
// over j is taken of a where scale_o >= 0 (the sign of weight_o) and the min where it is negative.
// Batch statistics (biased variance) are used when no running statistics are given.
#pragma once

#include <limits>

#include "edge_features/edge_features.h"

namespace vrnet {

// Checks of the optional per-channel tensors (weight, bias, running_mean, running_var): (O,), the
// dtype and device of projections.
inline void check_channel_vector(const c10::optional<at::Tensor>& t, const char* name, const at::Tensor& projections,
                                 int64_t channels) {
  if (!t.has_value()) return;
  check_like(*t, name, {channels}, projections, "projections");
}

// projections (B, 2O, N) and a graph idx (B, N, k) into its N points; eps > 0.
inline void check_projections_graph(const at::Tensor& projections, const at::Tensor& idx, double eps) {
  check_graph(projections, idx, "projections");
  TORCH_CHECK_VALUE(projections.size(1) % 2 == 0 && projections.size(1) > 0,
                    "projections must have shape (B, 2O, N) (neighbour terms, then centre terms), got ",
                    projections.sizes());
  TORCH_CHECK_VALUE(idx.size(1) == projections.size(2), "idx must have shape (B, N, k) with N = ",
                    projections.size(2), ", got ", idx.sizes());
  TORCH_CHECK_VALUE(eps > 0 && std::isfinite(eps), "eps must be a finite number > 0, got ", eps);
  check_index_range(idx, projections.size(2), "idx");
}

// The max over neighbours is taken before the LeakyReLU, which is exact only for an increasing one.
inline void check_negative_slope(double negative_slope) {
  TORCH_CHECK_VALUE(std::isfinite(negative_slope) && negative_slope >= 0,
                    "negative_slope must be a finite number >= 0 (the max is taken before the activation), got ",
                    negative_slope);
}

inline void check_edge_norm_max_inputs(const at::Tensor& projections, const at::Tensor& idx,
                                       const c10::optional<at::Tensor>& weight, const c10::optional<at::Tensor>& bias,
                                       const c10::optional<at::Tensor>& running_mean,
                                       const c10::optional<at::Tensor>& running_var, double eps) {
  check_projections_graph(projections, idx, eps);
  TORCH_CHECK_VALUE(running_mean.has_value() == running_var.has_value(),
                    "running_mean and running_var must be given together");
  const int64_t channels = projections.size(1) / 2;
  check_channel_vector(weight, "weight", projections, channels);
  check_channel_vector(bias, "bias", projections, channels);
  check_channel_vector(running_mean, "running_mean", projections, channels);
  check_channel_vector(running_var, "running_var", projections, channels);
  TORCH_CHECK_VALUE(running_mean.has_value() || idx.size(0) * idx.size(1) * idx.size(2) > 1,
                    "batch statistics need more than one edge per channel, got idx of shape ", idx.sizes());
}

// edge_norm_max_backward(grad_out, projections, idx, arg, weight, bias, mean, var, batch_stats, eps,
// negative_slope): grad_out and arg (B, O, N) (arg: int32, the winning slot in [0, k)), mean and var
// (O,) float64 as the forward returned them (the mean of a constant channel is exact, so its
// deviations are exactly 0).
inline void check_edge_norm_max_backward_inputs(const at::Tensor& grad, const at::Tensor& projections,
                                                const at::Tensor& idx, const at::Tensor& arg,
                                                const c10::optional<at::Tensor>& weight,
                                                const c10::optional<at::Tensor>& bias, const at::Tensor& mean,
                                                const at::Tensor& var, double eps) {
  check_projections_graph(projections, idx, eps);
  const int64_t B = projections.size(0), O = projections.size(1) / 2, N = projections.size(2);
  check_channel_vector(weight, "weight", projections, O);
  check_channel_vector(bias, "bias", projections, O);
  const auto check_statistic = [&](const at::Tensor& stat, const char* name) {
    TORCH_CHECK_VALUE(stat.dim() == 1 && stat.size(0) == O, name, " must have shape (", O, ",), got ", stat.sizes());
    TORCH_CHECK_TYPE(stat.scalar_type() == at::kDouble, name, " must be float64 (as the forward returns it), got ",
                     stat.scalar_type());
    check_same_device(projections, "projections", stat, name);
  };
  check_statistic(mean, "mean");
  check_statistic(var, "var");
  check_like(grad, "grad_out", {B, O, N}, projections, "projections");
  TORCH_CHECK_TYPE(arg.scalar_type() == at::kInt, "arg must be int32, got ", arg.scalar_type());
  check_same_device(projections, "projections", arg, "arg");
  TORCH_CHECK_VALUE(arg.sizes() == grad.sizes(), "arg must have shape ", grad.sizes(), ", got ", arg.sizes());
  TORCH_CHECK_VALUE(idx.size(1) * idx.size(2) <= std::numeric_limits<int32_t>::max(),
                    "idx has too many edges per batch for the backward (N * k must be < 2^31), got ", idx.sizes());
  const int64_t k = idx.size(2);
  if (!arg.is_cpu()) {
    if (arg.numel() == 0 || !device_values_checked()) return;
    const auto [lo, hi] = at::aminmax(arg);
    check_on_device({{lo.ge(0).logical_and(hi.lt(k)), "arg holds slots outside [0, " + std::to_string(k) + ")"}});
    return;
  }
  const at::Tensor slots = arg.contiguous();
  const int32_t* p = slots.const_data_ptr<int32_t>();
  std::atomic<bool> bad{false};
  parallel_ranges(slots.numel(), 1 << 16, [&](int64_t begin, int64_t end) {
    bool local = false;
    for (int64_t i = begin; i < end; ++i) local |= (p[i] < 0) | (p[i] >= k);
    if (local) bad.store(true, std::memory_order_relaxed);
  });
  TORCH_CHECK_VALUE(!bad.load(), "arg holds slots outside [0, ", k, ")");
}

// An optional per-channel tensor, contiguous, or an undefined tensor (a null pointer to a kernel).
inline at::Tensor contiguous_or_undefined(const c10::optional<at::Tensor>& t) {
  return t.has_value() ? t->contiguous() : at::Tensor();
}

// The backward's arguments checked, in the point-major (B, N, .) layout both kernels read (copies
// of the (B, ., N) arguments; free for the forward's own outputs); weight and bias undefined when
// not given.
struct EdgeNormMaxBackwardArgs {
  at::Tensor grad, points, arg, idx, mean, var, weight, bias;
};

inline EdgeNormMaxBackwardArgs checked_edge_norm_max_backward_args(
    const at::Tensor& grad, const at::Tensor& projections, const at::Tensor& idx, const at::Tensor& arg,
    const c10::optional<at::Tensor>& weight, const c10::optional<at::Tensor>& bias, const at::Tensor& mean,
    const at::Tensor& var, double eps, double negative_slope) {
  check_edge_norm_max_backward_inputs(grad, projections, idx, arg, weight, bias, mean, var, eps);
  check_negative_slope(negative_slope);
  return {grad.transpose(1, 2).contiguous(), projections.transpose(1, 2).contiguous(), arg.transpose(1, 2).contiguous(),
          idx.contiguous(), mean.contiguous(), var.contiguous(), contiguous_or_undefined(weight),
          contiguous_or_undefined(bias)};
}

}  // namespace vrnet
