// CUDA spatial consistency: the steps of the CPU op (spatial_consistency_cpu.cpp) on the device, with
// no host synchronisation between them.
//
//   columns   one thread per correspondence: the coordinates as six columns (px, py, pz, qx, qy, qz),
//             in double as given and in float relative to the first correspondence;
//   graph     one thread per 64-bit word of the compatibility graph (K rows of `words` words), the
//             32 lanes of a warp on consecutive rows of one word column (each reads the same 64
//             columns); the CPU op's test (spatial_consistency_math.h, rounded alike), so the graph is
//             the CPU op's bit for bit; float or double as the device flag `in_float` says;
//   degree    one thread per row;
//   seeds     one block: the correspondences by degree (sorted by the glue), kSeedChunk candidates a
//             round, each checked against the seeds of earlier rounds and against the earlier
//             candidates of its round in parallel, then accepted in order by one thread;
//   scores    one block per seed, one warp per neighbour j: the second-order score (a popcount of two
//             rows ANDed) as a sort key, score << kKeyIndexBits | (kKeyIndexMask - j), so that the
//             glue's top-k picks the CPU op's neighbours (highest score, then lowest index);
//   fits      one thread per seed: Kabsch on the seed and its neighbours in that order (the CPU op's
//             sums);
//   count     blocks of correspondences x seeds: each fit's inliers (integer atomics);
//   refine    one block: the best fit (most inliers, then the earlier seed), refitted on its inliers
//             while they grow. Its sums run in a fixed order over the block (the CPU op sums the
//             inliers one after another), so the refined transform can differ from the CPU op's in
//             the last bits; both are deterministic.
#pragma once

#include <cmath>

#include "common/cuda_device.cuh"
#include "kabsch/procrustes.h"
#include "spatial_consistency/spatial_consistency_math.h"

namespace vrnet {

constexpr int kScThreads = 256;             // threads of the seeds, scores and refine blocks (a power of two)
constexpr int kSeedChunk = kScThreads;      // candidate seeds per round of the seeds kernel
constexpr int kSeedChunkWords = kSeedChunk / 64;
constexpr int kKeyIndexBits = 16;           // the neighbour's index in the low bits of its sort key
constexpr int64_t kKeyIndexMask = (int64_t{1} << kKeyIndexBits) - 1;  // > the largest index (1 << 15)
constexpr int kMaxGraphWords = 512;         // words of one graph row at most: (1 << 15) / 64
constexpr int kFitDoubles = 12;             // a fit: R (9, row-major), t (3)

__global__ void sc_columns_kernel(const double* __restrict__ p, const double* __restrict__ q, int64_t K,
                                  double* __restrict__ cols_d, float* __restrict__ cols_f) {
  const int64_t k = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= K) return;
  for (int a = 0; a < 3; ++a) {
    cols_d[a * K + k] = p[3 * k + a];
    cols_d[(3 + a) * K + k] = q[3 * k + a];
    cols_f[a * K + k] = static_cast<float>(sub_rn(p[3 * k + a], p[a]));
    cols_f[(3 + a) * K + k] = static_cast<float>(sub_rn(q[3 * k + a], q[a]));
  }
}

// Bits of correspondences [j0, j0 + count) compatible with i (spatial_consistency_math.h).
template <typename T>
__device__ uint64_t sc_compatible_word(const T* cols, int64_t K, int64_t i, int64_t j0, int64_t count, T t2) {
  uint64_t bits = 0;
  for (int64_t l = 0; l < count; ++l) bits |= static_cast<uint64_t>(compatible(cols, K, i, j0 + l, t2)) << l;
  return bits;
}

__global__ void sc_graph_kernel(const double* __restrict__ cols_d, const float* __restrict__ cols_f,
                                const bool* __restrict__ in_float, int64_t K, int64_t words, double tolerance,
                                int64_t* __restrict__ graph) {
  const int64_t item = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (item >= K * words) return;
  const int64_t w = item / K, i = item % K, count = K - 64 * w < 64 ? K - 64 * w : 64;
  const double t2 = mul_rn(tolerance, tolerance);
  uint64_t word = *in_float ? sc_compatible_word(cols_f, K, i, 64 * w, count, static_cast<float>(t2))
                            : sc_compatible_word(cols_d, K, i, 64 * w, count, t2);
  if ((i >> 6) == w) word &= ~(uint64_t{1} << (i & 63));  // not compatible with itself
  graph[i * words + w] = static_cast<int64_t>(word);
}

__global__ void sc_degree_kernel(const int64_t* __restrict__ graph, int64_t K, int64_t words,
                                 int64_t* __restrict__ degree) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= K) return;
  int64_t count = 0;
  for (int64_t w = 0; w < words; ++w) count += __popcll(static_cast<unsigned long long>(graph[i * words + w]));
  degree[i] = count;
}

