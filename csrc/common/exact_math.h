// a + b, a - b, a * b and a / b rounded once each, for math shared by the CPU and CUDA kernels: on
// the GPU through the _rn intrinsics (nvcc would otherwise contract a * b + c into an FMA, and the
// results would differ from the CPU's in the last bit), on the host plain operators (the package and
// the CUDA emulator are built with -ffp-contract=off). Free of torch includes.
#pragma once

#include "common/host_device.h"

namespace vrnet {

// name(a, b) for float or double: `a op b` on the host, the intrinsic of the type on the GPU.
#ifdef __CUDA_ARCH__
#define VRNET_EXACT(name, op, float_rn, double_rn)                                      \
  template <typename T>                                                                 \
  VRNET_HOST_DEVICE inline T name(T a, T b) {                                           \
    if constexpr (sizeof(T) == sizeof(float)) return float_rn(a, b);                    \
    else return double_rn(a, b);                                                        \
  }
#else
#define VRNET_EXACT(name, op, float_rn, double_rn) \
  template <typename T>                            \
  VRNET_HOST_DEVICE inline T name(T a, T b) {      \
    return a op b;                                 \
  }
#endif

VRNET_EXACT(add_rn, +, __fadd_rn, __dadd_rn)
VRNET_EXACT(sub_rn, -, __fsub_rn, __dsub_rn)
VRNET_EXACT(mul_rn, *, __fmul_rn, __dmul_rn)
VRNET_EXACT(div_rn, /, __fdiv_rn, __ddiv_rn)
#undef VRNET_EXACT

}  // namespace vrnet
