// CUDA kNN kernels. knn3_kernel (C = 3): one thread per query scans the reference cloud in
// shared-memory tiles and keeps its top-k in a register-resident sorted buffer (RegisterTopK; exact
// differences, as the CPU grid search); knn_tiled_kernel does the same for feature rows of up to
// 128 float (64 double) values and k <= 32. Larger rows, as the CPU's GEMM-tiled search: knn_chunk_kernel
// merges chunks of dot products of the centred clouds into per-query candidate buffers,
// knn_rerank_kernel re-ranks them by exact distance, and knn_exact_rows_kernel scans exhaustively
// the rows where the approximation could have dropped a true neighbour. For large 3-D reference
// clouds, knn_grid_kernel searches the CPU's uniform grid (knn/grid.h; the points sorted by cell by
// the glue) instead of scanning every point. The backward kernels gather per output (the reference
// side through the inverse graph), so they are deterministic.
#pragma once

#include <limits>

#include "common/cuda_device.cuh"
#include "common/tensor_core.cuh"
#include "knn/grid.h"
#include "knn/topk.h"

namespace vrnet {

constexpr int kKnnTile = 256;  // reference points per shared-memory tile (C = 3)

template <typename scalar_t>
__device__ inline scalar_t knn_sq_dist3(scalar_t qx, scalar_t qy, scalar_t qz, const scalar_t* r) {
  const scalar_t dx = qx - r[0], dy = qy - r[1], dz = qz - r[2];
  return add_rn(add_rn(mul_rn(dx, dx), mul_rn(dy, dy)), mul_rn(dz, dz));
}

// The first k entries of a buffer to global memory (the guard keeps the indices compile-time).
template <typename scalar_t, int KMAX>
__device__ inline void knn_store(const RegisterTopK<scalar_t, KMAX>& top, int64_t k, scalar_t* dist, int64_t* idx) {
  VRNET_UNROLL
  for (int j = 0; j < KMAX; ++j)
    if (j < k) {
      dist[j] = top.dist[j];
      idx[j] = top.idx[j];
    }
}

template <typename scalar_t, int KMAX>
__global__ void knn3_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ ref, int64_t N,
                            int64_t M, int64_t k, bool exclude_self, scalar_t* __restrict__ dist_out,
                            int64_t* __restrict__ idx_out) {
  VRNET_SHARED(scalar_t, tile, 3 * kKnnTile);
  const int64_t b = blockIdx.y;
  const int64_t n = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const bool active = n < N;
  RegisterTopK<scalar_t, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  scalar_t worst = top.worst();
  scalar_t qx = 0, qy = 0, qz = 0;
  if (active) {
    const scalar_t* q = query + (b * N + n) * 3;
    qx = q[0];
    qy = q[1];
    qz = q[2];
  }
  const int64_t self = exclude_self ? n : -1;
  for (int64_t r0 = 0; r0 < M; r0 += kKnnTile) {
    const int count = static_cast<int>(M - r0 < kKnnTile ? M - r0 : kKnnTile);
    __syncthreads();
    for (int t = threadIdx.x; t < 3 * count; t += blockDim.x) tile[t] = ref[(b * M + r0) * 3 + t];
    __syncthreads();
    if (!active) continue;
    for (int j = 0; j < count; ++j) {
      const scalar_t d = knn_sq_dist3(qx, qy, qz, tile + 3 * j);
      if (d <= worst && r0 + j != self) {
        top.push(d, static_cast<int32_t>(r0 + j));
        worst = top.worst();
      }
    }
  }
  if (active) knn_store(top, k, dist_out + (b * N + n) * k, idx_out + (b * N + n) * k);
}

// The cell of each reference point (cells(): a far stray, outside the grid's box).
template <typename scalar_t>
__global__ void knn_grid_cells_kernel(const scalar_t* __restrict__ ref, const bool* __restrict__ inside, int64_t M,
                                      GridShape grid, int64_t* __restrict__ cell) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= M) return;
  const scalar_t* p = ref + 3 * i;
  cell[i] = inside[i] ? grid.cell_id(grid.cell_coord(p[0], 0), grid.cell_coord(p[1], 1), grid.cell_coord(p[2], 2))
                      : grid.cells();
}

