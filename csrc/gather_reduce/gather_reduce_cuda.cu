// CUDA fused neighbour gather + reduction, one thread per output (b, c, n); max/min keep the first
// winning neighbour slot (or the first NaN) exactly as the CPU kernel. The backward gathers through
// the inverse graph, one thread per value (b, c, m), so it has no atomics and is deterministic.
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "gather_reduce/gather_reduce.h"

namespace vrnet {
namespace {

template <typename scalar_t, Reduce R>
__global__ void gather_reduce_kernel(const scalar_t* __restrict__ values, const int64_t* __restrict__ idx, int64_t B,
                                     int64_t C, int64_t M, int64_t N, int64_t k, scalar_t* __restrict__ out,
                                     int64_t* __restrict__ arg) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * N) return;
  const int64_t n = t % N, bc = t / N, b = bc / C;
  const scalar_t* row = values + bc * M;
  const int64_t* nb = idx + (b * N + n) * k;
  if constexpr (R == Reduce::kMax || R == Reduce::kMin) {
    scalar_t best_v = row[nb[0]];
    int64_t best = 0;
    bool has_nan = best_v != best_v;
    for (int64_t j = 1; j < k && !has_nan; ++j) {
      const scalar_t v = row[nb[j]];
      if (v != v) {
        has_nan = true;
        best_v = v;
        best = j;
      } else if (R == Reduce::kMax ? v > best_v : v < best_v) {
        best_v = v;
        best = j;
      }
    }
    out[t] = best_v;
    arg[t] = best;
  } else {
    scalar_t acc = 0;
    for (int64_t j = 0; j < k; ++j) acc += row[nb[j]];
    out[t] = R == Reduce::kMean ? acc / static_cast<scalar_t>(k) : acc;
  }
}

// grad_values[b, c, m] = sum over edges (n, j) into m of grad[b, c, n] (times 1/k for mean; only the
// winning slot j = arg[b, c, n] for max/min).
template <typename scalar_t>
__global__ void gather_reduce_backward_kernel(const scalar_t* __restrict__ grad, const int64_t* __restrict__ arg,
                                              const int64_t* __restrict__ order, const int64_t* __restrict__ row_ptr,
                                              int64_t B, int64_t C, int64_t M, int64_t N, int64_t k, scalar_t scale,
                                              scalar_t* __restrict__ grad_values) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * M) return;
  const int64_t m = t % M, bc = t / M, b = bc / C;
  const int64_t* edges = order + b * N * k;
  const scalar_t* g = grad + bc * N;
  const int64_t* a = arg ? arg + bc * N : nullptr;
  scalar_t acc = 0;
  for (int64_t e = row_ptr[b * (M + 1) + m]; e < row_ptr[b * (M + 1) + m + 1]; ++e) {
    const int64_t pos = edges[e], n = pos / k;
    if (a == nullptr) acc += g[n] * scale;
    else if (a[n] == pos % k) acc += g[n];
  }
  grad_values[t] = acc;
}

std::tuple<at::Tensor, at::Tensor> gather_reduce_cuda(const at::Tensor& values_in, const at::Tensor& idx_in,
                                                      c10::string_view reduce_name) {
  const Reduce reduce = parse_reduce(reduce_name);
  check_gather_reduce_inputs(values_in, idx_in);
  const c10::cuda::CUDAGuard guard(values_in.device());
  const at::Tensor values = values_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = values.size(0), C = values.size(1), M = values.size(2), N = idx.size(1), k = idx.size(2);
  const bool keep_arg = reduce == Reduce::kMax || reduce == Reduce::kMin;
  at::Tensor out = at::empty({B, C, N}, values.options());
  at::Tensor arg = at::empty({keep_arg ? B : 0, C, N}, values.options().dtype(at::kLong));
  if (out.numel() == 0) return {out, arg};
  AT_DISPATCH_FLOATING_TYPES(values.scalar_type(), "gather_reduce_cuda", [&] {
    const scalar_t* vp = values.const_data_ptr<scalar_t>();
    const int64_t* ip = idx.const_data_ptr<int64_t>();
    scalar_t* op = out.mutable_data_ptr<scalar_t>();
    int64_t* ap = keep_arg ? arg.mutable_data_ptr<int64_t>() : nullptr;
    const unsigned int blocks = blocks_for(B * C * N);
    switch (reduce) {
      case Reduce::kMax:
        gather_reduce_kernel<scalar_t, Reduce::kMax><<<blocks, kThreads, 0, current_stream()>>>(vp, ip, B, C, M, N, k, op, ap);
        break;
      case Reduce::kMin:
        gather_reduce_kernel<scalar_t, Reduce::kMin><<<blocks, kThreads, 0, current_stream()>>>(vp, ip, B, C, M, N, k, op, ap);
        break;
      case Reduce::kSum:
        gather_reduce_kernel<scalar_t, Reduce::kSum><<<blocks, kThreads, 0, current_stream()>>>(vp, ip, B, C, M, N, k, op, ap);
        break;
      case Reduce::kMean:
        gather_reduce_kernel<scalar_t, Reduce::kMean><<<blocks, kThreads, 0, current_stream()>>>(vp, ip, B, C, M, N, k, op, ap);
        break;
    }
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {out, arg};
}

at::Tensor gather_reduce_backward_cuda(const at::Tensor& grad_in, const at::Tensor& idx_in, const at::Tensor& arg_in,
                                       c10::string_view reduce_name, int64_t num_values) {
  const Reduce reduce = parse_reduce(reduce_name);
  check_gather_reduce_backward_inputs(grad_in, idx_in, arg_in, reduce, num_values);
  const c10::cuda::CUDAGuard guard(grad_in.device());
  const at::Tensor grad = grad_in.contiguous(), idx = idx_in.contiguous(), arg = arg_in.contiguous();
  const int64_t B = grad.size(0), C = grad.size(1), N = grad.size(2), M = num_values, k = idx.size(2);
  at::Tensor grad_values = at::empty({B, C, M}, grad.options());
  if (grad_values.numel() == 0) return grad_values;
  const Incidence inc = build_incidence(idx, M);
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "gather_reduce_backward_cuda", [&] {
    const scalar_t scale = reduce == Reduce::kMean ? scalar_t(1) / static_cast<scalar_t>(k) : scalar_t(1);
    gather_reduce_backward_kernel<scalar_t><<<blocks_for(B * C * M), kThreads, 0, current_stream()>>>(
        grad.const_data_ptr<scalar_t>(), (reduce == Reduce::kMax || reduce == Reduce::kMin) ? arg.const_data_ptr<int64_t>() : nullptr,
        inc.order.const_data_ptr<int64_t>(), inc.row_ptr.const_data_ptr<int64_t>(), B, C, M, N, k, scale,
        grad_values.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return grad_values;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CUDA, m) {
  m.impl("gather_reduce", &gather_reduce_cuda);
  m.impl("gather_reduce_backward", &gather_reduce_backward_cuda);
}

}  // namespace vrnet
