// An emulator of the CUDA execution model for running this project's device code on a CPU.
//
// Included (through common/cuda_device.cuh) instead of the CUDA runtime when VRNET_CUDA_EMULATION
// is defined. Every CUDA thread of a block runs as a fiber on one OS thread; __syncthreads() and the
// warp collectives are rendezvous points between fibers of 32-lane warps. Blocks run one after the
// other in a seeded random order and, in a second pass over a restored copy of the launch's tensors,
// concurrently on several OS threads; results that differ between the passes are reported. The
// sanitizer (tests/cuda_emu/runtime.cpp) sees every load and store of the instrumented translation units
// and checks it against the launch's tensors, the block's shared memory, the thread's own stack and
// the module's static data. The runtime lives in tests/cuda_emu/runtime.cpp (not instrumented).
//
// Only this file and runtime.cpp know how threads run; kernels are written as plain CUDA.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <type_traits>

#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
#define __noinline__ __attribute__((noinline))

struct uint3 {
  unsigned int x, y, z;
};

struct dim3 {
  unsigned int x, y, z;
  constexpr dim3(unsigned int x_ = 1, unsigned int y_ = 1, unsigned int z_ = 1) : x(x_), y(y_), z(z_) {}
};

using cudaStream_t = void*;

namespace vrnet {
namespace emu {

// The executing CUDA thread's built-in variables (valid inside a kernel only).
uint3 thread_index();
uint3 block_index();
dim3 block_dimensions();
dim3 grid_dimensions();

// Shared memory of the executing block: the region of one __shared__ declaration (tag: the address
// of a static object unique to the declaration), or the launch's dynamic shared memory.
void* shared_region(const void* tag, std::size_t bytes, std::size_t align);
void* dynamic_shared_region();

void sync_threads();
void sync_warp(unsigned int mask);

enum class Collective : int { kShflIdx, kShflUp, kShflDown, kShflXor, kBallot, kAny, kAll, kSyncWarp, kMmaTf32 };
// One lane's part in a warp collective: value (size bytes, <= 8) in, the result out.
void warp_collective(Collective kind, unsigned int mask, const void* value, std::size_t size, int arg, int width,
                     void* result);
unsigned int warp_vote(Collective kind, unsigned int mask, int predicate);
// `mma.sync.aligned.m16n8k8.row.col.f32.tf32.tf32.f32` of a whole warp: d (16 x 8) += a (16 x 8) b (8 x 8),
// each lane holding its fragments in the PTX ISA's layout (common/tensor_core.cuh). Operands keep
// their TF32 bits only (the low 13 mantissa bits are ignored, as the tensor cores ignore them); each
// product is exact and the eight are added to d in k order in float32.
void mma_m16n8k8_tf32(float (&d)[4], const std::uint32_t (&a)[4], const std::uint32_t (&b)[2]);
unsigned int active_mask();

// Atomics on global or shared memory (checked by the sanitizer like any access).
float atomic_add(float* address, float value);
double atomic_add(double* address, double value);
int atomic_add(int* address, int value);
unsigned int atomic_add(unsigned int* address, unsigned int value);
unsigned long long atomic_add(unsigned long long* address, unsigned long long value);
int atomic_max(int* address, int value);
int atomic_min(int* address, int value);
unsigned int atomic_max(unsigned int* address, unsigned int value);
unsigned int atomic_min(unsigned int* address, unsigned int value);
long long atomic_max(long long* address, long long value);
long long atomic_min(long long* address, long long value);
int atomic_cas(int* address, int compare, int value);
unsigned int atomic_cas(unsigned int* address, unsigned int compare, unsigned int value);
unsigned long long atomic_cas(unsigned long long* address, unsigned long long compare, unsigned long long value);
int atomic_exch(int* address, int value);
unsigned int atomic_exch(unsigned int* address, unsigned int value);
float atomic_exch(float* address, float value);

}  // namespace emu
}  // namespace vrnet

#define threadIdx (::vrnet::emu::thread_index())
#define blockIdx (::vrnet::emu::block_index())
#define blockDim (::vrnet::emu::block_dimensions())
#define gridDim (::vrnet::emu::grid_dimensions())
constexpr int warpSize = 32;

// A macro, so that the barrier's call site (its return address) is the kernel's.
#define __syncthreads() ::vrnet::emu::sync_threads()
inline void __syncwarp(unsigned int mask = 0xffffffffu) { ::vrnet::emu::sync_warp(mask); }
inline unsigned int __activemask() { return ::vrnet::emu::active_mask(); }

namespace vrnet {
namespace emu {
template <typename T>
inline T shuffle(Collective kind, unsigned int mask, T value, int arg, int width) {
  static_assert(std::is_trivially_copyable<T>::value && sizeof(T) <= 8, "warp shuffles move values of 1-8 bytes");
  T result;
  warp_collective(kind, mask, &value, sizeof(T), arg, width, &result);
  return result;
}
}  // namespace emu
}  // namespace vrnet