// One thread per query, the CPU's grid search (knn_cpu.cpp, Grid::search): the far strays, then
// cube shells of cells around the query's cell, a cell skipped when its box lies beyond the buffer's
// worst candidate, until no unvisited cell can hold a closer point. xyz, order: the reference
// points sorted by cell and their original indices; start (cells + 1): each cell's first sorted
// point; the far strays from far_begin on.
template <typename scalar_t, int KMAX>
__global__ void knn_grid_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ xyz,
                                const int64_t* __restrict__ order, const int64_t* __restrict__ start,
                                int64_t far_begin, GridShape grid, int64_t N, int64_t M, int64_t k, bool exclude_self,
                                scalar_t* __restrict__ dist_out, int64_t* __restrict__ idx_out) {
  const int64_t n = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (n >= N) return;
  const scalar_t* q = query + 3 * n;
  const int64_t self = exclude_self ? n : -1;
  RegisterTopK<scalar_t, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  const auto offer = [&](int64_t from, int64_t to) {
    for (int64_t p = from; p < to; ++p)
      if (order[p] != self) top.push(knn_sq_dist3(q[0], q[1], q[2], xyz + 3 * p), static_cast<int32_t>(order[p]));
  };
  offer(far_begin, M);
  const int64_t c[3] = {grid.cell_coord(q[0], 0), grid.cell_coord(q[1], 1), grid.cell_coord(q[2], 2)};
  double outside[3], outside_total = 0;
  for (int a = 0; a < 3; ++a) {
    outside[a] = grid.outside_sq(q, a);
    outside_total += outside[a];
  }
  for (int64_t r = 0;; ++r) {
    const int64_t z0 = c[2] - r > 0 ? c[2] - r : 0, z1 = c[2] + r < grid.dims[2] - 1 ? c[2] + r : grid.dims[2] - 1;
    const int64_t y0 = c[1] - r > 0 ? c[1] - r : 0, y1 = c[1] + r < grid.dims[1] - 1 ? c[1] + r : grid.dims[1] - 1;
    const int64_t x0 = c[0] - r > 0 ? c[0] - r : 0, x1 = c[0] + r < grid.dims[0] - 1 ? c[0] + r : grid.dims[0] - 1;
    for (int64_t z = z0; z <= z1; ++z) {
      const bool z_shell = (z - c[2] == r) || (c[2] - z == r);
      for (int64_t y = y0; y <= y1; ++y) {
        const bool zy_shell = z_shell || (y - c[1] == r) || (c[1] - y == r);
        const int64_t step = zy_shell || r == 0 ? 1 : 2 * r;  // interior rows: their two shell cells only
        for (int64_t x = zy_shell ? x0 : c[0] - r; x <= x1; x += step) {
          if (x < x0) continue;
          const int64_t id = grid.cell_id(x, y, z);
          if (start[id] == start[id + 1]) continue;
          if (grid.cell_distance_sq(q, x, y, z) * (1.0 - 1e-5) > static_cast<double>(top.worst())) continue;
          offer(start[id], start[id + 1]);
        }
      }
    }
    bool more;
    const double bound = grid.beyond_sq(q, c, r, outside, outside_total, &more);
    if (!more || static_cast<double>(top.worst()) < bound * (1.0 - 1e-5)) break;
  }
  knn_store(top, k, dist_out + n * k, idx_out + n * k);
}

