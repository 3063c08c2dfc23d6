// Markers for code compiled both by the host compiler and by nvcc (device side).
#pragma once

#ifdef __CUDACC__
#define VRNET_HOST_DEVICE __host__ __device__
#else
#define VRNET_HOST_DEVICE
#endif

// Full unrolling where a loop must index its arrays with compile-time constants (GPU registers).
#ifdef __CUDA_ARCH__
#define VRNET_UNROLL _Pragma("unroll")
#else
#define VRNET_UNROLL
#endif
