// Torch glue of the CUDA edge_norm_max op (kernels: edge_norm_max_kernels.cuh).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "edge_norm_max/edge_norm_max.h"
#include "edge_norm_max/edge_norm_max_kernels.cuh"

namespace vrnet {
namespace {

// A tile block: 32 channels x kTileRows rows, one block per (channel group, tile of points).
LaunchConfig tile_blocks(int64_t points, int64_t O) {
  return {dim3(blocks_for(O, kTileChannels), blocks_for(points, kTilePoints)), dim3(kTileChannels, kTileRows), 0};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> edge_norm_max_cuda(
    const at::Tensor& projections_in, const at::Tensor& idx_in, const c10::optional<at::Tensor>& weight_in,
    const c10::optional<at::Tensor>& bias_in, const c10::optional<at::Tensor>& running_mean_in,
    const c10::optional<at::Tensor>& running_var_in, double eps, double negative_slope) {
  check_edge_norm_max_inputs(projections_in, idx_in, weight_in, bias_in, running_mean_in, running_var_in, eps);
  check_negative_slope(negative_slope);
  VRNET_CUDA_GUARD(projections_in);
  const at::Tensor points = projections_in.transpose(1, 2).contiguous();  // (B, N, 2O); free if point-major
  const at::Tensor idx = idx_in.contiguous();
  const at::Tensor weight = contiguous_or_undefined(weight_in), bias = contiguous_or_undefined(bias_in);
  const int64_t B = points.size(0), N = points.size(1), O = points.size(2) / 2, k = idx.size(2);
  const bool batch_stats = !running_mean_in.has_value();
  at::Tensor out = at::empty({B, N, O}, points.options());
  at::Tensor arg = at::empty({B, N, O}, points.options().dtype(at::kInt));
  const at::TensorOptions doubles = points.options().dtype(at::kDouble);
  at::Tensor mean = batch_stats ? at::empty({O}, doubles) : running_mean_in->to(at::kDouble).contiguous();
  at::Tensor var = batch_stats ? at::empty({O}, doubles) : running_var_in->to(at::kDouble).contiguous();
  if (out.numel() == 0) return {out.transpose(1, 2), mean, var, arg.transpose(1, 2)};
  const int64_t tiles = blocks_for(B * N, kTilePoints);
  at::Tensor shift, sums, squares;  // per tile and channel, batch statistics only
  if (batch_stats) {
    shift = at::empty({tiles, O}, doubles), sums = at::empty({tiles, O}, doubles);
    squares = at::empty({tiles, O}, doubles);
  }
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "edge_norm_max_cuda", [&] {
    launch<edge_norm_max_neighbours_kernel<scalar_t>>(tile_blocks(B * N, O), points, idx, weight, B, N, O, k, out, arg,
                                                      shift, sums, squares);
    if (batch_stats)
      launch<edge_norm_max_statistics_kernel>(per_item(O, 128), shift, sums, squares, B * N, O, k, mean, var);
    launch<edge_norm_max_output_kernel<scalar_t>>(per_item(B * N * O), points, weight, bias, mean, var, B * N, O, eps,
                                                  negative_slope, out);
  });
  return {out.transpose(1, 2), mean, var, arg.transpose(1, 2)};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> edge_norm_max_backward_cuda(
    const at::Tensor& grad_in, const at::Tensor& projections_in, const at::Tensor& idx_in, const at::Tensor& arg_in,
    const c10::optional<at::Tensor>& weight_in, const c10::optional<at::Tensor>& bias_in, const at::Tensor& mean_in,
    const at::Tensor& var_in, bool batch_stats, double eps, double negative_slope) {
  VRNET_CUDA_GUARD(projections_in);
  const EdgeNormMaxBackwardArgs a = checked_edge_norm_max_backward_args(
      grad_in, projections_in, idx_in, arg_in, weight_in, bias_in, mean_in, var_in, eps, negative_slope);
  const at::Tensor &grad = a.grad, &points = a.points, &arg = a.arg, &idx = a.idx, &mean = a.mean, &var = a.var;
  const at::Tensor &weight = a.weight, &bias = a.bias;
  const int64_t B = points.size(0), N = points.size(1), O = points.size(2) / 2, k = idx.size(2);
  at::Tensor grad_points = at::empty(points.sizes(), points.options());
  at::Tensor grad_weight = at::empty({O}, points.options()), grad_bias = at::empty({O}, points.options());
  if (grad_points.numel() == 0) return {grad_points.transpose(1, 2), grad_weight.zero_(), grad_bias.zero_()};
  const at::TensorOptions doubles = points.options().dtype(at::kDouble);
  const int64_t tiles = blocks_for(B * N, kTilePoints);
  at::Tensor gh = at::empty({B, N, O}, points.options());
  at::Tensor tile_g = at::empty({tiles, O}, doubles), tile_gx = at::empty({tiles, O}, doubles);
  at::Tensor per_edge = at::empty({O}, doubles), per_deviation = at::empty({O}, doubles);
  const Incidence inverse = build_incidence(idx, N);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "edge_norm_max_backward_cuda", [&] {
    launch<edge_norm_max_winners_kernel<scalar_t>>(tile_blocks(B * N, O), grad, points, idx, arg, weight, bias, mean,
                                                   var, B, N, O, k, eps, negative_slope, gh, tile_g, tile_gx);
    launch<edge_norm_max_channel_grads_kernel<scalar_t>>(per_item(O, 128), tile_g, tile_gx, weight, var, B * N, O, k,
                                                         eps, batch_stats, grad_weight, grad_bias, per_edge,
                                                         per_deviation);
    launch<edge_norm_max_input_grad_kernel<scalar_t>>(per_item(B * N * O), points, idx, arg, gh, inverse.order,
                                                      inverse.row_ptr, mean, per_edge, per_deviation, B, N, O, k,
                                                      batch_stats, grad_points);
  });
  return {grad_points.transpose(1, 2), grad_weight, grad_bias};
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("edge_norm_max", &edge_norm_max_cuda);
  m.impl("edge_norm_max_backward", &edge_norm_max_backward_cuda);
}

}  // namespace vrnet