// One block of kScThreads. seeds (S,): the chosen correspondences, the first *seed_count of them.
__global__ void sc_seeds_kernel(const double* __restrict__ p, const int64_t* __restrict__ order,
                                const int64_t* __restrict__ degree, int64_t K, int64_t S, double tolerance,
                                int64_t* __restrict__ seeds, int64_t* __restrict__ seed_count) {
  VRNET_SHARED(uint64_t, near_earlier, kSeedChunk * kSeedChunkWords);  // [t]: earlier candidates near t
  VRNET_SHARED(int, usable, kSeedChunk);  // 1: may be chosen; 0: near a seed of an earlier round; -1: stop
  VRNET_SHARED(int64_t, chosen, 2);       // seeds so far, whether the choice is over
  const int t = threadIdx.x;
  if (t == 0) chosen[0] = 0, chosen[1] = 0;
  __syncthreads();
  for (int64_t base = 0; base < K; base += kSeedChunk) {
    if (chosen[1]) break;  // every thread reads it between the same two barriers
    const int64_t count = chosen[0], position = base + t;
    int status = -1;
    if (position < K && degree[order[position]] >= 2) {
      const double* candidate = p + 3 * order[position];
      status = 1;
      for (int64_t s = 0; s < count && status; ++s)
        if (point_distance(candidate, p + 3 * seeds[s]) < tolerance) status = 0;
      for (int w = 0; w < kSeedChunkWords; ++w) {  // needed only by a candidate that may be chosen
        uint64_t bits = 0;
        for (int l = 0; l < 64 && status; ++l) {
          const int u = 64 * w + l;
          if (u < t && point_distance(candidate, p + 3 * order[base + u]) < tolerance) bits |= uint64_t{1} << l;
        }
        near_earlier[t * kSeedChunkWords + w] = bits;
      }
    } else {
      for (int w = 0; w < kSeedChunkWords; ++w) near_earlier[t * kSeedChunkWords + w] = 0;
    }
    usable[t] = status;
    __syncthreads();
    if (t == 0) {
      uint64_t accepted[kSeedChunkWords] = {};
      int64_t n = count;
      bool over = false;
      for (int u = 0; u < kSeedChunk && !over; ++u) {
        if (n >= S || usable[u] < 0) {
          over = true;
        } else if (usable[u] == 1) {
          bool near = false;
          for (int w = 0; w < kSeedChunkWords; ++w)
            near = near || (near_earlier[u * kSeedChunkWords + w] & accepted[w]);
          if (!near) {
            seeds[n++] = order[base + u];
            accepted[u >> 6] |= uint64_t{1} << (u & 63);
          }
        }
      }
      chosen[0] = n;
      chosen[1] = over;
    }
    __syncthreads();
  }
  if (t == 0) *seed_count = chosen[0];
}

__device__ inline int warp_sum_int(int v) {
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_xor_sync(kFullWarp, v, offset);
  return v;
}

// Block s (of S): keys[s, j] for every j, -1 where j is not compatible with seed s (or s is past the
// seeds chosen).
__global__ void sc_scores_kernel(const int64_t* __restrict__ graph, const int64_t* __restrict__ seeds,
                                 const int64_t* __restrict__ seed_count, int64_t K, int64_t words,
                                 int64_t* __restrict__ keys) {
  VRNET_SHARED(uint64_t, seed_row, kMaxGraphWords);
  const int64_t s = blockIdx.x;
  int64_t* out = keys + s * K;
  if (s >= *seed_count) {  // the whole block
    for (int64_t j = threadIdx.x; j < K; j += blockDim.x) out[j] = -1;
    return;
  }
  const int64_t seed = seeds[s];
  for (int64_t w = threadIdx.x; w < words; w += blockDim.x)
    seed_row[w] = static_cast<uint64_t>(graph[seed * words + w]);
  __syncthreads();
  const int lane = threadIdx.x & 31, warps = blockDim.x / 32;
  for (int64_t j = threadIdx.x / 32; j < K; j += warps) {
    if (!((seed_row[j >> 6] >> (j & 63)) & 1u)) {  // the same for the whole warp
      if (lane == 0) out[j] = -1;
      continue;
    }
    int score = 0;
    for (int64_t w = lane; w < words; w += 32)
      score += __popcll(seed_row[w] & static_cast<uint64_t>(graph[j * words + w]));
    score = warp_sum_int(score);
    if (lane == 0) out[j] = (static_cast<int64_t>(score) << kKeyIndexBits) | (kKeyIndexMask - j);
  }
}

