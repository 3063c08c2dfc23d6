// CUDA kernels of edge_norm_max (definition in edge_norm_max.h; glue in edge_norm_max_cuda.cu).
//
// The projections are read point-major, (B, N, 2O) in memory (what EdgeConv's product writes), with
// consecutive threads on consecutive channels of one point: a neighbour's gather is one coalesced
// row. Points are cut into tiles of kTilePoints (across batches); a block of kTileChannels x
// kTileRows threads takes one tile and 32 channels, each thread kTilePoints / kTileRows of the
// tile's points. Per-channel sums are kept per tile in double (about the tile's means of both terms,
// as the CPU kernel keeps them per task) and combined in tile order by one thread per channel: no
// atomics, deterministic.
//
// Forward: (1) per point and channel, over its k neighbours, the extreme of direction * a and its
// first slot (NaN wins at its first slot, as torch.max), and the tile's sums of z - shift and
// (z - shift)^2; (2) per channel, the batch mean and biased variance; (3) per point and channel,
// leaky_relu(scale * (extreme + b - mean) + bias). With running statistics only (1) and (3).
// Backward: (1) per point and channel the gradient of its winning edge value, and the tile's sums of
// dL/dh and dL/dh * (z_win - mean); (2) per channel the weight and bias gradients and what each edge
// gets through the statistics; (3) per point and channel the centre term's gradient over its k edges
// and the neighbour term's over its incoming edges (the graph's inverse, common/cuda_utils.cuh).
#pragma once

#include "common/cuda_device.cuh"

namespace vrnet {

constexpr int kTileChannels = 32;  // threadIdx.x: channels of a block
constexpr int kTileRows = 8;       // threadIdx.y
constexpr int kTilePoints = 64;    // points of a tile: kTilePoints / kTileRows per thread

// Where the thread of a tile block works: channel o (may be >= O: then it only joins the barriers)
// and its tile's points [first, last).
struct TileThread {
  int64_t o, first, last;
  int row;

