// CUDA geometry-structure loss: one thread per row i, the columns j streamed through shared-memory
// tiles, exact coordinate differences in double. The forward writes one partial sum per block (fixed
// order, no atomics) and the loss is their sum; the backward writes row i's gradient directly.
// Memory: O(B N) for the gradients plus B * ceil(N / 256) partial sums.
#pragma once

#include "common/cuda_device.cuh"

namespace vrnet {

constexpr int kPdlRowsPerBlock = 256;
constexpr int kPdlColumnTile = 256;

__device__ inline double pdl_distance(const double* p, const double* q) {
  const double dx = p[0] - q[0], dy = p[1] - q[1], dz = p[2] - q[2];
  return sqrt(dx * dx + dy * dy + dz * dz);
}

// Row i of cloud b: loads x_i, y_i (zeros past the end) and calls visit(x_j, y_j) for every column j,
// the columns streamed through shared memory. Every thread of the block must call it (all help load
// the tiles); threads with i >= N visit nothing. Returns whether i is a row.
template <typename scalar_t, typename Visit>
__device__ bool pdl_for_each_pair(const scalar_t* x_all, const scalar_t* y_all, int64_t N, double* xi, double* yi,
                                  Visit visit) {
  VRNET_SHARED(double, tile_x, 3 * kPdlColumnTile);
  VRNET_SHARED(double, tile_y, 3 * kPdlColumnTile);
  const int64_t b = blockIdx.y, i = static_cast<int64_t>(blockIdx.x) * kPdlRowsPerBlock + threadIdx.x;
  const scalar_t *x = x_all + b * N * 3, *y = y_all + b * N * 3;
  for (int a = 0; a < 3; ++a) {
    xi[a] = i < N ? double(x[3 * i + a]) : 0.0;
    yi[a] = i < N ? double(y[3 * i + a]) : 0.0;
  }
  for (int64_t j0 = 0; j0 < N; j0 += kPdlColumnTile) {
    const int count = static_cast<int>(N - j0 < kPdlColumnTile ? N - j0 : kPdlColumnTile);
    __syncthreads();
    for (int t = threadIdx.x; t < 3 * count; t += blockDim.x) {
      tile_x[t] = x[3 * j0 + t];
      tile_y[t] = y[3 * j0 + t];
    }
    __syncthreads();
    if (i >= N) continue;
    for (int j = 0; j < count; ++j) visit(tile_x + 3 * j, tile_y + 3 * j);
  }
  return i < N;
}

template <typename scalar_t>
__global__ void pdl_forward_kernel(const scalar_t* __restrict__ x, const scalar_t* __restrict__ y, int64_t N,
                                   double* __restrict__ partial) {
  VRNET_SHARED(double, block_sum, kPdlRowsPerBlock / 32);
  double xi[3], yi[3], acc = 0;
  pdl_for_each_pair(x, y, N, xi, yi, [&](const double* xj, const double* yj) {
    const double e = pdl_distance(xi, xj) - pdl_distance(yi, yj);
    acc += e * e;
  });
  acc = warp_sum(acc);
  if (threadIdx.x % 32 == 0) block_sum[threadIdx.x / 32] = acc;
  __syncthreads();
  if (threadIdx.x == 0) {
    double total = 0;
    for (int w = 0; w < kPdlRowsPerBlock / 32; ++w) total += block_sum[w];
    partial[blockIdx.y * gridDim.x + blockIdx.x] = total;
  }
}

// d loss / d x_i = 2 g / (N^2 loss) sum_j e_ij (x_i - x_j) / |x_i - x_j|, zero where loss or |.| is 0.
template <typename scalar_t>
__global__ void pdl_backward_kernel(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ x,
                                    const scalar_t* __restrict__ y, const scalar_t* __restrict__ loss, int64_t N,
                                    scalar_t* __restrict__ gx, scalar_t* __restrict__ gy) {
  double xi[3], yi[3], ax[3] = {0, 0, 0}, ay[3] = {0, 0, 0};
  const bool is_row = pdl_for_each_pair(x, y, N, xi, yi, [&](const double* xj, const double* yj) {
    const double dx = pdl_distance(xi, xj), dy = pdl_distance(yi, yj), e = dx - dy;
    const double cx = dx > 0 ? e / dx : 0.0, cy = dy > 0 ? e / dy : 0.0;
    for (int a = 0; a < 3; ++a) {
      ax[a] += cx * (xi[a] - xj[a]);
      ay[a] += cy * (yi[a] - yj[a]);
    }
  });
  if (!is_row) return;
  const int64_t b = blockIdx.y, i = static_cast<int64_t>(blockIdx.x) * kPdlRowsPerBlock + threadIdx.x;
  const double l = loss[b];
  const double scale = l > 0 ? 2.0 * double(grad[b]) / (double(N) * double(N) * l) : 0.0;
  for (int a = 0; a < 3; ++a) {
    gx[(b * N + i) * 3 + a] = static_cast<scalar_t>(scale * ax[a]);
    gy[(b * N + i) * 3 + a] = static_cast<scalar_t>(-scale * ay[a]);
  }
}

}  // namespace vrnet