// Exact squared distance of two rows of C values: channel c into partial sum c % 8, one rounding per
// operation, the partials added pairwise (the CPU kernels' squared_distance, so that both give the
// same bits).
template <typename scalar_t>
__device__ inline scalar_t knn_exact_sq_dist(const scalar_t* q, const scalar_t* r, int64_t C) {
  scalar_t partial[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  int64_t c = 0;
  for (; c + 8 <= C; c += 8) {
#pragma unroll
    for (int l = 0; l < 8; ++l) {
      const scalar_t diff = sub_rn(q[c + l], r[c + l]);
      partial[l] = add_rn(partial[l], mul_rn(diff, diff));
    }
  }
#pragma unroll
  for (int l = 0; l < 8; ++l)  // the last C % 8 channels (unrolled: the partials stay in registers)
    if (c + l < C) {
      const scalar_t diff = sub_rn(q[c + l], r[c + l]);
      partial[l] = add_rn(partial[l], mul_rn(diff, diff));
    }
  return add_rn(add_rn(add_rn(partial[0], partial[1]), add_rn(partial[2], partial[3])),
                add_rn(add_rn(partial[4], partial[5]), add_rn(partial[6], partial[7])));
}

constexpr int kKnnTileValues = 4096;  // reference values per shared-memory tile (C > 3): C * refs

// Other C up to CMAX (and k <= KMAX): knn3_kernel's scan with C values a point. The query's values
// stay in registers (loops unrolled to CMAX, channels past C skipped), the reference cloud passes
// through shared memory in tiles of kKnnTileValues / C points, and every distance is
// knn_exact_sq_dist's (the same partial sums in the same order): the CPU's exact distances, bit for
// bit, at any offset from the origin, and no re-ranking.
template <typename scalar_t, int KMAX, int CMAX>
__global__ void knn_tiled_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ ref, int64_t N,
                                 int64_t M, int64_t C, int64_t k, bool exclude_self, scalar_t* __restrict__ dist_out,
                                 int64_t* __restrict__ idx_out) {
  VRNET_SHARED(scalar_t, tile, kKnnTileValues);
  const int64_t b = blockIdx.y;
  const int64_t n = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const bool active = n < N;
  const int64_t tile_points = kKnnTileValues / C;
  RegisterTopK<scalar_t, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  scalar_t worst = top.worst();
  scalar_t q[CMAX];
  VRNET_UNROLL
  for (int c = 0; c < CMAX; ++c) q[c] = active && c < C ? query[(b * N + n) * C + c] : scalar_t(0);
  const int64_t self = exclude_self ? n : -1;
  for (int64_t r0 = 0; r0 < M; r0 += tile_points) {
    const int64_t count = M - r0 < tile_points ? M - r0 : tile_points;
    __syncthreads();
    for (int64_t t = threadIdx.x; t < count * C; t += blockDim.x) tile[t] = ref[(b * M + r0) * C + t];
    __syncthreads();
    if (!active) continue;
    for (int64_t j = 0; j < count; ++j) {
      const scalar_t* r = tile + j * C;
      scalar_t partial[8] = {0, 0, 0, 0, 0, 0, 0, 0};  // channel c into partial c % 8, as knn_exact_sq_dist
      VRNET_UNROLL
      for (int c = 0; c < CMAX; ++c)
        if (c < C) {
          const scalar_t diff = sub_rn(q[c], r[c]);
          partial[c % 8] = add_rn(partial[c % 8], mul_rn(diff, diff));
        }
      const scalar_t d = add_rn(add_rn(add_rn(partial[0], partial[1]), add_rn(partial[2], partial[3])),
                                add_rn(add_rn(partial[4], partial[5]), add_rn(partial[6], partial[7])));
      if (d <= worst && r0 + j != self) {
        top.push(d, static_cast<int32_t>(r0 + j));
        worst = top.worst();
      }
    }
  }
  if (active) knn_store(top, k, dist_out + (b * N + n) * k, idx_out + (b * N + n) * k);
}

// Merges one chunk of dot products dots[b, j, n] = ref_c[b, r0 + j] . query_c[b, q0 + n] (clouds
// centred on the reference mean) into the running `width` best candidates of queries q0.., ranked by
// the approximate distance max(|q|^2 + |r|^2 - 2 q.r, 0) (+inf where not finite), as the CPU tiles
// compute it. State kept in cand_dist / cand_idx (B, N, width) between chunks.
template <typename scalar_t, int KMAX>
__global__ void knn_chunk_kernel(const scalar_t* __restrict__ dots, const scalar_t* __restrict__ query_norm,
                                 const scalar_t* __restrict__ ref_norm, int64_t N, int64_t M, int64_t q0,
                                 int64_t query_count, int64_t r0, int64_t ref_count, int64_t width, bool exclude_self,
                                 scalar_t* __restrict__ cand_dist, int64_t* __restrict__ cand_idx) {
  const int64_t b = blockIdx.y;
  const int64_t local = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (local >= query_count) return;
  const int64_t n = q0 + local;
  RegisterTopK<scalar_t, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  scalar_t* d_row = cand_dist + (b * N + n) * width;
  int64_t* i_row = cand_idx + (b * N + n) * width;
  if (r0 > 0) {  // the best of the earlier chunks (the other KMAX - width slots stay empty)
    VRNET_UNROLL
    for (int j = 0; j < KMAX; ++j)
      if (j < width) {
        top.dist[j] = d_row[j];
        top.idx[j] = static_cast<int32_t>(i_row[j]);
      }
  }
  scalar_t worst = top.worst();
  const scalar_t qn = query_norm[b * N + n];
  const scalar_t* col = dots + b * ref_count * query_count + local;
  const scalar_t largest = std::numeric_limits<scalar_t>::max();
  for (int64_t j = 0; j < ref_count; ++j) {
    const int64_t m = r0 + j;
    scalar_t d = sub_rn(add_rn(qn, ref_norm[b * M + m]), mul_rn(scalar_t(2), col[j * query_count]));
    d = d <= largest ? (d > scalar_t(0) ? d : scalar_t(0)) : std::numeric_limits<scalar_t>::infinity();
    if (d <= worst && !(exclude_self && m == n)) {
      top.push(d, static_cast<int32_t>(m));
      worst = top.worst();
    }
  }
  knn_store(top, width, d_row, i_row);
}