  __device__ TileThread(int64_t points) {
    o = static_cast<int64_t>(blockIdx.x) * kTileChannels + threadIdx.x;
    first = static_cast<int64_t>(blockIdx.y) * kTilePoints;
    last = first + kTilePoints < points ? first + kTilePoints : points;
    row = threadIdx.y;
  }
};

// Sums `count` (<= 3) doubles of every row of the block's threads of one channel, in row order;
// the totals land in row 0's threads (`scratch`: count * kTileRows * kTileChannels shared doubles).
__device__ inline void sum_rows(double* values, int count, double* scratch) {
  for (int i = 0; i < count; ++i) scratch[(i * kTileRows + threadIdx.y) * kTileChannels + threadIdx.x] = values[i];
  __syncthreads();
  if (threadIdx.y == 0)
    for (int i = 0; i < count; ++i) {
      double total = 0;
      for (int r = 0; r < kTileRows; ++r) total += scratch[(i * kTileRows + r) * kTileChannels + threadIdx.x];
      values[i] = total;
    }
  __syncthreads();
}

// As the CPU kernel's: NaN propagates.
__device__ inline double leaky_relu(double h, double slope) { return (h < 0 ? 0.0 : h) + slope * (h < 0 ? h : 0.0); }
__device__ inline double leaky_relu_slope(double h, double slope) { return h > 0 ? 1.0 : slope; }

__device__ inline double invstd_of(const double* var, int64_t o, double eps) { return 1.0 / sqrt(var[o] + eps); }

template <typename scalar_t>
__device__ double weight_of(const scalar_t* weight, int64_t o) {
  return weight != nullptr ? static_cast<double>(weight[o]) : 1.0;
}

// Forward (1). P (B, N, 2O), idx (B, N, k); extreme and arg (B, N, O); per tile and channel
// (batch statistics only, else null): shift, sum (z - shift), sum (z - shift)^2.
template <typename scalar_t>
__global__ void edge_norm_max_neighbours_kernel(const scalar_t* __restrict__ P, const int64_t* __restrict__ idx,
                                                const scalar_t* __restrict__ weight, int64_t B, int64_t N,
                                                int64_t O, int64_t k, scalar_t* __restrict__ extreme,
                                                int32_t* __restrict__ arg, double* __restrict__ tile_shift,
                                                double* __restrict__ tile_sum, double* __restrict__ tile_squares) {
  VRNET_SHARED(double, scratch, 3 * kTileRows * kTileChannels);
  const TileThread at(B * N);
  const bool channel = at.o < O, batch_stats = tile_shift != nullptr;
  const double direction = channel && weight != nullptr && weight[at.o] < 0 ? -1.0 : 1.0;
  double shift[2] = {0, 0};  // the tile's means of a and of b in this channel
  if (batch_stats) {
    for (int64_t p = at.first + at.row; channel && p < at.last; p += kTileRows) {
      shift[0] += static_cast<double>(P[p * 2 * O + at.o]);
      shift[1] += static_cast<double>(P[p * 2 * O + O + at.o]);
    }
    sum_rows(shift, 2, scratch);
    if (at.row == 0) scratch[threadIdx.x] = shift[0], scratch[kTileChannels + threadIdx.x] = shift[1];
    __syncthreads();
    shift[0] = scratch[threadIdx.x] / static_cast<double>(at.last - at.first);
    shift[1] = scratch[kTileChannels + threadIdx.x] / static_cast<double>(at.last - at.first);
    __syncthreads();
  }
  double sums[2] = {0, 0};  // sum (z - shift) and sum (z - shift)^2 over this thread's edges
  for (int64_t p = at.first + at.row; channel && p < at.last; p += kTileRows) {
    const int64_t batch_start = (p / N) * N;
    const int64_t* nb = idx + p * k;
    double top = 0, s = 0, q = 0, nan_value = 0;
    int32_t slot = 0, nan_slot = -1;
    for (int64_t j = 0; j < k; ++j) {
      const double v = static_cast<double>(P[(batch_start + nb[j]) * 2 * O + at.o]);
      const double signed_v = direction * v;
      if (j == 0 || signed_v > top) top = signed_v, slot = static_cast<int32_t>(j);
      if (v != v && nan_slot < 0) nan_slot = static_cast<int32_t>(j), nan_value = v;
      const double d = v - shift[0];
      s += d, q += d * d;
    }
    extreme[p * O + at.o] = static_cast<scalar_t>(nan_slot >= 0 ? nan_value : direction * top);
    arg[p * O + at.o] = nan_slot >= 0 ? nan_slot : slot;
    const double c = static_cast<double>(P[p * 2 * O + O + at.o]) - shift[1];
    sums[0] += s + static_cast<double>(k) * c;
    sums[1] += q + 2 * c * s + static_cast<double>(k) * c * c;
  }
  if (!batch_stats) return;  // (no barrier follows)
  sum_rows(sums, 2, scratch);
  if (at.row == 0 && channel) {
    const int64_t slot = static_cast<int64_t>(blockIdx.y) * O + at.o;
    tile_shift[slot] = shift[0] + shift[1], tile_sum[slot] = sums[0], tile_squares[slot] = sums[1];
  }
}

// Forward (2): one thread per channel combines the tiles in order: mean and biased variance of the
// B * N * k edges.
__global__ void edge_norm_max_statistics_kernel(const double* __restrict__ tile_shift,
                                                       const double* __restrict__ tile_sum,
                                                       const double* __restrict__ tile_squares, int64_t points,
                                                       int64_t O, int64_t k, double* __restrict__ mean_out,
                                                       double* __restrict__ var_out) {
  const int64_t o = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (o >= O) return;
  const int64_t tiles = (points + kTilePoints - 1) / kTilePoints;
  const double count = static_cast<double>(points * k);
  double total = 0;
  for (int64_t t = 0; t < tiles; ++t) {
    const int64_t edges = ((t + 1) * kTilePoints < points ? kTilePoints : points - t * kTilePoints) * k;
    total += tile_sum[t * O + o] + static_cast<double>(edges) * tile_shift[t * O + o];
  }
  const double mean = total / count;
  double squares = 0;  // sum (z - mean)^2 = sum over tiles of sum (z - s_t - d)^2 with d = mean - s_t
  for (int64_t t = 0; t < tiles; ++t) {
    const int64_t edges = ((t + 1) * kTilePoints < points ? kTilePoints : points - t * kTilePoints) * k;
    const double d = mean - tile_shift[t * O + o];
    squares += tile_squares[t * O + o] - 2 * d * tile_sum[t * O + o] + static_cast<double>(edges) * d * d;
  }
  mean_out[o] = mean;
  var_out[o] = squares / count < 0 ? 0.0 : squares / count;  // NaN stays NaN, as std::max
}

// Forward (3), one thread per (point, channel), in place on the extremes: out (B, N, O).
template <typename scalar_t>
__global__ void edge_norm_max_output_kernel(const scalar_t* __restrict__ P, const scalar_t* __restrict__ weight,
                                            const scalar_t* __restrict__ bias, const double* __restrict__ mean,
                                            const double* __restrict__ var, int64_t points, int64_t O, double eps,
                                            double slope, scalar_t* __restrict__ out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= points * O) return;
  const int64_t p = i / O, o = i % O;
  const double scale = weight_of(weight, o) * invstd_of(var, o, eps);
  const double shifted = bias != nullptr ? static_cast<double>(bias[o]) : 0.0;
  const double centred = static_cast<double>(out[i]) + static_cast<double>(P[p * 2 * O + O + o]) - mean[o];
  const double h = scale * centred + shifted;
  out[i] = static_cast<scalar_t>(leaky_relu(h, slope));
}

