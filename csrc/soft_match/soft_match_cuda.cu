// Torch glue of the CUDA soft_match_flash op (kernel: soft_match_kernels.cuh): float32 inputs with
// feature size c and value width D of at most 64; `passes` 3 (about float32's accuracy) or 1 (TF32).
// No host synchronisation.
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "soft_match/soft_match.h"
#include "soft_match/soft_match_kernels.cuh"

namespace vrnet {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_flash_cuda(const at::Tensor& query_in,
                                                                     const at::Tensor& key_in,
                                                                     const at::Tensor& values_in, double scale,
                                                                     int64_t passes) {
  check_soft_match_inputs(query_in, key_in, values_in, scale);
  TORCH_CHECK_TYPE(query_in.scalar_type() == at::kFloat, "soft_match_flash takes float32 tensors, got ",
                   query_in.scalar_type());
  TORCH_CHECK_VALUE(query_in.size(2) <= kFlashMaxWidth && values_in.size(2) <= kFlashMaxWidth,
                    "soft_match_flash takes feature sizes and value widths of at most ", kFlashMaxWidth, ", got c = ",
                    query_in.size(2), ", D = ", values_in.size(2));
  TORCH_CHECK_VALUE(passes == 1 || passes == 3, "passes must be 1 (TF32) or 3 (split TF32), got ", passes);
  VRNET_CUDA_GUARD(query_in);
  TORCH_CHECK(compute_capability_major() >= kTensorCoreMajor,
              "soft_match_flash needs TF32 tensor cores (compute capability 8.0 or later)");
  const at::Tensor query = query_in.contiguous(), key = key_in.contiguous(), values = values_in.contiguous();
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1);
  const int C = static_cast<int>(query.size(2)), D = static_cast<int>(values.size(2));
  at::Tensor out = at::empty({B, N, D}, query.options());
  at::Tensor lse = at::empty({B, N}, query.options());
  at::Tensor argmax = at::empty({B, N}, query.options().dtype(at::kLong));
  if (B * N == 0) return {out, lse, argmax};
  const int64_t row_tiles = (N + kFlashRows - 1) / kFlashRows;
  TORCH_CHECK_VALUE(B * row_tiles < (int64_t{1} << 31), "soft_match_flash: too many query rows (B * N = ", B * N, ")");
  const LaunchConfig config{dim3(static_cast<unsigned int>(B * row_tiles)), dim3(kFlashThreads),
                            sizeof(float) * static_cast<std::size_t>(flash_shared_floats(C, D))};
  const float scale_f = static_cast<float>(scale);
  if (passes == 3) {
    launch<soft_match_flash_kernel<3>>(config, query, key, values, N, M, C, D, scale_f, row_tiles, out, lse, argmax);
  } else {
    launch<soft_match_flash_kernel<1>>(config, query, key, values, N, M, C, D, scale_f, row_tiles, out, lse, argmax);
  }
  return {out, lse, argmax};
}

}  // namespace

VRNET_CUDA_IMPL(m) { m.impl("soft_match_flash", &soft_match_flash_cuda); }

}  // namespace vrnet
