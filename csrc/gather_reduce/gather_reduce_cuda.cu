// Torch glue of the CUDA gather_reduce op (kernels: gather_reduce_kernels.cuh).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "gather_reduce/gather_reduce.h"
#include "gather_reduce/gather_reduce_kernels.cuh"

namespace vrnet {
namespace {

template <typename scalar_t, Reduce R>
void launch_gather_reduce(const at::Tensor& values, const at::Tensor& idx, at::Tensor& out, const at::Tensor& arg) {
  const int64_t B = values.size(0), C = values.size(1), M = values.size(2), N = idx.size(1), k = idx.size(2);
  launch<gather_reduce_kernel<scalar_t, R>>(per_item(B * C * N), values, idx, B, C, M, N, k, out, arg);
}

std::tuple<at::Tensor, at::Tensor> gather_reduce_cuda(const at::Tensor& values_in, const at::Tensor& idx_in,
                                                      c10::string_view reduce_name) {
  const Reduce reduce = parse_reduce(reduce_name);
  check_gather_reduce_inputs(values_in, idx_in);
  VRNET_CUDA_GUARD(values_in);
  const at::Tensor values = values_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = values.size(0), C = values.size(1), N = idx.size(1);
  const bool keep_arg = reduce == Reduce::kMax || reduce == Reduce::kMin;
  at::Tensor out = at::empty({B, C, N}, values.options());
  at::Tensor arg = at::empty({keep_arg ? B : 0, C, N}, values.options().dtype(at::kLong));
  if (out.numel() == 0) return {out, arg};
  const at::Tensor arg_out = keep_arg ? arg : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(values.scalar_type(), "gather_reduce_cuda", [&] {
    switch (reduce) {
      case Reduce::kMax: launch_gather_reduce<scalar_t, Reduce::kMax>(values, idx, out, arg_out); break;
      case Reduce::kMin: launch_gather_reduce<scalar_t, Reduce::kMin>(values, idx, out, arg_out); break;
      case Reduce::kSum: launch_gather_reduce<scalar_t, Reduce::kSum>(values, idx, out, arg_out); break;
      case Reduce::kMean: launch_gather_reduce<scalar_t, Reduce::kMean>(values, idx, out, arg_out); break;
    }
  });
  return {out, arg};
}

at::Tensor gather_reduce_backward_cuda(const at::Tensor& grad_in, const at::Tensor& idx_in, const at::Tensor& arg_in,
                                       c10::string_view reduce_name, int64_t num_values) {
  const Reduce reduce = parse_reduce(reduce_name);
  check_gather_reduce_backward_inputs(grad_in, idx_in, arg_in, reduce, num_values);
  VRNET_CUDA_GUARD(grad_in);
  const at::Tensor grad = grad_in.contiguous(), idx = idx_in.contiguous(), arg = arg_in.contiguous();
  const int64_t B = grad.size(0), C = grad.size(1), N = grad.size(2), M = num_values, k = idx.size(2);
  at::Tensor grad_values = at::empty({B, C, M}, grad.options());
  if (grad_values.numel() == 0) return grad_values;
  const Incidence inc = build_incidence(idx, M);
  const bool use_arg = reduce == Reduce::kMax || reduce == Reduce::kMin;
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "gather_reduce_backward_cuda", [&] {
    const scalar_t scale = reduce == Reduce::kMean ? scalar_t(1) / static_cast<scalar_t>(k) : scalar_t(1);
    launch<gather_reduce_backward_kernel<scalar_t>>(per_item(B * C * M), grad, use_arg ? arg : at::Tensor(),
                                                    inc.order, inc.row_ptr, B, C, M, N, k, scale, grad_values);
  });
  return grad_values;
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("gather_reduce", &gather_reduce_cuda);
  m.impl("gather_reduce_backward", &gather_reduce_backward_cuda);
}

}  // namespace vrnet