// Backward (1): gh (B, N, O) = dL/dh * scale at each point's winning edge; per tile and channel the
// sums of dL/dh and dL/dh * (z_win - mean).
template <typename scalar_t>
__global__ void edge_norm_max_winners_kernel(const scalar_t* __restrict__ G, const scalar_t* __restrict__ P,
                                             const int64_t* __restrict__ idx, const int32_t* __restrict__ arg,
                                             const scalar_t* __restrict__ weight, const scalar_t* __restrict__ bias,
                                             const double* __restrict__ mean, const double* __restrict__ var,
                                             int64_t B, int64_t N, int64_t O, int64_t k, double eps, double slope,
                                             scalar_t* __restrict__ gh, double* __restrict__ tile_g,
                                             double* __restrict__ tile_gx) {
  VRNET_SHARED(double, scratch, 2 * kTileRows * kTileChannels);
  const TileThread at(B * N);
  const bool channel = at.o < O;
  double sums[2] = {0, 0};
  if (channel) {
    const double scale = weight_of(weight, at.o) * invstd_of(var, at.o, eps);
    const double shifted = bias != nullptr ? static_cast<double>(bias[at.o]) : 0.0;
    for (int64_t p = at.first + at.row; p < at.last; p += kTileRows) {
      const int64_t winner = (p / N) * N + idx[p * k + arg[p * O + at.o]];
      const double centred =
          static_cast<double>(P[winner * 2 * O + at.o]) + static_cast<double>(P[p * 2 * O + O + at.o]) - mean[at.o];
      const double g = static_cast<double>(G[p * O + at.o]) * leaky_relu_slope(scale * centred + shifted, slope);
      gh[p * O + at.o] = static_cast<scalar_t>(g * scale);
      sums[0] += g, sums[1] += g * centred;
    }
  }
  sum_rows(sums, 2, scratch);
  if (at.row == 0 && channel) {
    const int64_t slot = static_cast<int64_t>(blockIdx.y) * O + at.o;
    tile_g[slot] = sums[0], tile_gx[slot] = sums[1];
  }
}