// Re-ranks each query's candidates by exact distance and writes its k best. The approximate
// distances are wrong by at most `slack` = relative_error (|q|^2 + max |r|^2); if a candidate dropped
// from the full buffer could still be among the k nearest (the last candidate is within 2 slack of
// the k-th, or the norms overflow), the row is flagged for the exhaustive exact scan.
template <typename scalar_t, int KMAX>
__global__ void knn_rerank_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ ref,
                                  const scalar_t* __restrict__ cand_dist, const int64_t* __restrict__ cand_idx,
                                  const scalar_t* __restrict__ query_norm, const scalar_t* __restrict__ ref_norm_max,
                                  int64_t N, int64_t M, int64_t C, int64_t width, int64_t k, scalar_t relative_error,
                                  scalar_t* __restrict__ dist_out, int64_t* __restrict__ idx_out,
                                  int32_t* __restrict__ exhaustive) {
  const int64_t b = blockIdx.y;
  const int64_t n = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (n >= N) return;
  const int64_t row = b * N + n;
  const scalar_t* d_row = cand_dist + row * width;
  const int64_t* i_row = cand_idx + row * width;
  const scalar_t* q = query + row * C;
  RegisterTopK<scalar_t, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  for (int64_t j = 0; j < width; ++j) {
    const int64_t m = i_row[j];
    if (m < M) top.push(knn_exact_sq_dist(q, ref + (b * M + m) * C, C), static_cast<int32_t>(m));
  }
  knn_store(top, k, dist_out + row * k, idx_out + row * k);
  const scalar_t slack = relative_error * (query_norm[row] + ref_norm_max[b]);
  const scalar_t kth = d_row[k - 1], last = d_row[width - 1];
  const bool full = i_row[width - 1] < M;
  const scalar_t largest = std::numeric_limits<scalar_t>::max();
  exhaustive[row] = !(slack <= largest) || !(kth <= largest) || (full && last <= kth + 2 * slack);
}

// The exact k nearest of each flagged query row, by a scan of all M references: a warp per row (grid:
// per_query_warp), lane l scanning references l, l + 32, ... into its own KMAX best, then the k best of
// the 32 lists by k rounds of a warp-wide minimum (ties by lower index; each reference is in one list).
template <typename scalar_t, int KMAX>
__global__ void knn_exact_rows_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ ref,
                                      const int32_t* __restrict__ exhaustive, int64_t N, int64_t M, int64_t C,
                                      int64_t k, bool exclude_self, scalar_t* __restrict__ dist_out,
                                      int64_t* __restrict__ idx_out) {
  const int64_t b = blockIdx.y;
  const int64_t n = (static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x) / 32;
  const int lane = threadIdx.x % 32;
  if (n >= N || !exhaustive[b * N + n]) return;  // the whole warp: one row
  const scalar_t* q = query + (b * N + n) * C;
  RegisterTopK<scalar_t, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  for (int64_t m = lane; m < M; m += 32)
    if (!(exclude_self && m == n)) top.push(knn_exact_sq_dist(q, ref + (b * M + m) * C, C), static_cast<int32_t>(m));
  for (int64_t j = 0; j < k; ++j) {
    scalar_t best = top.dist[0];
    int32_t best_idx = top.idx[0];
    for (int offset = 16; offset > 0; offset >>= 1) {
      const scalar_t other = __shfl_xor_sync(kFullWarp, best, offset);
      const int32_t other_idx = __shfl_xor_sync(kFullWarp, best_idx, offset);
      if (TopK<scalar_t>::less(other, other_idx, best, best_idx)) {
        best = other;
        best_idx = other_idx;
      }
    }
    if (lane == 0) {
      dist_out[(b * N + n) * k + j] = best;
      idx_out[(b * N + n) * k + j] = best_idx;
    }
    if (top.idx[0] == best_idx) top.pop_front(static_cast<int32_t>(M));
  }
}

