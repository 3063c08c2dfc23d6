// Torch glue of the CUDA soft_match op (kernels: soft_match_kernels.cuh).
#include <ATen/ops/empty.h>
#include <ATen/ops/isfinite.h>
#include <ATen/ops/mul.h>
#include <ATen/ops/sub.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "soft_match/soft_match.h"
#include "soft_match/soft_match_kernels.cuh"

namespace vrnet {
namespace {

constexpr std::size_t kTileBytes = 40 * 1024;  // dynamic shared memory per block (of the 48 KB default)

// One block per kSoftMatchRows rows of one side (grid y: the batch); the other side streamed in tiles
// of `tile` rows of `row_values` values each, as many as fit kTileBytes (at most 64).
struct TiledLaunch {
  LaunchConfig config;
  int tile;
};

TiledLaunch tiled(int64_t rows, int64_t batch, int64_t row_values, std::size_t element_bytes) {
  TORCH_CHECK_VALUE(batch <= 65535, "query must have at most 65535 clouds per call on CUDA, got ", batch);
  const int64_t fit = static_cast<int64_t>(kTileBytes / (row_values * element_bytes));
  TORCH_CHECK_VALUE(fit >= 1, "soft_match on CUDA holds at most ", kTileBytes / element_bytes - 2,
                    " channels + values per row in shared memory, got ", row_values);
  const int tile = static_cast<int>(std::min<int64_t>(64, fit));
  return {{dim3(blocks_for(rows, kSoftMatchRows), static_cast<unsigned int>(batch)), dim3(kSoftMatchRows),
           static_cast<std::size_t>(tile * row_values) * element_bytes},
          tile};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_cuda(const at::Tensor& query_in, const at::Tensor& key_in,
                                                               const at::Tensor& values_in, double scale) {
  check_soft_match_inputs(query_in, key_in, values_in, scale);
  VRNET_CUDA_GUARD(query_in);
  const at::Tensor query = query_in.contiguous(), key = key_in.contiguous(), values = values_in.contiguous();
  check_on_device({finite_condition(query, "query"), finite_condition(key, "key"),
                   finite_condition(values, "values")});
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1), C = query.size(2), D = values.size(2);
  at::Tensor out = at::empty({B, N, D}, query.options());
  at::Tensor lse = at::empty({B, N}, query.options());
  at::Tensor argmax = at::empty({B, N}, query.options().dtype(at::kLong));
  if (B * N > 0) {
    AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "soft_match_cuda", [&] {
      const TiledLaunch t = tiled(N, B, C + D, sizeof(scalar_t));
      launch<soft_match_forward_kernel<scalar_t>>(t.config, query, key, values, N, M, C, D, scale, t.tile, out, lse,
                                                  argmax);
    });
    check_on_device({{at::isfinite(lse).all(), "soft_match scores overflow: scale * query . key is not finite"}});
  }
  return {out, lse, argmax};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_backward_cuda(
    const at::Tensor& grad_out_in, const at::Tensor& grad_lse_in, const at::Tensor& query_in,
    const at::Tensor& key_in, const at::Tensor& values_in, const at::Tensor& out_in, const at::Tensor& lse_in,
    double scale) {
  check_soft_match_backward_inputs(grad_out_in, grad_lse_in, query_in, key_in, values_in, out_in, lse_in, scale);
  VRNET_CUDA_GUARD(query_in);
  const at::Tensor query = query_in.contiguous(), key = key_in.contiguous(), values = values_in.contiguous();
  const at::Tensor grad_out = grad_out_in.contiguous(), lse = lse_in.contiguous();
  const at::Tensor shift = at::sub(grad_lse_in, at::mul(grad_out, out_in).sum(2)).contiguous();
  at::Tensor grad_query = at::zeros_like(query), grad_key = at::zeros_like(key);
  at::Tensor grad_values = at::zeros_like(values);
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1), C = query.size(2), D = values.size(2);
  if (B * N > 0) {
    AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "soft_match_backward_cuda", [&] {
      const TiledLaunch by_query = tiled(N, B, C + D, sizeof(scalar_t));
      launch<soft_match_grad_query_kernel<scalar_t>>(by_query.config, query, key, values, grad_out, lse, shift, N, M,
                                                     C, D, scale, by_query.tile, grad_query);
      const TiledLaunch by_key = tiled(M, B, C + D + 2, sizeof(scalar_t));
      launch<soft_match_grad_key_kernel<scalar_t>>(by_key.config, query, key, values, grad_out, lse, shift, N, M, C,
                                                   D, scale, by_key.tile, grad_key, grad_values);
    });
  }
  return {grad_query, grad_key, grad_values};
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("soft_match", &soft_match_cuda);
  m.impl("soft_match_backward", &soft_match_backward_cuda);
}

}  // namespace vrnet
