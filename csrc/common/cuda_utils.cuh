// Host side of the CUDA ops (the torch glue in csrc/<op>/<op>_cuda.cu): launch geometry, one launch
// helper that takes tensors for the kernel's pointer parameters, the device guard and stream, and
// the inverse of a neighbour graph used by every deterministic scatter-free backward.
//
// launch<kernel>(config, args...) is `kernel<<<grid, block, shared_bytes, stream>>>(args...)` under
// nvcc, with each at::Tensor argument passed as its data pointer of the parameter's type. Under the
// CPU emulator (VRNET_CUDA_EMULATION) the same call runs the kernel through cuda_emu, which checks
// every access against those tensors' extents. VRNET_CUDA_IMPL registers the glue as the op's CUDA
// kernel (vrnet_ext, CUDA) or, emulated, as a CPU op of the test library vrnet_ext_emu.
#pragma once

#include <ATen/ops/arange.h>
#include <ATen/ops/searchsorted.h>
#include <ATen/ops/sort.h>

#include <algorithm>
#include <cstdint>
#include <tuple>
#include <type_traits>
#include <utility>

#include "common/common.h"
#include "common/cuda_device.cuh"
#include "common/kernel_args.h"

#ifdef VRNET_CUDA_EMULATION
#include "cuda_emu/launch.h"
#define VRNET_CUDA_GUARD(tensor) ((void)0)
#define VRNET_CUDA_IMPL(m) TORCH_LIBRARY_IMPL(vrnet_ext_emu, CPU, m)
#else
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#define VRNET_CUDA_GUARD(tensor) const c10::cuda::CUDAGuard vrnet_device_guard((tensor).device())
#define VRNET_CUDA_IMPL(m) TORCH_LIBRARY_IMPL(vrnet_ext, CUDA, m)
#endif

namespace vrnet {

#ifndef VRNET_CUDA_EMULATION
inline cudaStream_t current_stream() { return c10::cuda::getCurrentCUDAStream().stream(); }

// The current device's compute capability, major part (8: Ampere, 9: Hopper).
inline int compute_capability_major() {
  int device = 0, major = 0;
  C10_CUDA_CHECK(cudaGetDevice(&device));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, device));
  return major;
}

template <auto Kernel, typename Params, typename... Args, std::size_t... I>
void launch_indexed(const LaunchConfig& config, std::index_sequence<I...>, Args&&... args) {
  Kernel<<<config.grid, config.block, config.shared_bytes, current_stream()>>>(
      launch_detail::convert<std::tuple_element_t<I, Params>>(std::forward<Args>(args))...);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}
#endif

// Inverse of a neighbour graph idx (B, N, k) with values in [0, M): for target m of batch b, the
// flat positions p = n * k + j with idx[b, n, j] == m are order[b, row_ptr[b, m] : row_ptr[b, m + 1]],
// ascending. Lets a backward gather per target instead of scattering with atomics.
struct Incidence {
  at::Tensor order;    // (B, N * k) int64
  at::Tensor row_ptr;  // (B, M + 1) int64
};

inline Incidence build_incidence(const at::Tensor& idx, int64_t num_targets) {
  const int64_t B = idx.size(0);
  const at::Tensor flat = idx.reshape({B, -1});
  const auto [sorted, order] = flat.sort(/*stable=*/true, /*dim=*/1, /*descending=*/false);
  const at::Tensor targets = at::arange(num_targets + 1, idx.options()).expand({B, num_targets + 1}).contiguous();
  return {order.contiguous(), at::searchsorted(sorted, targets).contiguous()};
}

}  // namespace vrnet
