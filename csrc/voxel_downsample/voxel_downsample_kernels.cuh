// CUDA voxel downsampling with the CPU kernel's results bit for bit: each point's cell (the CPU's
// arithmetic in the points' dtype), the points ordered by cell lexicographically with a stable sort
// (by the glue: one sort of packed keys, or one per axis), so that each voxel's points are
// contiguous and in input order, then one thread per voxel summing them in double in that order, as
// the CPU's single pass does. Deterministic (no atomics in the sums).
#pragma once

#include <cmath>

#include "common/cuda_device.cuh"

namespace vrnet {

constexpr int kPackedCellBits = 21;  // cells below 2^21 on every axis fit one 63-bit key

// cells (N, 3) int64: floor((p - low) / size); a cell at or past `limit` (or not a number) sets
// *too_far and is written as 0.
template <typename scalar_t>
__global__ void voxel_cells_kernel(const scalar_t* __restrict__ points, const scalar_t* __restrict__ low, int64_t N,
                                   double voxel_size, double limit, int64_t* __restrict__ cells,
                                   int* __restrict__ too_far) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= N) return;
  const scalar_t size = static_cast<scalar_t>(voxel_size);
  for (int a = 0; a < 3; ++a) {
    const double cell = floor(static_cast<double>(div_rn(sub_rn(points[3 * i + a], low[a]), size)));
    const bool inside = cell < limit;
    if (!inside) atomicMax(too_far, 1);
    cells[3 * i + a] = inside ? static_cast<int64_t>(cell) : 0;
  }
}

__global__ void voxel_keys_kernel(const int64_t* __restrict__ cells, int64_t N, int64_t* __restrict__ keys) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= N) return;
  keys[i] = (cells[3 * i] << (2 * kPackedCellBits)) | (cells[3 * i + 1] << kPackedCellBits) | cells[3 * i + 2];
}

// first[r]: whether sorted position r starts a voxel (its cell differs from position r - 1's).
__global__ void voxel_firsts_kernel(const int64_t* __restrict__ cells, const int64_t* __restrict__ order, int64_t N,
                                    bool* __restrict__ first) {
  const int64_t r = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (r >= N) return;
  bool starts = r == 0;
  for (int a = 0; a < 3 && !starts; ++a) starts = cells[3 * order[r] + a] != cells[3 * order[r - 1] + a];
  first[r] = starts;
}

// One thread per voxel: the mean of sorted positions [begins[v], begins[v + 1]) (N for the last).
template <typename scalar_t>
__global__ void voxel_means_kernel(const scalar_t* __restrict__ points, const int64_t* __restrict__ order,
                                   const int64_t* __restrict__ begins, int64_t N, int64_t V,
                                   scalar_t* __restrict__ out) {
  const int64_t v = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (v >= V) return;
  const int64_t begin = begins[v], end = v + 1 < V ? begins[v + 1] : N;
  double sums[3] = {0, 0, 0};
  for (int64_t r = begin; r < end; ++r)
    for (int a = 0; a < 3; ++a) sums[a] = add_rn(sums[a], static_cast<double>(points[3 * order[r] + a]));
  for (int a = 0; a < 3; ++a) out[3 * v + a] = static_cast<scalar_t>(sums[a] / static_cast<double>(end - begin));
}

}  // namespace vrnet
