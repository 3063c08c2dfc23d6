// What every kernel header (csrc/<op>/<op>_kernels.cuh) includes: the CUDA language (from nvcc, or
// from the CPU emulator of cuda_emu/ when VRNET_CUDA_EMULATION is defined), shared-memory
// declarations that compile for both, exact (never FMA-contracted) arithmetic and warp reductions.
// Free of ATen / c10, so that kernels compile without torch.
#pragma once

#ifdef VRNET_CUDA_EMULATION
#include "cuda_emu/cuda_emu.h"
// `__shared__ type name[count]` and `extern __shared__ type name[]`, as one region per block.
#define VRNET_SHARED(type, name, count) VRNET_EMU_SHARED(type, name, count)
#define VRNET_DYNAMIC_SHARED(type, name) VRNET_EMU_DYNAMIC_SHARED(type, name)
#else
#define VRNET_SHARED(type, name, count) __shared__ type name[count]
#define VRNET_DYNAMIC_SHARED(type, name) extern __shared__ type name[]
#endif

#include <cstdint>

#include "common/exact_math.h"  // add_rn, sub_rn, mul_rn, div_rn
#include "common/host_device.h"

namespace vrnet {

constexpr int kThreads = 256;
constexpr unsigned int kFullWarp = 0xffffffffu;

// Sum over the 32 lanes of a warp; every lane gets the total (fixed order: deterministic). All 32
// lanes must call it.
__device__ inline double warp_sum(double v) {
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_xor_sync(kFullWarp, v, offset);
  return v;
}

// Maximum over the 32 lanes of a warp; every lane gets it. All 32 lanes must call it.
__device__ inline double warp_max(double v) {
  for (int offset = 16; offset > 0; offset >>= 1) {
    const double other = __shfl_xor_sync(kFullWarp, v, offset);
    v = other > v ? other : v;
  }
  return v;
}

}  // namespace vrnet
