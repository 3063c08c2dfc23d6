// Torch glue of the CUDA soft_match_flash op and its backward (kernels: soft_match_kernels.cuh):
// float32 inputs with feature size c and value width D of at most 64; `passes` 3 (about float32's
// accuracy) or 1 (TF32). No host synchronisation.
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>

#include <algorithm>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "soft_match/soft_match.h"
#include "soft_match/soft_match_kernels.cuh"

namespace vrnet {
namespace {

// What both directions of the flash kernel take: float32, c and D of at most 64, 1 or 3 passes, a GPU
// with TF32 tensor cores.
void check_flash_inputs(const at::Tensor& query, const at::Tensor& values, int64_t passes) {
  TORCH_CHECK_TYPE(query.scalar_type() == at::kFloat, "soft_match_flash takes float32 tensors, got ",
                   query.scalar_type());
  TORCH_CHECK_VALUE(query.size(2) <= kFlashMaxWidth && values.size(2) <= kFlashMaxWidth,
                    "soft_match_flash takes feature sizes and value widths of at most ", kFlashMaxWidth, ", got c = ",
                    query.size(2), ", D = ", values.size(2));
  TORCH_CHECK_VALUE(passes == 1 || passes == 3, "passes must be 1 (TF32) or 3 (split TF32), got ", passes);
  TORCH_CHECK(compute_capability_major() >= kTensorCoreMajor,
              "soft_match_flash needs TF32 tensor cores (compute capability 8.0 or later)");
}

// Parts of the keys each tile of query rows is split into: enough for B x row tiles x parts to reach
// target_blocks (a few per multiprocessor: few query rows would leave most of a GPU idle), at most
// kFlashMaxSplits, each of at least kFlashMinSplitKeys keys.
int64_t key_splits_for(int64_t blocks, int64_t M, int64_t target_blocks) {
  if (blocks >= target_blocks) return 1;
  const int64_t wanted = (target_blocks + blocks - 1) / blocks;
  return std::max<int64_t>(1, std::min<int64_t>({wanted, kFlashMaxSplits, M / kFlashMinSplitKeys}));
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_flash_cuda(const at::Tensor& query_in,
                                                                     const at::Tensor& key_in,
                                                                     const at::Tensor& values_in, double scale,
                                                                     int64_t passes, int64_t target_blocks) {
  check_soft_match_inputs(query_in, key_in, values_in, scale);
  VRNET_CUDA_GUARD(query_in);
  check_flash_inputs(query_in, values_in, passes);
  const at::Tensor query = query_in.contiguous(), key = key_in.contiguous(), values = values_in.contiguous();
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1);
  const int C = static_cast<int>(query.size(2)), D = static_cast<int>(values.size(2));
  at::Tensor out = at::empty({B, N, D}, query.options());
  at::Tensor lse = at::empty({B, N}, query.options());
  at::Tensor argmax = at::empty({B, N}, query.options().dtype(at::kLong));
  if (B * N == 0) return {out, lse, argmax};
  const int64_t row_tiles = (N + kFlashRows - 1) / kFlashRows;
  TORCH_CHECK_VALUE(B * row_tiles < (int64_t{1} << 31), "soft_match_flash: too many query rows (B * N = ", B * N, ")");
  int64_t key_splits = key_splits_for(B * row_tiles, M, target_blocks);
  const int64_t key_tiles = (M + kFlashKeys - 1) / kFlashKeys;
  const int64_t split_keys = (key_tiles + key_splits - 1) / key_splits * kFlashKeys;
  key_splits = (M + split_keys - 1) / split_keys;  // none empty
  at::Tensor partial_acc, partial_max, partial_sum, partial_peak;
  if (key_splits > 1) {
    partial_acc = at::empty({B, key_splits, N, D}, query.options());
    partial_max = at::empty({B, key_splits, N}, query.options());
    partial_sum = at::empty({B, key_splits, N}, query.options());
    partial_peak = at::empty({B, key_splits, N}, argmax.options());
  }
  const LaunchConfig config{dim3(static_cast<unsigned int>(B * row_tiles * key_splits)), dim3(kFlashThreads),
                            sizeof(float) * static_cast<std::size_t>(flash_shared_floats(C, D))};
  const float scale_f = static_cast<float>(scale);
  const auto run = [&](auto passes_constant) {
    launch<soft_match_flash_kernel<decltype(passes_constant)::value>>(
        config, query, key, values, N, M, C, D, scale_f, row_tiles, key_splits, split_keys, out, lse, argmax,
        partial_acc, partial_max, partial_sum, partial_peak);
  };
  if (passes == 3) run(std::integral_constant<int, 3>{});
  else run(std::integral_constant<int, 1>{});
  if (key_splits > 1)
    launch<soft_match_flash_combine_kernel>(per_item(B * N), partial_acc, partial_max, partial_sum, partial_peak, B * N,
                                            N, key_splits, D, out, lse, argmax);
  return {out, lse, argmax};
}

// The backward's two launches: dK and dV per block of keys, then dQ per block of queries.
template <int kPasses>
void launch_flash_backward(const at::Tensor& query, const at::Tensor& key, const at::Tensor& values,
                           const at::Tensor& grad_out, const at::Tensor& lse, const at::Tensor& delta, float scale,
                           at::Tensor& grad_query, at::Tensor& grad_key, at::Tensor& grad_values) {
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1);
  const int C = static_cast<int>(query.size(2)), D = static_cast<int>(values.size(2));
  const int64_t key_tiles = (M + kFlashBackRows - 1) / kFlashBackRows;
  const int64_t row_tiles = (N + kFlashBackRows - 1) / kFlashBackRows;
  TORCH_CHECK_VALUE(B * std::max(key_tiles, row_tiles) < (int64_t{1} << 31),
                    "soft_match_flash: too many rows (B = ", B, ", N = ", N, ", M = ", M, ")");
  const std::size_t shared_bytes = sizeof(float) * static_cast<std::size_t>(flash_backward_shared_floats(C, D));
  launch<soft_match_flash_grad_kv_kernel<kPasses>>(
      LaunchConfig{dim3(static_cast<unsigned int>(B * key_tiles)), dim3(kFlashBackThreads), shared_bytes}, query, key,
      values, grad_out, lse, delta, N, M, C, D, scale, key_tiles, grad_key, grad_values);
  if (N == 0) return;
  launch<soft_match_flash_grad_query_kernel<kPasses>>(
      LaunchConfig{dim3(static_cast<unsigned int>(B * row_tiles)), dim3(kFlashBackThreads), shared_bytes}, query, key,
      values, grad_out, lse, delta, N, M, C, D, scale, row_tiles, grad_query);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_flash_backward_cuda(
    const at::Tensor& grad_out_in, const at::Tensor& grad_lse_in, const at::Tensor& query_in, const at::Tensor& key_in,
    const at::Tensor& values_in, const at::Tensor& out_in, const at::Tensor& lse_in, double scale, int64_t passes) {
  check_soft_match_backward_inputs(grad_out_in, grad_lse_in, query_in, key_in, values_in, out_in, lse_in, scale);
  VRNET_CUDA_GUARD(query_in);
  check_flash_inputs(query_in, values_in, passes);
  const at::Tensor query = query_in.contiguous(), key = key_in.contiguous(), values = values_in.contiguous();
  const at::Tensor grad_out = grad_out_in.contiguous(), lse = lse_in.contiguous();
  const at::Tensor delta = grad_out.mul(out_in).sum(-1).sub(grad_lse_in).contiguous();  // dO_i . O_i - dlse_i
  at::Tensor grad_query = at::empty_like(query), grad_key = at::empty_like(key), grad_values = at::empty_like(values);
  if (query.size(0) == 0) return {grad_query, grad_key, grad_values};
  const float scale_f = static_cast<float>(scale);
  if (passes == 3) {
    launch_flash_backward<3>(query, key, values, grad_out, lse, delta, scale_f, grad_query, grad_key, grad_values);
  } else {
    launch_flash_backward<1>(query, key, values, grad_out, lse, delta, scale_f, grad_query, grad_key, grad_values);
  }
  return {grad_query, grad_key, grad_values};
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("soft_match_flash", &soft_match_flash_cuda);
  m.impl("soft_match_flash_backward", &soft_match_flash_backward_cuda);
}

}  // namespace vrnet
