// Flush-to-zero / denormals-are-zero for every OpenMP worker thread (MKL and ATen share them).
// torch.set_flush_denormal only changes the calling thread; softmax tails and their gradients
// in VRNet's N x M matching are often denormal and slow x86 GEMMs down by 10x or more.
#include <torch/library.h>

#include "common/denormals.h"

#ifdef VRNET_HAS_MXCSR
#include <omp.h>
#endif

namespace vrnet {
namespace {

bool set_flush_denormal(bool enabled) {
#ifdef VRNET_HAS_MXCSR
  auto apply = [enabled] {
    _mm_setcsr(enabled ? (_mm_getcsr() | kFlushDenormalFlags) : (_mm_getcsr() & ~kFlushDenormalFlags));
  };
  apply();
#pragma omp parallel
  apply();
  return true;
#else
  (void)enabled;
  return false;
#endif
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(vrnet_ext, m) {
  m.def("set_flush_denormal(bool enabled) -> bool", &set_flush_denormal);
}

}  // namespace vrnet