// ---------------------------------------------------------------------------------------------------
// Feature rows (float32, C <= kKnnTensorCoreMaxC, k <= kKnnTensorCoreMaxK) on the TF32 tensor cores.
// knn_tensor_core_kernel: a block of kKnnTensorCoreWarps warps takes 16 query rows a warp of one
// batch item and walks over the reference rows in shared-memory tiles of 32; each warp's dot products
// by m16n8k8 products (three passes: each operand split into two TF32 parts, common/tensor_core.cuh), the
// approximate squared distances |q|^2 + |r|^2 - 2 q.r of the
// clouds centred on the reference mean. A row's scores lie with its four lanes (columns 2t, 2t + 1 of
// each 8-wide tile: lane t of the quad sees a fixed quarter of the reference rows), and each lane
// keeps the kKnnLaneCandidates best of its quarter for each of its two rows in registers. The four
// lists of each row (its candidates) go to knn_tensor_core_rerank_kernel, which ranks them by exact
// distance (knn_exact_sq_dist: the CPU's bits) and proves the result: a reference row a lane dropped
// lies at or beyond that lane's worst kept approximate distance, so once that bound less the
// approximation's error exceeds the k-th exact distance (less its own rounding) for every lane whose
// list is full, no dropped row can be among the k nearest. Rows without that proof are flagged for
// knn_exact_rows_kernel's exhaustive scan.

// Each reference cloud's mean in float64: grid (B, ceil(C / 32)), block (32, kKnnMeanSlices); thread (c, s)
// sums points s, s + kKnnMeanSlices, ... of channel c, the slices then added in order (deterministic).
constexpr int kKnnMeanSlices = 8;
template <typename scalar_t>
__global__ void knn_mean_kernel(const scalar_t* __restrict__ points, int64_t M, int64_t C,
                                double* __restrict__ mean) {
  VRNET_SHARED(double, partial, 32 * kKnnMeanSlices);
  const int64_t b = blockIdx.x, c = static_cast<int64_t>(blockIdx.y) * 32 + threadIdx.x;
  double sum = 0.0;
  if (c < C)
    for (int64_t p = threadIdx.y; p < M; p += kKnnMeanSlices) sum += static_cast<double>(points[(b * M + p) * C + c]);
  partial[threadIdx.y * 32 + threadIdx.x] = sum;
  __syncthreads();
  if (threadIdx.y != 0 || c >= C) return;
  double total = 0.0;
  for (int s = 0; s < kKnnMeanSlices; ++s) total += partial[s * 32 + threadIdx.x];
  mean[b * C + c] = total / static_cast<double>(M);
}

// rows (B, R, C) less their cloud's mean (B, C), in float64, rounded to scalar_t, and their squared norms
// (B, R): a thread per row (grid as per_query).
template <typename scalar_t>
__global__ void knn_centre_kernel(const scalar_t* __restrict__ rows, const double* __restrict__ mean, int64_t R,
                                  int64_t C, scalar_t* __restrict__ centred, scalar_t* __restrict__ norms) {
  const int64_t b = blockIdx.y, r = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (r >= R) return;
  const scalar_t* x = rows + (b * R + r) * C;
  scalar_t* y = centred + (b * R + r) * C;
  scalar_t norm = 0;
  for (int64_t c = 0; c < C; ++c) {
    y[c] = static_cast<scalar_t>(static_cast<double>(x[c]) - mean[b * C + c]);
    norm = add_rn(norm, mul_rn(y[c], y[c]));
  }
  norms[b * R + r] = norm;
}