// One thread per seed: Kabsch on the seed and its neighbours (top_keys (S, c), best first, -1 past the
// last), summed as the CPU op sums them. fits (S, kFitDoubles); fit_ok[s] = 0 below 3 members.
__global__ void sc_fits_kernel(const double* __restrict__ p, const double* __restrict__ q,
                               const int64_t* __restrict__ seeds, const int64_t* __restrict__ seed_count,
                               const int64_t* __restrict__ top_keys, int64_t S, int64_t c,
                               double* __restrict__ fits, int64_t* __restrict__ fit_ok) {
  const int64_t s = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (s >= S) return;
  const int64_t* keys = top_keys + s * c;
  int64_t n = 0;
  if (s < *seed_count) {
    n = 1;
    while (n - 1 < c && keys[n - 1] >= 0) ++n;
  }
  fit_ok[s] = n >= 3;
  if (n < 3) return;
  auto member = [&](int64_t m) { return m == 0 ? seeds[s] : kKeyIndexMask - (keys[m - 1] & kKeyIndexMask); };
  Procrustes fit;
  fit.wsum = static_cast<double>(n);
  for (int64_t m = 0; m < n; ++m) {
    const int64_t k = member(m);
    for (int a = 0; a < 3; ++a) {
      fit.src_c[a] = add_rn(fit.src_c[a], p[3 * k + a] / fit.wsum);
      fit.tgt_c[a] = add_rn(fit.tgt_c[a], q[3 * k + a] / fit.wsum);
    }
  }
  for (int64_t m = 0; m < n; ++m) {
    const int64_t k = member(m);
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b)
        fit.H[3 * a + b] = add_rn(fit.H[3 * a + b],
                                  mul_rn(sub_rn(p[3 * k + a], fit.src_c[a]), sub_rn(q[3 * k + b], fit.tgt_c[b])) /
                                      fit.wsum);
  }
  fit.solve_rotation();
  fit.write(fits + s * kFitDoubles, fits + s * kFitDoubles + 9);
}

// Grid (blocks over K, S): counts[s] += the correspondences fit s maps within the threshold.
__global__ void sc_count_kernel(const double* __restrict__ cols_d, const double* __restrict__ fits,
                                const int64_t* __restrict__ fit_ok, int64_t K, double threshold2,
                                int64_t* __restrict__ counts) {
  const int64_t s = blockIdx.y;
  if (!fit_ok[s]) return;  // the whole block
  const int64_t k = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const double* fit = fits + s * kFitDoubles;
  const bool inside = k < K && maps_within(fit, fit + 9, cols_d, K, k, threshold2);
  const unsigned int ballot = __ballot_sync(kFullWarp, inside);
  if ((threadIdx.x & 31) == 0 && ballot != 0)
    atomicAdd(reinterpret_cast<unsigned long long*>(counts + s), static_cast<unsigned long long>(__popc(ballot)));
}

// Sums values[t * N + v] over the block's threads t for each v, in a fixed order; every thread gets
// the N totals in `out`. Call with every thread of the block, values written, no barrier needed before.
template <int N>
__device__ void sc_block_sum(double* values, double* out) {
  __syncthreads();
  for (int stride = kScThreads / 2; stride > 0; stride >>= 1) {
    if (static_cast<int>(threadIdx.x) < stride)
      for (int v = 0; v < N; ++v) values[threadIdx.x * N + v] += values[(threadIdx.x + stride) * N + v];
    __syncthreads();
  }
  for (int v = 0; v < N; ++v) out[v] = values[v];
  __syncthreads();
}

// The inliers of `fit` as bits (words of 64 correspondences) into `bits`; returns their number (every
// thread).
__device__ inline double sc_inlier_bits(const double* fit, const double* cols, int64_t K, int64_t words,
                                        double threshold2, uint64_t* bits, double* partial) {
  double count = 0;
  for (int64_t w = threadIdx.x; w < words; w += kScThreads) {
    uint64_t word = 0;
    for (int64_t k = 64 * w; k < K && k < 64 * w + 64; ++k)
      word |= static_cast<uint64_t>(maps_within(fit, fit + 9, cols, K, k, threshold2)) << (k & 63);
    bits[w] = word;
    count += __popcll(word);
  }
  partial[threadIdx.x] = count;
  double total;
  sc_block_sum<1>(partial, &total);
  return total;
}

