// TF32 tensor-core products of one warp (sm_80 and later): `mma.sync.aligned.m16n8k8` with float32
// accumulators, and the loading of its fragments from shared-memory tiles. Under the CPU emulator the
// product is the emulator's collective of the same layout (cuda_emu/cuda_emu.h).
//
// Fragment layout (PTX ISA, "Matrix Fragments for mma.m16n8k8", .tf32), lane = 4 g + t:
//   A (16 x 8, row, k):  a0 (g, t)    a1 (g + 8, t)    a2 (g, t + 4)    a3 (g + 8, t + 4)
//   B (8 x 8,  k, col):  b0 (t, g)    b1 (t + 4, g)
//   D (16 x 8, row, col): d0 (g, 2t)  d1 (g, 2t + 1)   d2 (g + 8, 2t)   d3 (g + 8, 2t + 1)
//
// With three passes a float32 operand x is split into x_hi = tf32(x) and x_lo = tf32(x - x_hi), and
// a b is accumulated as a_lo b_hi + a_hi b_lo + a_hi b_hi: about float32's accuracy (the dropped
// a_lo b_lo is ~2^-22 of a b) on the tensor cores. One pass rounds each operand to TF32 (~2^-11).
#pragma once

#include "common/cuda_device.cuh"

// The tensor cores' TF32 products need sm_80 or later: compiled for an older GPU, mma_tf32 traps, and
// the host code of a kernel that uses it refuses such devices (compute_capability_major()).
#if defined(VRNET_CUDA_EMULATION) || !defined(__CUDA_ARCH__) || __CUDA_ARCH__ >= 800
#define VRNET_TENSOR_CORES 1
#else
#define VRNET_TENSOR_CORES 0
#endif

namespace vrnet {

constexpr int kTensorCoreMajor = 8;  // compute capability of the first GPUs with TF32 tensor cores

// x rounded to TF32 (8 exponent, 10 mantissa bits; to nearest, ties away from zero), as float bits.
__device__ inline std::uint32_t to_tf32(float x) {
#if defined(VRNET_CUDA_EMULATION) || !VRNET_TENSOR_CORES
  std::uint32_t bits = __float_as_uint(x);
  if ((bits & 0x7f800000u) != 0x7f800000u) bits = (bits + 0x1000u) & 0xffffe000u;  // Inf / NaN kept
  return bits;
#else
  std::uint32_t bits;
  asm("cvt.rna.tf32.f32 %0, %1;" : "=r"(bits) : "f"(x));
  return bits;
#endif
}

// d (16 x 8) += a (16 x 8) b (8 x 8) on the tensor cores; all 32 lanes of the warp call it together.
__device__ inline void mma_tf32(float (&d)[4], const std::uint32_t (&a)[4], const std::uint32_t (&b)[2]) {
#ifdef VRNET_CUDA_EMULATION
  ::vrnet::emu::mma_m16n8k8_tf32(d, a, b);
#elif !VRNET_TENSOR_CORES
  __trap();
#else
  asm volatile("mma.sync.aligned.m16n8k8.row.col.f32.tf32.tf32.f32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, {%8, %9}, "
               "{%0, %1, %2, %3};"
               : "+f"(d[0]), "+f"(d[1]), "+f"(d[2]), "+f"(d[3])
               : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]));
#endif
}

// One operand fragment of `kPasses` (1 or 3) passes: its TF32 values and, for three, the remainders.
template <int kSize, int kPasses>
struct Tf32Fragment {
  std::uint32_t hi[kSize];
  std::uint32_t lo[kSize];

  __device__ void set(int i, float x) {
    hi[i] = to_tf32(x);
    if (kPasses == 3) lo[i] = to_tf32(x - __uint_as_float(hi[i]));
  }
};

template <int kPasses>
using FragmentA = Tf32Fragment<4, kPasses>;
template <int kPasses>
using FragmentB = Tf32Fragment<2, kPasses>;

// d += a b in `kPasses` passes (the small products first).
template <int kPasses>
__device__ inline void mma_passes(float (&d)[4], const FragmentA<kPasses>& a, const FragmentB<kPasses>& b) {
  if (kPasses == 3) {
    mma_tf32(d, a.lo, b.hi);
    mma_tf32(d, a.hi, b.lo);
  }
  mma_tf32(d, a.hi, b.hi);
}

// A from a row-major tile: A(row, k) = tile[(row0 + row) * stride + k0 + k].
template <int kPasses>
__device__ inline FragmentA<kPasses> load_a(const float* tile, int stride, int row0, int k0, int lane) {
  const int g = lane >> 2, t = lane & 3;
  FragmentA<kPasses> a;
  a.set(0, tile[(row0 + g) * stride + k0 + t]);
  a.set(1, tile[(row0 + g + 8) * stride + k0 + t]);
  a.set(2, tile[(row0 + g) * stride + k0 + t + 4]);
  a.set(3, tile[(row0 + g + 8) * stride + k0 + t + 4]);
  return a;
}