constexpr int kKnnTensorCoreWarps = 2;
constexpr int kKnnTensorCoreRows = kKnnTensorCoreWarps * 16;  // query rows per block
constexpr int kKnnTensorCoreKeys = 32;                        // reference rows per shared-memory tile
constexpr int kKnnTensorCoreMaxC = 128;
constexpr int kKnnTensorCoreMaxK = 32;
constexpr int kKnnLaneCandidates = 16;                         // per lane and query row
// Three passes (about float32's accuracy): with one (TF32, ~1e-3 of the norms) the proof failed for 6-14 %
// of the rows of FPFH matching (similar descriptors) and 0.1-0.4 % of a model's feature graphs, against 0-0.4 %
// and none with three; each such row is scanned whole (benchmarks/knn_proof_rate.py).
constexpr int kKnnTensorCorePasses = 3;
constexpr int kKnnRowCandidates = 4 * kKnnLaneCandidates;      // per query row: the quad's four lists

// Floats of dynamic shared memory a block uses: the query rows, a reference tile and its norms.
VRNET_HOST_DEVICE constexpr int knn_tensor_core_shared_floats(int c) {
  return (kKnnTensorCoreRows + kKnnTensorCoreKeys) * row_fragment_stride(c) + kKnnTensorCoreKeys;
}

// Bound on |approximate - true| squared distance of centred rows q, r as a multiple of
// |q|^2 + max |r|^2, for three-pass products: each operand's two TF32 parts miss it by 2^-22 of it and the
// dropped product of the small parts is 2^-22 of |q_c r_c| (about 3.1 2^-22 |q| |r| in all, |q| |r| <=
// (|q|^2 + |r|^2) / 2), the tensor cores' float32 accumulation of 3 C products (taken as truncating: 2^-22
// each), twice for -2 q.r; the norms' sums and the final additions (2^-23 each); the centred values' own
// rounding (2^-24 of each, 2^-22 of the norms in the distance); with margin. Split parts too small for a
// normal float (flushed to zero) err by at most 2^-126 each: kKnnTensorCoreAbsoluteError per channel.
VRNET_HOST_DEVICE inline float knn_tensor_core_relative_error(int64_t C) {
  return static_cast<float>(8 * C + 64) * 0x1p-23f;
}
constexpr float kKnnTensorCoreAbsoluteError = 0x1p-100f;  // per channel (with the relative term: any |q|, |r|)

