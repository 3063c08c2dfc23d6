// Kernels for the CUDA emulator's self-tests (tests/test_cuda_emulation.py): deliberately broken
// ones, each of which the emulator must report, and known-good patterns that must pass. Registered
// as vrnet_ext_emu::selftest(name, x): x is a float32 vector, the result a float32 vector.
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <string>

#include "common/cuda_utils.cuh"
#include "common/tensor_core.cuh"

namespace vrnet {
namespace {

// Writes one element past the end of out.
__global__ void oob_write_kernel(const float* x, int64_t n, float* out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i <= n) out[i] = x[i < n ? i : 0];
}

// Reads a neighbour's shared slot without a __syncthreads() after the writes.
__global__ void missing_sync_kernel(const float* x, float* out) {
  VRNET_SHARED(float, slot, 64);
  const int t = threadIdx.x;
  slot[t] = x[t];
  out[t] = slot[(t + 1) % 64];
}

// A barrier inside a branch that only the even threads take.
__global__ void partial_barrier_kernel(const float* x, float* out) {
  VRNET_SHARED(float, slot, 64);
  const int t = threadIdx.x;
  slot[t] = x[t];
  if (t % 2 == 0) __syncthreads();
  out[t] = slot[t];
}

// Two different barriers in the two arms of a branch.
__global__ void divergent_barrier_kernel(const float* x, float* out) {
  VRNET_SHARED(float, slot, 64);
  const int t = threadIdx.x;
  slot[t] = x[t];
  if (t < 32) {
    __syncthreads();
    out[t] = slot[63 - t];
  } else {
    __syncthreads();
    out[t] = slot[63 - t] + 1;
  }
}

// Every thread writes the same shared slot between the same two barriers.
__global__ void shared_race_kernel(const float* x, float* out) {
  VRNET_SHARED(float, total, 1);
  const int t = threadIdx.x;
  total[0] = x[t];
  __syncthreads();
  out[t] = total[0];
}

// A warp sum whose shuffles use width 16 (the xor with 16 then returns the lane's own value).
__global__ void narrow_shuffle_sum_kernel(const float* x, float* out) {
  float v = x[threadIdx.x];
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_xor_sync(kFullWarp, v, offset, 16);
  out[threadIdx.x] = v;
}

// A shuffle width that is not a power of two.
__global__ void invalid_shuffle_width_kernel(const float* x, float* out) {
  out[threadIdx.x] = __shfl_down_sync(kFullWarp, x[threadIdx.x], 1, 24);
}

// A shuffle whose mask names lanes that never arrive (the upper half returned early).
__global__ void shuffle_missing_lanes_kernel(const float* x, float* out) {
  if (threadIdx.x >= 16) return;
  out[threadIdx.x] = __shfl_down_sync(kFullWarp, x[threadIdx.x], 1);
}

// Half the warp at a shuffle, the other half (the last to arrive) at a tensor-core product.
__global__ void mma_beside_a_shuffle_kernel(const float* x, float* out) {
  float d[4] = {0.0f, 0.0f, 0.0f, 0.0f};
  if (threadIdx.x >= 16) {
    const std::uint32_t a[4] = {0, 0, 0, 0}, b[2] = {0, 0};
    mma_tf32(d, a, b);
  } else {
    d[0] = __shfl_sync(kFullWarp, x[threadIdx.x], 0);
  }
  out[threadIdx.x] = d[0];
}

// One float atomicAdd per block into one total: the rounding depends on the order of the blocks.
__global__ void order_dependent_sum_kernel(const float* x, float* out) {
  if (threadIdx.x == 0) atomicAdd(out, x[blockIdx.x]);
}

// Every block writes out[0] (plain stores): a race between blocks.
__global__ void inter_block_race_kernel(const float* x, float* out) {
  if (threadIdx.x == 0) out[0] = x[blockIdx.x];
}

// Good: block sum by warp shuffles, partials in shared memory, a second level inside warp 0 only.
__global__ void block_sum_kernel(const float* x, int64_t n, float* out) {
  VRNET_SHARED(double, partial, 32);
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const int warp = threadIdx.x / 32, lane = threadIdx.x % 32, warps = blockDim.x / 32;
  double v = warp_sum(i < n ? double(x[i]) : 0.0);
  if (lane == 0) partial[warp] = v;
  __syncthreads();
  if (warp == 0) {
    v = warp_sum(lane < warps ? partial[lane] : 0.0);
    if (lane == 0) out[blockIdx.x] = static_cast<float>(v);
  }
}

// Good: whole warps return before the others shuffle.
__global__ void early_warp_exit_kernel(const float* x, float* out) {
  if (threadIdx.x >= 64) return;
  out[threadIdx.x] = static_cast<float>(warp_sum(x[threadIdx.x]));
}

// Good: dynamic shared memory, reversed through a barrier.
__global__ void dynamic_shared_kernel(const float* x, float* out) {
  VRNET_DYNAMIC_SHARED(float, buffer);
  const int t = threadIdx.x;
  buffer[t] = x[t];
  __syncthreads();
  out[t] = buffer[blockDim.x - 1 - t];
}

// Good: the warp intrinsics, 8 outputs per lane (ballot, any, all, shfl idx/up/down/xor with
// widths below 32, and a partial-mask shuffle among the even lanes).
__global__ void warp_intrinsics_kernel(const float* x, float* out) {
  const int lane = threadIdx.x;
  const float v = x[lane];
  float* o = out + 8 * lane;
  o[0] = static_cast<float>(__ballot_sync(kFullWarp, v > 0) & 0xffffu);
  o[1] = static_cast<float>(__any_sync(kFullWarp, v > 2));
  o[2] = static_cast<float>(__all_sync(kFullWarp, v > -100));
  o[3] = __shfl_sync(kFullWarp, v, 3, 16);
  o[4] = __shfl_up_sync(kFullWarp, v, 2, 8);
  o[5] = __shfl_down_sync(kFullWarp, v, 3, 8);
  o[6] = __shfl_xor_sync(kFullWarp, v, 5, 32);
  o[7] = lane % 2 == 0 ? __shfl_down_sync(0x55555555u, v, 2) : -1.0f;
}

// Good: integer atomics (order-independent) on global and shared memory.
__global__ void integer_atomics_kernel(const float* x, int64_t n, int* out) {
  VRNET_SHARED(int, block_max, 1);
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (threadIdx.x == 0) block_max[0] = -1000000;
  __syncthreads();
  if (i < n) {
    const int value = static_cast<int>(x[i]);
    atomicAdd(out, value);
    atomicMax(&block_max[0], value);
    atomicMin(out + 1, value);
  }
  __syncthreads();
  if (threadIdx.x == 0) atomicMax(out + 2, block_max[0]);
}

at::Tensor selftest(c10::string_view name_view, const at::Tensor& x_in) {
  const std::string name(name_view);
  const at::Tensor x = x_in.contiguous();
  TORCH_CHECK(x.scalar_type() == at::kFloat && x.dim() == 1, "x must be a float32 vector");
  const int64_t n = x.size(0);
  at::Tensor out = at::zeros({n}, x.options());
  if (name == "oob_write") {
    // n elements inside a larger allocation: the stray write lands in the slack.
    out = at::zeros({n + 16}, x.options()).narrow(0, 0, n);
    launch<oob_write_kernel>(per_item(n + 1, 64), x, n, out);
  } else if (name == "missing_sync") {
    launch<missing_sync_kernel>({dim3(1), dim3(64), 0}, x, out);
  } else if (name == "partial_barrier") {
    launch<partial_barrier_kernel>({dim3(1), dim3(64), 0}, x, out);
  } else if (name == "divergent_barrier") {
    launch<divergent_barrier_kernel>({dim3(1), dim3(64), 0}, x, out);
  } else if (name == "shared_race") {
    launch<shared_race_kernel>({dim3(1), dim3(64), 0}, x, out);
  } else if (name == "narrow_shuffle_sum") {
    launch<narrow_shuffle_sum_kernel>({dim3(1), dim3(32), 0}, x, out);
  } else if (name == "invalid_shuffle_width") {
    launch<invalid_shuffle_width_kernel>({dim3(1), dim3(32), 0}, x, out);
  } else if (name == "shuffle_missing_lanes") {
    launch<shuffle_missing_lanes_kernel>({dim3(1), dim3(32), 0}, x, out);
  } else if (name == "mma_beside_a_shuffle") {
    launch<mma_beside_a_shuffle_kernel>({dim3(1), dim3(32), 0}, x, out);
  } else if (name == "order_dependent_sum") {
    launch<order_dependent_sum_kernel>({dim3(static_cast<unsigned int>(n)), dim3(32), 0}, x, out);
  } else if (name == "inter_block_race") {
    launch<inter_block_race_kernel>({dim3(static_cast<unsigned int>(n)), dim3(32), 0}, x, out);
  } else if (name == "block_sum") {
    const LaunchConfig config = per_item(n, 256);
    out = at::zeros({static_cast<int64_t>(config.grid.x)}, x.options());
    launch<block_sum_kernel>(config, x, n, out);
  } else if (name == "early_warp_exit") {
    launch<early_warp_exit_kernel>({dim3(1), dim3(128), 0}, x, out);
  } else if (name == "dynamic_shared") {
    launch<dynamic_shared_kernel>({dim3(1), dim3(static_cast<unsigned int>(n)), n * sizeof(float)}, x, out);
  } else if (name == "warp_intrinsics") {
    out = at::zeros({8 * n}, x.options());
    launch<warp_intrinsics_kernel>({dim3(1), dim3(32), 0}, x, out);
  } else if (name == "integer_atomics") {
    at::Tensor counters = at::zeros({3}, x.options().dtype(at::kInt));
    counters[1] = 1000000;
    counters[2] = -1000000;
    launch<integer_atomics_kernel>(per_item(n, 64), x, n, counters);
    return counters.to(at::kFloat);
  } else {
    TORCH_CHECK_VALUE(false, "unknown self-test kernel '", name, "'");
  }
  return out;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(vrnet_ext_emu, m) {
  m.def("selftest(str name, Tensor x) -> Tensor");
  m.impl("selftest", c10::DispatchKey::CPU, &selftest);
}

}  // namespace vrnet