// Kabsch on the correspondences whose bits are set (n of them) into `fit` (shared); each thread
// sums a contiguous range of correspondences, the block's partial sums are added in a fixed order.
__device__ inline void sc_refit(const double* cols, int64_t K, const uint64_t* members, double n, double* partial,
                                double* fit) {
  const int64_t per_thread = (K + kScThreads - 1) / kScThreads, first = threadIdx.x * per_thread;
  const int64_t last = first + per_thread < K ? first + per_thread : K;
  auto is_member = [&](int64_t k) { return (members[k >> 6] >> (k & 63)) & 1u; };
  double sums[6] = {0, 0, 0, 0, 0, 0};
  for (int64_t k = first; k < last; ++k)
    if (is_member(k))
      for (int v = 0; v < 6; ++v) sums[v] = add_rn(sums[v], cols[v * K + k]);
  for (int v = 0; v < 6; ++v) partial[threadIdx.x * 6 + v] = sums[v];
  double centroids[6];
  sc_block_sum<6>(partial, centroids);
  for (int v = 0; v < 6; ++v) centroids[v] /= n;
  double products[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  for (int64_t k = first; k < last; ++k)
    if (is_member(k))
      for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b)
          products[3 * a + b] = add_rn(products[3 * a + b], mul_rn(sub_rn(cols[a * K + k], centroids[a]),
                                                                   sub_rn(cols[(3 + b) * K + k], centroids[3 + b])));
  for (int v = 0; v < 9; ++v) partial[threadIdx.x * 9 + v] = products[v];
  double H[9];
  sc_block_sum<9>(partial, H);
  if (threadIdx.x == 0) {
    Procrustes solve;
    solve.wsum = n;
    for (int a = 0; a < 3; ++a) solve.src_c[a] = centroids[a], solve.tgt_c[a] = centroids[3 + a];
    for (int v = 0; v < 9; ++v) solve.H[v] = H[v] / n;
    solve.solve_rotation();
    solve.write(fit, fit + 9);
  }
  __syncthreads();
}

// One block of kScThreads: the best of the S fits, refitted on its inliers while they grow (at most
// 10 rounds, as the CPU op); transform (4, 4), mask (K,).
__global__ void sc_refine_kernel(const double* __restrict__ cols_d, const double* __restrict__ fits,
                                 const int64_t* __restrict__ fit_ok, const int64_t* __restrict__ counts,
                                 int64_t S, int64_t K, int64_t words, double threshold2,
                                 double* __restrict__ transform, bool* __restrict__ mask) {
  VRNET_SHARED(uint64_t, members, kMaxGraphWords);
  VRNET_SHARED(uint64_t, grown, kMaxGraphWords);
  VRNET_SHARED(double, best, kFitDoubles);
  VRNET_SHARED(double, refit, kFitDoubles);
  VRNET_SHARED(double, partial, kScThreads * 9);
  VRNET_SHARED(int64_t, best_count, 1);
  if (threadIdx.x == 0) {
    int64_t chosen = -1, most = -1;
    for (int64_t s = 0; s < S; ++s)
      if (fit_ok[s] && counts[s] > most) chosen = s, most = counts[s];
    for (int v = 0; v < kFitDoubles; ++v)  // no fit: the identity
      best[v] = chosen >= 0 ? fits[chosen * kFitDoubles + v] : (v % 4 == 0 && v < 9);
    best_count[0] = most;
  }
  __syncthreads();
  double n = 0;
  if (best_count[0] >= 3) {
    n = sc_inlier_bits(best, cols_d, K, words, threshold2, members, partial);
  } else {
    for (int64_t w = threadIdx.x; w < words; w += kScThreads) members[w] = 0;
  }
  __syncthreads();
  for (int round = 0; round < 10 && n >= 3; ++round) {
    sc_refit(cols_d, K, members, n, partial, refit);
    const double grown_count = sc_inlier_bits(refit, cols_d, K, words, threshold2, grown, partial);
    if (grown_count < n) break;
    double changed = 0;
    for (int64_t w = threadIdx.x; w < words; w += kScThreads) changed += grown[w] != members[w];
    partial[threadIdx.x] = changed;
    sc_block_sum<1>(partial, &changed);
    for (int64_t w = threadIdx.x; w < words; w += kScThreads) members[w] = grown[w];
    if (threadIdx.x < kFitDoubles) best[threadIdx.x] = refit[threadIdx.x];
    n = grown_count;
    __syncthreads();
    if (changed == 0) break;
  }
  if (threadIdx.x < 16) {
    const int a = threadIdx.x / 4, b = threadIdx.x % 4;
    transform[threadIdx.x] = a == 3 ? (b == 3 ? 1.0 : 0.0) : (b == 3 ? best[9 + a] : best[3 * a + b]);
  }
  for (int64_t k = threadIdx.x; k < K; k += kScThreads) mask[k] = (members[k >> 6] >> (k & 63)) & 1u;
}

}  // namespace vrnet