// grid: one block per (batch item, tile of kKnnTensorCoreRows query rows), blockIdx.x = b * row_tiles + tile;
// kKnnTensorCoreWarps * 32 threads; knn_tensor_core_shared_floats(C) floats of dynamic shared memory.
// query, ref: centred (B, N, C), (B, M, C); query_norm (B, N), ref_norm (B, M): their squared norms.
// Writes each query row's four lists (ascending approximate distance; reference index M: empty slot)
// to cand_dist, cand_idx (B, N, kKnnRowCandidates), lane t's list at t * kKnnLaneCandidates.
__global__ void knn_tensor_core_kernel(const float* __restrict__ query, const float* __restrict__ ref,
                                       const float* __restrict__ query_norm, const float* __restrict__ ref_norm,
                                       int64_t N, int64_t M, int C, bool exclude_self, int64_t row_tiles,
                                       float* __restrict__ cand_dist, int32_t* __restrict__ cand_idx) {
  VRNET_DYNAMIC_SHARED(float, shared);
  const int stride = row_fragment_stride(C);
  float* q_tile = shared;
  float* r_tile = q_tile + kKnnTensorCoreRows * stride;
  float* r_norm = r_tile + kKnnTensorCoreKeys * stride;

  const auto [b, row0, warp, lane, g, t, warp_row] = RowTileThread(blockIdx.x, row_tiles, kKnnTensorCoreRows);
  const int steps = (C + 7) / 8;

  load_tile(query + b * N * C, row0, N, C, kKnnTensorCoreRows, stride, q_tile);

  // rows g (slot 0) and g + 8 (slot 1) of the warp's 16
  int64_t row[2];
  float q_norm[2];
  RegisterTopK<float, kKnnLaneCandidates> top[2];
  VRNET_UNROLL
  for (int s = 0; s < 2; ++s) {
    row[s] = row0 + warp_row + g + 8 * s;
    q_norm[s] = row[s] < N ? query_norm[b * N + row[s]] : 0.0f;
    top[s].reset(static_cast<int32_t>(M));
  }
  const float largest = std::numeric_limits<float>::max();

  for (int64_t j0 = 0; j0 < M; j0 += kKnnTensorCoreKeys) {
    __syncthreads();  // every warp is done with the previous tile (and the query rows are loaded)
    load_tile(ref + b * M * C, j0, M, C, kKnnTensorCoreKeys, stride, r_tile);
    for (int i = threadIdx.x; i < kKnnTensorCoreKeys; i += blockDim.x)
      r_norm[i] = j0 + i < M ? ref_norm[b * M + j0 + i] : 0.0f;
    __syncthreads();

    float dot[kKnnTensorCoreKeys / 8][4];
    warp_products_abt<kKnnTensorCorePasses>(dot, q_tile, stride, warp_row, r_tile, stride, steps, lane);
    VRNET_UNROLL
    for (int n = 0; n < kKnnTensorCoreKeys / 8; ++n)
      VRNET_UNROLL for (int i = 0; i < 4; ++i) {
        const int s = i >> 1, col = n * 8 + 2 * t + (i & 1);
        const int64_t j = j0 + col;
        if (j >= M || (exclude_self && j == row[s])) continue;
        float d = (q_norm[s] + r_norm[col]) - 2.0f * dot[n][i];
        d = d <= largest ? fmaxf(d, 0.0f) : std::numeric_limits<float>::infinity();  // NaN, overflow: +inf
        if (d <= top[s].worst()) top[s].push(d, static_cast<int32_t>(j));
      }
  }

  VRNET_UNROLL
  for (int s = 0; s < 2; ++s) {
    if (row[s] >= N) continue;
    const int64_t at = (b * N + row[s]) * kKnnRowCandidates + t * kKnnLaneCandidates;
    VRNET_UNROLL
    for (int i = 0; i < kKnnLaneCandidates; ++i) {
      cand_dist[at + i] = top[s].dist[i];
      cand_idx[at + i] = top[s].idx[i];
    }
  }
}

// The k-th smallest approximate distance among a row's four ascending lists (+inf: fewer than k entries).
__device__ inline float knn_kth_of_lists(const float* d_row, const int32_t* i_row, int64_t M, int64_t k) {
  int head[4] = {0, 0, 0, 0};
  float kth = std::numeric_limits<float>::infinity();
  for (int64_t taken = 0; taken < k; ++taken) {
    int best = -1;
    float best_d = std::numeric_limits<float>::infinity();
    VRNET_UNROLL
    for (int list = 0; list < 4; ++list) {
      const int at = list * kKnnLaneCandidates + head[list];
      if (head[list] < kKnnLaneCandidates && i_row[at] < M && (best < 0 || d_row[at] < best_d)) {
        best = list;
        best_d = d_row[at];
      }
    }
    if (best < 0) return std::numeric_limits<float>::infinity();
    kth = best_d;
    VRNET_UNROLL
    for (int list = 0; list < 4; ++list) head[list] += list == best;
  }
  return kth;
}

