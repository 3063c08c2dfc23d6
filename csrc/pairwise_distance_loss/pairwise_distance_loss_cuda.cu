// CUDA geometry-structure loss: one thread per row i, the columns j streamed through shared-memory
// tiles, exact coordinate differences in double. The forward writes one partial sum per block (fixed
// order, no atomics) and the loss is their sum; the backward writes row i's gradient directly.
// Memory: O(B N) for the gradients plus B * ceil(N / 256) partial sums.
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "pairwise_distance_loss/pairwise_distance_loss.h"

namespace vrnet {
namespace {

constexpr int kRowsPerBlock = 256;
constexpr int kColumnTile = 256;

__device__ inline double distance(const double* p, const double* q) {
  const double dx = p[0] - q[0], dy = p[1] - q[1], dz = p[2] - q[2];
  return sqrt(dx * dx + dy * dy + dz * dz);
}

// Row i of cloud b: loads x_i, y_i (zeros past the end) and calls visit(x_i, y_i, x_j, y_j) for every
// column j, the columns streamed through shared memory. Every thread of the block must call it
// (all help load the tiles); threads with i >= N visit nothing. Returns whether i is a row.
template <typename scalar_t, typename Visit>
__device__ bool for_each_pair(const scalar_t* x_all, const scalar_t* y_all, int64_t N, double* xi, double* yi,
                              Visit visit) {
  __shared__ double tile_x[3 * kColumnTile], tile_y[3 * kColumnTile];
  const int64_t b = blockIdx.y, i = static_cast<int64_t>(blockIdx.x) * kRowsPerBlock + threadIdx.x;
  const scalar_t *x = x_all + b * N * 3, *y = y_all + b * N * 3;
  for (int a = 0; a < 3; ++a) {
    xi[a] = i < N ? double(x[3 * i + a]) : 0.0;
    yi[a] = i < N ? double(y[3 * i + a]) : 0.0;
  }
  for (int64_t j0 = 0; j0 < N; j0 += kColumnTile) {
    const int count = static_cast<int>(N - j0 < kColumnTile ? N - j0 : kColumnTile);
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
  __shared__ double block_sum[kRowsPerBlock / 32];
  double xi[3], yi[3], acc = 0;
  for_each_pair(x, y, N, xi, yi, [&](const double* xj, const double* yj) {
    const double e = distance(xi, xj) - distance(yi, yj);
    acc += e * e;
  });
  acc = warp_sum(acc);
  if (threadIdx.x % 32 == 0) block_sum[threadIdx.x / 32] = acc;
  __syncthreads();
  if (threadIdx.x == 0) {
    double total = 0;
    for (int w = 0; w < kRowsPerBlock / 32; ++w) total += block_sum[w];
    partial[blockIdx.y * gridDim.x + blockIdx.x] = total;
  }
}

// d loss / d x_i = 2 g / (N^2 loss) sum_j e_ij (x_i - x_j) / |x_i - x_j|, zero where loss or |.| is 0.
template <typename scalar_t>
__global__ void pdl_backward_kernel(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ x,
                                    const scalar_t* __restrict__ y, const scalar_t* __restrict__ loss, int64_t N,
                                    scalar_t* __restrict__ gx, scalar_t* __restrict__ gy) {
  double xi[3], yi[3], ax[3] = {0, 0, 0}, ay[3] = {0, 0, 0};
  const bool is_row = for_each_pair(x, y, N, xi, yi, [&](const double* xj, const double* yj) {
    const double dx = distance(xi, xj), dy = distance(yi, yj), e = dx - dy;
    const double cx = dx > 0 ? e / dx : 0.0, cy = dy > 0 ? e / dy : 0.0;
    for (int a = 0; a < 3; ++a) {
      ax[a] += cx * (xi[a] - xj[a]);
      ay[a] += cy * (yi[a] - yj[a]);
    }
  });
  if (!is_row) return;
  const int64_t b = blockIdx.y, i = static_cast<int64_t>(blockIdx.x) * kRowsPerBlock + threadIdx.x;
  const double l = loss[b];
  const double scale = l > 0 ? 2.0 * double(grad[b]) / (double(N) * double(N) * l) : 0.0;
  for (int a = 0; a < 3; ++a) {
    gx[(b * N + i) * 3 + a] = static_cast<scalar_t>(scale * ax[a]);
    gy[(b * N + i) * 3 + a] = static_cast<scalar_t>(-scale * ay[a]);
  }
}

void check_batch(int64_t B) {
  TORCH_CHECK_VALUE(B <= 65535, "x must have at most 65535 clouds per call on CUDA, got ", B);
}

at::Tensor pairwise_distance_loss_cuda(const at::Tensor& x_in, const at::Tensor& y_in) {
  check_pairwise_distance_loss_inputs(x_in, y_in);
  const c10::cuda::CUDAGuard guard(x_in.device());
  const at::Tensor x = x_in.contiguous(), y = y_in.contiguous();
  const int64_t B = x.size(0), N = x.size(1);
  check_batch(B);
  if (B == 0) return at::empty({0}, x.options());
  check_on_device({finite_condition(x, "x"), finite_condition(y, "y")});
  const unsigned int row_blocks = blocks_for(N, kRowsPerBlock);
  at::Tensor partial = at::empty({B, row_blocks}, x.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "pairwise_distance_loss_cuda", [&] {
    pdl_forward_kernel<scalar_t><<<dim3(row_blocks, B), kRowsPerBlock, 0, current_stream()>>>(
        x.const_data_ptr<scalar_t>(), y.const_data_ptr<scalar_t>(), N, partial.mutable_data_ptr<double>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  // Over ordered pairs (both i < j and j < i): the same mean as the CPU kernel's 2 * upper / N^2.
  return partial.sum(1).div(double(N) * double(N)).sqrt().to(x.scalar_type());
}

std::tuple<at::Tensor, at::Tensor> pairwise_distance_loss_backward_cuda(const at::Tensor& grad_in,
                                                                        const at::Tensor& x_in, const at::Tensor& y_in,
                                                                        const at::Tensor& loss_in) {
  check_pairwise_distance_loss_backward_inputs(grad_in, x_in, y_in, loss_in);
  const c10::cuda::CUDAGuard guard(x_in.device());
  const at::Tensor grad = grad_in.contiguous(), x = x_in.contiguous(), y = y_in.contiguous();
  const at::Tensor loss = loss_in.contiguous();
  const int64_t B = x.size(0), N = x.size(1);
  check_batch(B);
  at::Tensor gx = at::empty_like(x), gy = at::empty_like(y);
  if (B == 0) return {gx, gy};
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "pairwise_distance_loss_backward_cuda", [&] {
    pdl_backward_kernel<scalar_t><<<dim3(blocks_for(N, kRowsPerBlock), B), kRowsPerBlock, 0, current_stream()>>>(
        grad.const_data_ptr<scalar_t>(), x.const_data_ptr<scalar_t>(), y.const_data_ptr<scalar_t>(),
        loss.const_data_ptr<scalar_t>(), N, gx.mutable_data_ptr<scalar_t>(), gy.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {gx, gy};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CUDA, m) {
  m.impl("pairwise_distance_loss", &pairwise_distance_loss_cuda);
  m.impl("pairwise_distance_loss_backward", &pairwise_distance_loss_backward_cuda);
}

}  // namespace vrnet
