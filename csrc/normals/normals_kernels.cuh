// CUDA surface normals: one thread per point running the shared per-point routine
// (normals/normals_math.h), as the CPU kernel does.
#pragma once

#include "common/cuda_device.cuh"
#include "normals/normals_math.h"

namespace vrnet {

template <typename scalar_t>
__global__ void normals_kernel(const scalar_t* __restrict__ points, const int64_t* __restrict__ idx, int64_t N,
                               int64_t k, double view_x, double view_y, double view_z, scalar_t* __restrict__ out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const double view[3] = {view_x, view_y, view_z};
  if (i < N) normal_one(points, idx + i * k, i, k, view, out + 3 * i);
}

}  // namespace vrnet