// One thread per query row: its candidates ranked by exact distance (ties by lower index), the k best
// written, and the row flagged for the exhaustive scan unless the bound above proves them the k nearest.
// With A the k-th smallest approximate distance, error the approximation's bound and rho the exact
// distances' own rounding, a candidate whose approximate distance d has (d - error)(1 - rho) > (A + error)(1 + rho)
// lies beyond k others whatever the rounding: it is not computed. query, ref: the inputs as given (not
// centred); query_norm, ref_norm_max (B): the centred squared norms and each cloud's largest.
template <int KMAX>
__global__ void knn_tensor_core_rerank_kernel(const float* __restrict__ query, const float* __restrict__ ref,
                                              const float* __restrict__ cand_dist,
                                              const int32_t* __restrict__ cand_idx,
                                              const float* __restrict__ query_norm,
                                              const float* __restrict__ ref_norm_max, int64_t N, int64_t M,
                                              int64_t C, int64_t k, float* __restrict__ dist_out,
                                              int64_t* __restrict__ idx_out, int32_t* __restrict__ exhaustive) {
  const int64_t b = blockIdx.y;
  const int64_t n = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (n >= N) return;
  const int64_t row = b * N + n;
  const float* q = query + row * C;
  const float* d_row = cand_dist + row * kKnnRowCandidates;
  const int32_t* i_row = cand_idx + row * kKnnRowCandidates;
  const float largest = std::numeric_limits<float>::max();
  const float error = knn_tensor_core_relative_error(C) * (query_norm[row] + ref_norm_max[b]) +
                      static_cast<float>(C) * kKnnTensorCoreAbsoluteError;
  const float rounding = static_cast<float>(C + 16) * 0x1p-23f;  // of a float32 exact distance, relative
  const float beyond = (knn_kth_of_lists(d_row, i_row, M, k) + error) * (1.0f + rounding);  // +inf: compute all

  RegisterTopK<float, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  // A full list (no empty slot) may have dropped rows: their approximate distances are at least its last.
  float dropped_from = std::numeric_limits<float>::infinity();
  bool bounded = true;  // false: a full list ends in an overflowed distance, which bounds nothing
  for (int list = 0; list < 4; ++list) {
    const int last = (list + 1) * kKnnLaneCandidates - 1;
    if (i_row[last] < M) {
      bounded = bounded && d_row[last] <= largest;
      dropped_from = fminf(dropped_from, d_row[last]);
    }
    for (int i = list * kKnnLaneCandidates; i <= last; ++i) {
      const int64_t m = i_row[i];
      if (m >= M || (d_row[i] - error) * (1.0f - rounding) > beyond) continue;
      top.push(knn_exact_sq_dist(q, ref + (b * M + m) * C, C), static_cast<int32_t>(m));
    }
  }
  knn_store(top, k, dist_out + row * k, idx_out + row * k);
  float kth = 0.0f;
  int32_t kth_idx = 0;
  VRNET_UNROLL
  for (int j = 0; j < KMAX; ++j)
    if (j == k - 1) {
      kth = top.dist[j];
      kth_idx = top.idx[j];
    }
  // A dropped row's exact (float32) distance is at least (dropped_from - error) less its own rounding.
  const bool proven = bounded && kth_idx < M && kth <= largest && error <= largest &&
                      (dropped_from - error) * (1.0f - rounding) > kth;
  exhaustive[row] = !proven;
}

// grad_query[b, n, c] = sum_j 2 g[b, n, j] (q[b, n, c] - r[b, idx, c]).
template <typename scalar_t>
__global__ void knn_grad_query_kernel(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ query,
                                      const scalar_t* __restrict__ ref, const int64_t* __restrict__ idx, int64_t B,
                                      int64_t N, int64_t M, int64_t C, int64_t k, scalar_t* __restrict__ grad_query) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * N * C) return;
  const int64_t c = t % C, bn = t / C, b = bn / N;
  const scalar_t q = query[t];
  scalar_t acc = 0;
  for (int64_t j = 0; j < k; ++j) {
    const int64_t m = idx[bn * k + j];
    acc += 2 * grad[bn * k + j] * (q - ref[(b * M + m) * C + c]);
  }
  grad_query[t] = acc;
}

// grad_ref[b, m, c] = -sum over edges (n, j) into m of 2 g[b, n, j] (q[b, n, c] - r[b, m, c]).
template <typename scalar_t>
__global__ void knn_grad_ref_kernel(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ query,
                                    const scalar_t* __restrict__ ref, const int64_t* __restrict__ order,
                                    const int64_t* __restrict__ row_ptr, int64_t B, int64_t N, int64_t M, int64_t C,
                                    int64_t k, scalar_t* __restrict__ grad_ref) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * M * C) return;
  const int64_t c = t % C, bm = t / C, b = bm / M, m = bm % M;
  const scalar_t r = ref[t];
  const int64_t* edges = order + b * N * k;
  scalar_t acc = 0;
  for (int64_t e = row_ptr[b * (M + 1) + m]; e < row_ptr[b * (M + 1) + m + 1]; ++e) {
    const int64_t pos = edges[e], n = pos / k;
    acc -= 2 * grad[b * N * k + pos] * (query[(b * N + n) * C + c] - r);
  }
  grad_ref[t] = acc;
}

}  // namespace vrnet
