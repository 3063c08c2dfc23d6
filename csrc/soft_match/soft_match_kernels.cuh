// soft_match's CUDA kernel: flash-style soft matching on TF32 tensor cores for feature and value
// widths of at most 64 (the scene model's 32-dimensional features; matchings of 10^5 points).
//
// A block of 4 warps takes 64 query rows of one batch item (16 a warp) and walks over the keys in
// tiles of 32 held in shared memory: each warp's scores S = scale Q Kᵀ by m16n8k8 products, the
// online-softmax recurrence per row (running maximum m, normaliser l, the accumulated P V rescaled by
// exp(m_old - m_new) when the maximum grows), P = exp(S - m) through the warp's slice of shared
// memory into the A operand of O += P V. No N x M matrix; no atomics (deterministic). Few query rows:
// the keys in parts, a block per (row tile, part), combined by soft_match_flash_combine_kernel.
// Rows are held by lanes as the products' D fragments place them: rows g and g + 8 of the warp's 16,
// columns 2t and 2t + 1 of each 8-wide tile (common/tensor_core.cuh); a row's four lanes combine
// their maxima and sums by shuffles.
#pragma once

#include <cmath>
#include <cstdint>

#include "common/cuda_device.cuh"
#include "common/tensor_core.cuh"

namespace vrnet {

constexpr int kFlashWarps = 4;
constexpr int kFlashThreads = kFlashWarps * 32;
constexpr int kFlashRows = kFlashWarps * 16;  // query rows per block
constexpr int kFlashKeys = 32;                 // keys per shared-memory tile
constexpr int kFlashMaxWidth = 64;             // largest feature size c and value width D
constexpr int kFlashMaxSplits = 16;            // parts of the keys a row tile's blocks may take
constexpr int kFlashMinSplitKeys = 256;        // keys per part at least (the partials' cost amortised)
constexpr int kFlashValueTiles = kFlashMaxWidth / 8;

// Row strides of the shared tiles (floats), chosen so that a fragment's 32 loads hit 32 banks:
// Q and K are read as (g, t) (row_fragment_stride), V as (t, g) -> t * stride + g (stride = 8 mod 32),
// P as Q.
VRNET_HOST_DEVICE constexpr int flash_feature_stride(int c) { return row_fragment_stride(c); }
VRNET_HOST_DEVICE constexpr int flash_value_stride(int d) { return (d + 31) / 32 * 32 + 8; }
constexpr int kFlashProbStride = kFlashKeys + 4;

// Floats of dynamic shared memory a block uses: Q (64 rows), K and V (32 rows), P (64 rows).
VRNET_HOST_DEVICE constexpr int flash_shared_floats(int c, int d) {
  return (kFlashRows + kFlashKeys) * flash_feature_stride(c) + kFlashKeys * flash_value_stride(d) +
         kFlashRows * kFlashProbStride;
}

// (value, index) pairs: the larger value, on ties the lower index (the first maximum).
__device__ inline void take_first_max(float& value, int64_t& index, float other, int64_t other_index) {
  if (other > value || (other == value && other_index < index)) {
    value = other;
    index = other_index;
  }
}

// A warp's accumulated 16 rows into rows first .. first + 15 of a (rows_total, width) row-major matrix,
// each of the lane's two rows (g, g + 8) multiplied by its factor; rows past rows_total are skipped.
__device__ inline void store_rows(const float (&acc)[kFlashValueTiles][4], const float (&factor)[2], int64_t first,
                                  int64_t rows_total, int width, float* __restrict__ out, int lane) {
  const int g = lane >> 2, t = lane & 3;
  VRNET_UNROLL
  for (int s = 0; s < 2; ++s) {
    const int64_t row = first + g + 8 * s;
    if (row >= rows_total) continue;
    VRNET_UNROLL
    for (int f = 0; f < kFlashValueTiles; ++f) {
      VRNET_UNROLL for (int i = 2 * s; i < 2 * s + 2; ++i) {
        const int col = f * 8 + 2 * t + (i & 1);
        if (col < width) out[row * width + col] = acc[f][i] * factor[s];
      }
    }
  }
}

// grid: one block per (batch item, tile of 64 query rows, part of the keys), blockIdx.x = (b * row_tiles +
// tile) * key_splits + split, the split's keys from split * split_keys (a multiple of kFlashKeys);
// kFlashThreads threads; flash_shared_floats(C, D) floats of dynamic shared memory. One split: the
// outputs. More: each split's rows unnormalised (the sum of exp(s - m) v), its maximum m, sum of
// exp(s - m) and first peak, at (b * key_splits + split) * N + row of partial_acc (times D), partial_max,
// partial_sum, partial_peak, for soft_match_flash_combine_kernel.
template <int kPasses>
__global__ void soft_match_flash_kernel(const float* __restrict__ query, const float* __restrict__ key,
                                        const float* __restrict__ values, int64_t N, int64_t M, int C, int D,
                                        float scale, int64_t row_tiles, int64_t key_splits, int64_t split_keys,
                                        float* __restrict__ out, float* __restrict__ lse,
                                        int64_t* __restrict__ argmax, float* __restrict__ partial_acc,
                                        float* __restrict__ partial_max, float* __restrict__ partial_sum,
                                        int64_t* __restrict__ partial_peak) {
  VRNET_DYNAMIC_SHARED(float, shared);
  const int feature_stride = flash_feature_stride(C), value_stride = flash_value_stride(D);
  float* q_tile = shared;
  float* k_tile = q_tile + kFlashRows * feature_stride;
  float* v_tile = k_tile + kFlashKeys * feature_stride;
  float* p_tile = v_tile + kFlashKeys * value_stride;

  const auto [b, row0, warp, lane, g, t, warp_row] = RowTileThread(blockIdx.x / key_splits, row_tiles, kFlashRows);
  const int64_t split = blockIdx.x % key_splits;
  const int64_t keys_begin = split * split_keys, keys_end = keys_begin + split_keys < M ? keys_begin + split_keys : M;
  const int feature_steps = (C + 7) / 8, value_tiles = (D + 7) / 8;

  load_tile(query + b * N * C, row0, N, C, kFlashRows, feature_stride, q_tile);

  // rows g (slot 0) and g + 8 (slot 1) of the warp's 16
  float row_max[2] = {-INFINITY, -INFINITY}, row_sum[2] = {0.0f, 0.0f};
  int64_t row_peak[2] = {0, 0};
  float acc[kFlashValueTiles][4];
  zero(acc);

  for (int64_t j0 = keys_begin; j0 < keys_end; j0 += kFlashKeys) {
    __syncthreads();  // every warp is done with the previous tiles (and Q is loaded)
    load_tile(key + b * M * C, j0, keys_end, C, kFlashKeys, feature_stride, k_tile);
    load_tile(values + b * M * D, j0, keys_end, D, kFlashKeys, value_stride, v_tile);
    __syncthreads();

    float score[kFlashKeys / 8][4];
    warp_products_abt<kPasses>(score, q_tile, feature_stride, warp_row, k_tile, feature_stride, feature_steps, lane);

    // scale, mask the keys past the split's, and each row's first maximum in the tile
    float tile_max[2] = {-INFINITY, -INFINITY};
    int64_t tile_peak[2] = {M, M};
    VRNET_UNROLL
    for (int n = 0; n < kFlashKeys / 8; ++n)
      VRNET_UNROLL for (int i = 0; i < 4; ++i) {
        const int64_t j = j0 + n * 8 + 2 * t + (i & 1);
        score[n][i] = j < keys_end ? score[n][i] * scale : -INFINITY;
        if (j < keys_end) take_first_max(tile_max[i >> 1], tile_peak[i >> 1], score[n][i], j);
      }
    float alpha[2], shift[2];
    VRNET_UNROLL
    for (int s = 0; s < 2; ++s) {
      for (int offset = 1; offset < 4; offset <<= 1) {
        const float other = __shfl_xor_sync(kFullWarp, tile_max[s], offset);
        const int64_t other_peak = __shfl_xor_sync(kFullWarp, tile_peak[s], offset);
        take_first_max(tile_max[s], tile_peak[s], other, other_peak);
      }
      if (tile_max[s] > row_max[s]) row_peak[s] = tile_peak[s];
      const float new_max = fmaxf(row_max[s], tile_max[s]);
      // while every score so far is -inf (underflowed), weights exp(s - 0): 0, not exp(-inf + inf)
      shift[s] = new_max == -INFINITY ? 0.0f : new_max;
      alpha[s] = expf(row_max[s] - shift[s]);
      row_max[s] = new_max;
    }

    // P = exp(S - m) into the warp's rows of p_tile; the rows' sums
    float tile_sum[2] = {0.0f, 0.0f};
    VRNET_UNROLL
    for (int n = 0; n < kFlashKeys / 8; ++n)
      VRNET_UNROLL for (int i = 0; i < 4; ++i) {
        const float p = expf(score[n][i] - shift[i >> 1]);
        tile_sum[i >> 1] += p;
        p_tile[(warp_row + g + 8 * (i >> 1)) * kFlashProbStride + n * 8 + 2 * t + (i & 1)] = p;
      }
    VRNET_UNROLL
    for (int s = 0; s < 2; ++s) {
      for (int offset = 1; offset < 4; offset <<= 1) tile_sum[s] += __shfl_xor_sync(kFullWarp, tile_sum[s], offset);
      row_sum[s] = row_sum[s] * alpha[s] + tile_sum[s];
    }
    VRNET_UNROLL
    for (int v = 0; v < kFlashValueTiles; ++v)
      VRNET_UNROLL for (int i = 0; i < 4; ++i) acc[v][i] *= alpha[i >> 1];
    __syncwarp();

    // O += P V
    warp_products_ab<kPasses>(acc, p_tile + warp_row * kFlashProbStride, kFlashProbStride, v_tile, value_stride,
                              kFlashKeys / 8, value_tiles, lane);
  }

  if (key_splits > 1) {
    const int64_t part = (b * key_splits + split) * N;
    const float ones[2] = {1.0f, 1.0f};
    VRNET_UNROLL
    for (int s = 0; s < 2; ++s) {
      const int64_t row = row0 + warp_row + g + 8 * s;
      if (row < N && t == 0) {
        partial_max[part + row] = row_max[s];
        partial_sum[part + row] = row_sum[s];
        partial_peak[part + row] = row_peak[s];
      }
    }
    store_rows(acc, ones, row0 + warp_row, N, D, partial_acc + part * D, lane);
    return;
  }
  float inverse_sum[2];
  VRNET_UNROLL
  for (int s = 0; s < 2; ++s) {
    inverse_sum[s] = 1.0f / row_sum[s];
    const int64_t row = row0 + warp_row + g + 8 * s;
    if (row < N && t == 0) {
      lse[b * N + row] = row_max[s] + logf(row_sum[s]);
      argmax[b * N + row] = row_peak[s];
    }
  }
  store_rows(acc, inverse_sum, row0 + warp_row, N, D, out + b * N * D, lane);
}

// The key splits of soft_match_flash_kernel combined, a thread per query row r = b * N + n (BN rows):
// m the largest split maximum, each split weighted by exp(m_split - m), in split order (deterministic);
// the first peak of the first split that reaches m.
__global__ void soft_match_flash_combine_kernel(const float* __restrict__ partial_acc,
                                                const float* __restrict__ partial_max,
                                                const float* __restrict__ partial_sum,
                                                const int64_t* __restrict__ partial_peak, int64_t BN, int64_t N,
                                                int64_t key_splits, int D, float* __restrict__ out,
                                                float* __restrict__ lse, int64_t* __restrict__ argmax) {
  const int64_t r = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (r >= BN) return;
  const int64_t first = (r / N * key_splits) * N + r % N;  // split s of row r at first + s * N
  float row_max = -INFINITY;
  int64_t peak = 0;
  for (int64_t s = 0; s < key_splits; ++s)
    take_first_max(row_max, peak, partial_max[first + s * N], partial_peak[first + s * N]);
  float weight[kFlashMaxSplits];
  float row_sum = 0.0f;
  for (int64_t s = 0; s < key_splits; ++s) {
    weight[s] = expf(partial_max[first + s * N] - row_max);
    row_sum += partial_sum[first + s * N] * weight[s];
  }
  lse[r] = row_max + logf(row_sum);
  argmax[r] = peak;
  const float inverse_sum = 1.0f / row_sum;
  for (int d = 0; d < D; ++d) {
    float total = 0.0f;
    for (int64_t s = 0; s < key_splits; ++s) total += partial_acc[(first + s * N) * D + d] * weight[s];
    out[r * D + d] = total * inverse_sum;
  }
}

// ---------------------------------------------------------------------------------------------------
// The backward, as flash attention's: with P = exp(scale Q Kᵀ - lse) recomputed tile by tile from the
// saved log-normaliser, dP = dO Vᵀ and delta_i = dO_i . O_i - dlse_i (given),
//   dS = P (dP - delta),  dQ = scale dS K,  dK = scale dSᵀ Q,  dV = Pᵀ dO.
// Two kernels, each owning the rows it writes (no atomics: deterministic): blocks of 2 warps take 32
// keys and walk over the queries in tiles of 32 (dK, dV), or take 32 queries and walk over the keys
// (dQ). Feature and value tiles use flash_feature_stride (a 2-way bank conflict where read as B).

constexpr int kFlashBackWarps = 2;
constexpr int kFlashBackThreads = kFlashBackWarps * 32;
constexpr int kFlashBackRows = kFlashBackWarps * 16;  // keys (dK, dV) or queries (dQ) per block
constexpr int kFlashBackTile = 32;                     // queries or keys per shared-memory tile

// Floats of dynamic shared memory of either backward kernel: two feature tiles and two value tiles of
// 32 rows, and per warp two 16 x 32 probability tiles, plus 64 floats of row statistics.
VRNET_HOST_DEVICE constexpr int flash_backward_shared_floats(int c, int d) {
  return 2 * kFlashBackTile * (flash_feature_stride(c) + flash_feature_stride(d)) +
         2 * kFlashBackWarps * 16 * kFlashProbStride + 2 * kFlashBackTile;
}

// grid: one block per (batch item, 32 keys), blockIdx.x = b * key_tiles + tile; kFlashBackThreads
// threads; flash_backward_shared_floats(C, D) floats of dynamic shared memory.
template <int kPasses>
__global__ void soft_match_flash_grad_kv_kernel(const float* __restrict__ query, const float* __restrict__ key,
                                                const float* __restrict__ values, const float* __restrict__ grad_out,
                                                const float* __restrict__ lse, const float* __restrict__ delta,
                                                int64_t N, int64_t M, int C, int D, float scale, int64_t key_tiles,
                                                float* __restrict__ grad_key, float* __restrict__ grad_values) {
  VRNET_DYNAMIC_SHARED(float, shared);
  const int fs = flash_feature_stride(C), vs = flash_feature_stride(D);
  float* k_tile = shared;                               // the block's keys (A of Sᵀ)
  float* v_tile = k_tile + kFlashBackTile * fs;         // their values (A of dPᵀ)
  float* q_tile = v_tile + kFlashBackTile * vs;         // a tile of queries
  float* go_tile = q_tile + kFlashBackTile * fs;        // their output gradients
  float* p_tiles = go_tile + kFlashBackTile * vs;       // per warp: Pᵀ, then dSᵀ (16 keys x 32 queries)
  float* row_lse = p_tiles + 2 * kFlashBackWarps * 16 * kFlashProbStride;
  float* row_delta = row_lse + kFlashBackTile;

  const auto [b, j0, warp, lane, g, t, warp_row] = RowTileThread(blockIdx.x, key_tiles, kFlashBackRows);
  float* pt_tile = p_tiles + warp * 2 * 16 * kFlashProbStride;
  float* dst_tile = pt_tile + 16 * kFlashProbStride;
  const int feature_steps = (C + 7) / 8, value_steps = (D + 7) / 8;

  load_tile(key + b * M * C, j0, M, C, kFlashBackTile, fs, k_tile);
  load_tile(values + b * M * D, j0, M, D, kFlashBackTile, vs, v_tile);
  float acc_k[kFlashValueTiles][4], acc_v[kFlashValueTiles][4];
  zero(acc_k);
  zero(acc_v);

  for (int64_t i0 = 0; i0 < N; i0 += kFlashBackTile) {
    __syncthreads();  // every warp is done with the previous query tile (and the keys are loaded)
    load_tile(query + b * N * C, i0, N, C, kFlashBackTile, fs, q_tile);
    load_tile(grad_out + b * N * D, i0, N, D, kFlashBackTile, vs, go_tile);
    for (int i = threadIdx.x; i < kFlashBackTile; i += blockDim.x) {
      const bool inside = i0 + i < N;  // queries past N weigh exp(-inf) = 0 (and have no output gradient)
      row_lse[i] = inside ? lse[b * N + i0 + i] : INFINITY;
      row_delta[i] = inside ? delta[b * N + i0 + i] : 0.0f;
    }
    __syncthreads();

    float st[kFlashBackTile / 8][4], dpt[kFlashBackTile / 8][4];  // Sᵀ = K Qᵀ and dPᵀ = V dOᵀ
    warp_products_abt<kPasses>(st, k_tile, fs, warp_row, q_tile, fs, feature_steps, lane);
    warp_products_abt<kPasses>(dpt, v_tile, vs, warp_row, go_tile, vs, value_steps, lane);
    VRNET_UNROLL
    for (int n = 0; n < kFlashBackTile / 8; ++n) {
      VRNET_UNROLL for (int i = 0; i < 4; ++i) {
        const int q = n * 8 + 2 * t + (i & 1), at = (g + 8 * (i >> 1)) * kFlashProbStride + q;
        const float p = expf(st[n][i] * scale - row_lse[q]);
        pt_tile[at] = p;
        dst_tile[at] = p * (dpt[n][i] - row_delta[q]);
      }
    }
    __syncwarp();
    warp_products_ab<kPasses>(acc_v, pt_tile, kFlashProbStride, go_tile, vs, kFlashBackTile / 8, value_steps, lane);
    warp_products_ab<kPasses>(acc_k, dst_tile, kFlashProbStride, q_tile, fs, kFlashBackTile / 8, feature_steps, lane);
  }

  const float scales[2] = {scale, scale}, ones[2] = {1.0f, 1.0f};
  store_rows(acc_k, scales, j0 + warp_row, M, C, grad_key + b * M * C, lane);
  store_rows(acc_v, ones, j0 + warp_row, M, D, grad_values + b * M * D, lane);
}

// grid: one block per (batch item, 32 queries), blockIdx.x = b * row_tiles + tile; kFlashBackThreads
// threads; flash_backward_shared_floats(C, D) floats of dynamic shared memory.
template <int kPasses>
__global__ void soft_match_flash_grad_query_kernel(const float* __restrict__ query, const float* __restrict__ key,
                                                   const float* __restrict__ values,
                                                   const float* __restrict__ grad_out, const float* __restrict__ lse,
                                                   const float* __restrict__ delta, int64_t N, int64_t M, int C, int D,
                                                   float scale, int64_t row_tiles, float* __restrict__ grad_query) {
  VRNET_DYNAMIC_SHARED(float, shared);
  const int fs = flash_feature_stride(C), vs = flash_feature_stride(D);
  float* q_tile = shared;                          // the block's queries (A of S)
  float* go_tile = q_tile + kFlashBackTile * fs;   // their output gradients (A of dP)
  float* k_tile = go_tile + kFlashBackTile * vs;   // a tile of keys
  float* v_tile = k_tile + kFlashBackTile * fs;    // their values
  float* ds_tiles = v_tile + kFlashBackTile * vs;  // per warp: dS (16 queries x 32 keys)

  const auto [b, row0, warp, lane, g, t, warp_row] = RowTileThread(blockIdx.x, row_tiles, kFlashBackRows);
  float* ds_tile = ds_tiles + warp * 2 * 16 * kFlashProbStride;
  const int feature_steps = (C + 7) / 8, value_steps = (D + 7) / 8;

  load_tile(query + b * N * C, row0, N, C, kFlashBackTile, fs, q_tile);
  load_tile(grad_out + b * N * D, row0, N, D, kFlashBackTile, vs, go_tile);
  float own_lse[2], own_delta[2];
  VRNET_UNROLL
  for (int s = 0; s < 2; ++s) {
    const int64_t row = row0 + warp_row + g + 8 * s;
    own_lse[s] = row < N ? lse[b * N + row] : 0.0f;
    own_delta[s] = row < N ? delta[b * N + row] : 0.0f;
  }
  float acc[kFlashValueTiles][4];
  zero(acc);

  for (int64_t j0 = 0; j0 < M; j0 += kFlashBackTile) {
    __syncthreads();  // every warp is done with the previous key tile (and the queries are loaded)
    load_tile(key + b * M * C, j0, M, C, kFlashBackTile, fs, k_tile);
    load_tile(values + b * M * D, j0, M, D, kFlashBackTile, vs, v_tile);
    __syncthreads();

    float score[kFlashBackTile / 8][4], dp[kFlashBackTile / 8][4];  // S = Q Kᵀ (as the forward) and dP = dO Vᵀ
    warp_products_abt<kPasses>(score, q_tile, fs, warp_row, k_tile, fs, feature_steps, lane);
    warp_products_abt<kPasses>(dp, go_tile, vs, warp_row, v_tile, vs, value_steps, lane);
    VRNET_UNROLL
    for (int n = 0; n < kFlashBackTile / 8; ++n) {
      VRNET_UNROLL for (int i = 0; i < 4; ++i) {
        const int64_t j = j0 + n * 8 + 2 * t + (i & 1);
        const float p = j < M ? expf(score[n][i] * scale - own_lse[i >> 1]) : 0.0f;
        ds_tile[(g + 8 * (i >> 1)) * kFlashProbStride + n * 8 + 2 * t + (i & 1)] = p * (dp[n][i] - own_delta[i >> 1]);
      }
    }
    __syncwarp();
    warp_products_ab<kPasses>(acc, ds_tile, kFlashProbStride, k_tile, fs, kFlashBackTile / 8, feature_steps, lane);
  }

  const float scales[2] = {scale, scale};
  store_rows(acc, scales, row0 + warp_row, N, C, grad_query + b * N * C, lane);
}

}  // namespace vrnet