// Backward (2): one thread per channel. grad_weight, grad_bias (O,); what every edge's z gets through
// the statistics: per_edge + per_deviation * (z - mean) (zero with running statistics).
template <typename scalar_t>
__global__ void edge_norm_max_channel_grads_kernel(const double* __restrict__ tile_g,
                                                   const double* __restrict__ tile_gx,
                                                   const scalar_t* __restrict__ weight, const double* __restrict__ var,
                                                   int64_t points, int64_t O, int64_t k, double eps, bool batch_stats,
                                                   scalar_t* __restrict__ grad_weight, scalar_t* __restrict__ grad_bias,
                                                   double* __restrict__ per_edge, double* __restrict__ per_deviation) {
  const int64_t o = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (o >= O) return;
  const int64_t tiles = (points + kTilePoints - 1) / kTilePoints;
  double g = 0, gx = 0;
  for (int64_t t = 0; t < tiles; ++t) g += tile_g[t * O + o], gx += tile_gx[t * O + o];
  const double invstd = invstd_of(var, o, eps), scale = weight_of(weight, o) * invstd;
  const double count = static_cast<double>(points * k);
  grad_bias[o] = static_cast<scalar_t>(g);
  grad_weight[o] = static_cast<scalar_t>(gx * invstd);
  per_edge[o] = batch_stats ? -scale * g / count : 0.0;                                   // through the mean
  per_deviation[o] = batch_stats ? 2 * (-0.5 * scale * invstd * invstd * gx) / count : 0.0;  // through invstd
}

// Backward (3), one thread per (point, channel): grad_P (B, N, 2O). The centre term b[p] gets its
// winner's gh and, with batch statistics, from each of its k edges per_edge + per_deviation *
// (z - mean); the neighbour term a[p] gets the same from each incoming edge (n, j) (order / row_ptr:
// the graph's inverse), plus gh[n] where (n, j) is n's winner. With running statistics there is no
// term through them (not even 0 times a NaN value).
template <typename scalar_t>
__global__ void edge_norm_max_input_grad_kernel(const scalar_t* __restrict__ P, const int64_t* __restrict__ idx,
                                                const int32_t* __restrict__ arg, const scalar_t* __restrict__ gh,
                                                const int64_t* __restrict__ order, const int64_t* __restrict__ row_ptr,
                                                const double* __restrict__ mean, const double* __restrict__ per_edge,
                                                const double* __restrict__ per_deviation, int64_t B, int64_t N,
                                                int64_t O, int64_t k, bool batch_stats,
                                                scalar_t* __restrict__ grad_P) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= B * N * O) return;
  const int64_t p = i / O, o = i % O, b = p / N, m = p % N, batch_start = b * N;
  double grad_b = static_cast<double>(gh[i]);
  if (batch_stats) {
    const double centre = static_cast<double>(P[p * 2 * O + O + o]) - mean[o];
    double deviations = 0;
    for (int64_t j = 0; j < k; ++j)
      deviations += static_cast<double>(P[(batch_start + idx[p * k + j]) * 2 * O + o]) + centre;
    grad_b += static_cast<double>(k) * per_edge[o] + per_deviation[o] * deviations;
  }
  grad_P[p * 2 * O + O + o] = static_cast<scalar_t>(grad_b);
  const double own = static_cast<double>(P[p * 2 * O + o]) - mean[o];
  const int64_t* edges = order + b * N * k;
  double grad_a = 0;
  for (int64_t e = row_ptr[b * (N + 1) + m]; e < row_ptr[b * (N + 1) + m + 1]; ++e) {
    const int64_t n = batch_start + edges[e] / k, j = edges[e] % k;
    if (batch_stats) grad_a += per_edge[o] + per_deviation[o] * (own + static_cast<double>(P[n * 2 * O + O + o]));
    if (arg[n * O + o] == j) grad_a += static_cast<double>(gh[n * O + o]);
  }
  grad_P[p * 2 * O + o] = static_cast<scalar_t>(grad_a);
}

}  // namespace vrnet