// B from a tile holding B(k, col) at tile[(k0 + k) * k_step + (col0 + col) * col_step]: k_step = 1 where
// B's columns are the tile's rows (the keys of Q Kᵀ), col_step = 1 where the tile is B row-major.
template <int kPasses>
__device__ inline FragmentB<kPasses> load_b(const float* tile, int k_step, int col_step, int k0, int col0, int lane) {
  const int g = lane >> 2, t = lane & 3;
  FragmentB<kPasses> b;
  b.set(0, tile[(k0 + t) * k_step + (col0 + g) * col_step]);
  b.set(1, tile[(k0 + t + 4) * k_step + (col0 + g) * col_step]);
  return b;
}

// Row stride (floats) of a shared tile of rows `width` values long whose fragments are read as (g, t) ->
// g * stride + t (A, and B where B's columns are the tile's rows): 4 mod 32, so the 32 loads hit 32 banks.
VRNET_HOST_DEVICE constexpr int row_fragment_stride(int width) { return (width + 31) / 32 * 32 + 4; }

// Where a thread of a block over rows of one batch item works: block = b * tiles + tile (blockIdx.x, or
// a part of it), the block's `rows` rows from `first` (16 a warp, the warp's from first + warp_row); lane =
// 4 g + t as in the fragments. Taken apart where used:
//   const auto [b, first, warp, lane, g, t, warp_row] = RowTileThread(blockIdx.x, tiles, rows);
struct RowTileThread {
  int64_t b, first;
  int warp, lane, g, t, warp_row;

  __device__ RowTileThread(int64_t block, int64_t tiles, int rows)
      : b(block / tiles), first(block % tiles * rows), warp(threadIdx.x / 32), lane(threadIdx.x % 32), g(lane >> 2),
        t(lane & 3), warp_row(warp * 16) {}
};

// rows x width values of a (rows_total, width) row-major matrix from row `first` into a tile of
// `stride` floats a row, zeros past its rows and in its columns up to the next multiple of 8 (what the
// products read); all threads of the block take part, a warp per row (coalesced, no division).
__device__ inline void load_tile(const float* __restrict__ source, int64_t first, int64_t rows_total, int width,
                                 int rows, int stride, float* tile) {
  const int warps = blockDim.x / 32, lane = threadIdx.x % 32, read = (width + 7) / 8 * 8;
  for (int row = threadIdx.x / 32; row < rows; row += warps) {
    const int64_t at = first + row;
    for (int col = lane; col < read; col += 32)
      tile[row * stride + col] = at < rows_total && col < width ? source[at * width + col] : 0.0f;
  }
}

// Zeros for an accumulator of n_tiles fragments.
template <int n_tiles>
__device__ inline void zero(float (&acc)[n_tiles][4]) {
  VRNET_UNROLL
  for (int n = 0; n < n_tiles; ++n) {
    VRNET_UNROLL for (int i = 0; i < 4; ++i) acc[n][i] = 0.0f;
  }
}

// acc (16 x 8 n_tiles) = A Bᵀ, A the 16 rows of a_tile from row0 and B's columns the rows of b_tile,
// both 8 * steps values long (zero-padded): a warp's scores Q Kᵀ, or dO Vᵀ.
template <int kPasses, int n_tiles>
__device__ inline void warp_products_abt(float (&acc)[n_tiles][4], const float* a_tile, int a_stride, int row0,
                                         const float* b_tile, int b_stride, int steps, int lane) {
  zero(acc);
  for (int step = 0; step < steps; ++step) {
    const FragmentA<kPasses> a = load_a<kPasses>(a_tile, a_stride, row0, step * 8, lane);
    VRNET_UNROLL
    for (int n = 0; n < n_tiles; ++n)
      mma_passes<kPasses>(acc[n], a, load_b<kPasses>(b_tile, 1, b_stride, step * 8, n * 8, lane));
  }
}

// acc (16 x 8 col_tiles, the first `used` fragments) += A B, A the 16 rows of a_tile (8 * k_steps values
// from column 0), B the tile b_tile row-major (8 * k_steps rows): P V, and the backward's products.
template <int kPasses, int col_tiles>
__device__ inline void warp_products_ab(float (&acc)[col_tiles][4], const float* a_tile, int a_stride,
                                        const float* b_tile, int b_stride, int k_steps, int used, int lane) {
  for (int step = 0; step < k_steps; ++step) {
    const FragmentA<kPasses> a = load_a<kPasses>(a_tile, a_stride, 0, step * 8, lane);
    VRNET_UNROLL
    for (int f = 0; f < col_tiles; ++f)
      if (f < used) mma_passes<kPasses>(acc[f], a, load_b<kPasses>(b_tile, b_stride, 1, step * 8, f * 8, lane));
  }
}


}  // namespace vrnet
