// Flush-to-zero / denormals-are-zero on x86 (the MXCSR register; a no-op elsewhere). The mode belongs
// to each thread: MKL, oneDNN and ATen's CPU kernels running on a thread follow that thread's mode.
#pragma once

#if defined(__x86_64__) || defined(_M_X64)
#include <xmmintrin.h>
#define VRNET_HAS_MXCSR 1
#endif

namespace vrnet {

constexpr unsigned int kFlushDenormalFlags = 0x8040;  // FTZ (bit 15) | DAZ (bit 6)

// FTZ + DAZ on the calling thread while the object lives; then the thread's own mode is restored.
class ScopedFlushDenormals {
 public:
#ifdef VRNET_HAS_MXCSR
  ScopedFlushDenormals() : saved_(_mm_getcsr()) { _mm_setcsr(saved_ | kFlushDenormalFlags); }
  ~ScopedFlushDenormals() { _mm_setcsr(saved_); }
#else
  ScopedFlushDenormals() {}  // user-provided: a const instance needs no initialiser
#endif
  ScopedFlushDenormals(const ScopedFlushDenormals&) = delete;
  ScopedFlushDenormals& operator=(const ScopedFlushDenormals&) = delete;

#ifdef VRNET_HAS_MXCSR
 private:
  unsigned int saved_;
#endif
};

}  // namespace vrnet