template <typename T>
inline T __shfl_sync(unsigned int mask, T var, int src_lane, int width = warpSize) {
  return ::vrnet::emu::shuffle(::vrnet::emu::Collective::kShflIdx, mask, var, src_lane, width);
}
template <typename T>
inline T __shfl_up_sync(unsigned int mask, T var, unsigned int delta, int width = warpSize) {
  return ::vrnet::emu::shuffle(::vrnet::emu::Collective::kShflUp, mask, var, static_cast<int>(delta), width);
}
template <typename T>
inline T __shfl_down_sync(unsigned int mask, T var, unsigned int delta, int width = warpSize) {
  return ::vrnet::emu::shuffle(::vrnet::emu::Collective::kShflDown, mask, var, static_cast<int>(delta), width);
}
template <typename T>
inline T __shfl_xor_sync(unsigned int mask, T var, int lane_mask, int width = warpSize) {
  return ::vrnet::emu::shuffle(::vrnet::emu::Collective::kShflXor, mask, var, lane_mask, width);
}
inline unsigned int __ballot_sync(unsigned int mask, int predicate) {
  return ::vrnet::emu::warp_vote(::vrnet::emu::Collective::kBallot, mask, predicate);
}
inline int __any_sync(unsigned int mask, int predicate) {
  return static_cast<int>(::vrnet::emu::warp_vote(::vrnet::emu::Collective::kAny, mask, predicate));
}
inline int __all_sync(unsigned int mask, int predicate) {
  return static_cast<int>(::vrnet::emu::warp_vote(::vrnet::emu::Collective::kAll, mask, predicate));
}

inline float atomicAdd(float* a, float v) { return ::vrnet::emu::atomic_add(a, v); }
inline double atomicAdd(double* a, double v) { return ::vrnet::emu::atomic_add(a, v); }
inline int atomicAdd(int* a, int v) { return ::vrnet::emu::atomic_add(a, v); }
inline unsigned int atomicAdd(unsigned int* a, unsigned int v) { return ::vrnet::emu::atomic_add(a, v); }
inline unsigned long long atomicAdd(unsigned long long* a, unsigned long long v) {
  return ::vrnet::emu::atomic_add(a, v);
}
inline int atomicMax(int* a, int v) { return ::vrnet::emu::atomic_max(a, v); }
inline int atomicMin(int* a, int v) { return ::vrnet::emu::atomic_min(a, v); }
inline unsigned int atomicMax(unsigned int* a, unsigned int v) { return ::vrnet::emu::atomic_max(a, v); }
inline unsigned int atomicMin(unsigned int* a, unsigned int v) { return ::vrnet::emu::atomic_min(a, v); }
inline long long atomicMax(long long* a, long long v) { return ::vrnet::emu::atomic_max(a, v); }
inline long long atomicMin(long long* a, long long v) { return ::vrnet::emu::atomic_min(a, v); }
inline int atomicCAS(int* a, int c, int v) { return ::vrnet::emu::atomic_cas(a, c, v); }
inline unsigned int atomicCAS(unsigned int* a, unsigned int c, unsigned int v) {
  return ::vrnet::emu::atomic_cas(a, c, v);
}
inline unsigned long long atomicCAS(unsigned long long* a, unsigned long long c, unsigned long long v) {
  return ::vrnet::emu::atomic_cas(a, c, v);
}
inline int atomicExch(int* a, int v) { return ::vrnet::emu::atomic_exch(a, v); }
inline unsigned int atomicExch(unsigned int* a, unsigned int v) { return ::vrnet::emu::atomic_exch(a, v); }
inline float atomicExch(float* a, float v) { return ::vrnet::emu::atomic_exch(a, v); }

// Round-to-nearest intrinsics: one IEEE operation each (the build uses -ffp-contract=off).
inline float __fadd_rn(float a, float b) { return a + b; }
inline float __fsub_rn(float a, float b) { return a - b; }
inline float __fmul_rn(float a, float b) { return a * b; }
inline float __fdiv_rn(float a, float b) { return a / b; }
inline double __dadd_rn(double a, double b) { return a + b; }
inline double __dsub_rn(double a, double b) { return a - b; }
inline double __dmul_rn(double a, double b) { return a * b; }
inline double __ddiv_rn(double a, double b) { return a / b; }
inline float __fmaf_rn(float a, float b, float c) { return std::fma(a, b, c); }
inline double __fma_rn(double a, double b, double c) { return std::fma(a, b, c); }
// Bit counts, as the CUDA intrinsics.
inline int __popc(unsigned int x) { return __builtin_popcount(x); }
inline int __popcll(unsigned long long x) { return __builtin_popcountll(x); }
inline float __expf(float x) { return std::exp(x); }
inline float __logf(float x) { return std::log(x); }
inline float rsqrtf(float x) { return 1.0f / std::sqrt(x); }
inline double rsqrt(double x) { return 1.0 / std::sqrt(x); }
// Reinterpretation of a double's bits, as the CUDA intrinsics.
inline long long __double_as_longlong(double x) {
  long long bits;
  std::memcpy(&bits, &x, sizeof bits);
  return bits;
}
inline unsigned int __float_as_uint(float x) {
  unsigned int bits;
  std::memcpy(&bits, &x, sizeof bits);
  return bits;
}
inline float __uint_as_float(unsigned int bits) {
  float x;
  std::memcpy(&x, &bits, sizeof x);
  return x;
}
inline double __longlong_as_double(long long bits) {
  double x;
  std::memcpy(&x, &bits, sizeof x);
  return x;
}

#define VRNET_EMU_CAT2(a, b) a##b
#define VRNET_EMU_CAT(a, b) VRNET_EMU_CAT2(a, b)
// `__shared__ type name[count];` of CUDA: one region per block, the same for all its threads.
#define VRNET_EMU_SHARED(type, name, count)                                                          \
  static const char VRNET_EMU_CAT(vrnet_shared_tag_, __LINE__) = 0;                                  \
  type(&name)[count] = *reinterpret_cast<type(*)[count]>(                                            \
      ::vrnet::emu::shared_region(&VRNET_EMU_CAT(vrnet_shared_tag_, __LINE__), sizeof(type) * (count), \
                                  alignof(type)))
// `extern __shared__ type name[];`: the launch's dynamic shared memory.
#define VRNET_EMU_DYNAMIC_SHARED(type, name) type* name = reinterpret_cast<type*>(::vrnet::emu::dynamic_shared_region())
