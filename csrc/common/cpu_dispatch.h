// Run-time choice of x86 vector code: the portable C++ is always built; functions compiled for
// AVX-512 (GCC/Clang target attributes) run only where the CPU has it. VRNET_CPU_DISPATCH=generic
// (read when the library loads) keeps the portable code, so tests can compare the two paths.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <string>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define VRNET_X86_DISPATCH 1
#endif

namespace vrnet {

inline bool cpu_dispatch_generic() {
  const char* value = std::getenv("VRNET_CPU_DISPATCH");
  return value != nullptr && std::string(value) == "generic";
}

#ifdef VRNET_X86_DISPATCH
inline const bool kHasAvx512 = __builtin_cpu_supports("avx512f") && !cpu_dispatch_generic();
inline const bool kHasVpopcnt = kHasAvx512 && __builtin_cpu_supports("avx512vpopcntdq");
inline const bool kHasPopcnt = __builtin_cpu_supports("popcnt") && !cpu_dispatch_generic();

#define VRNET_AVX512 __attribute__((target("avx512f"), always_inline)) static inline

// The AVX-512 operations the vector kernels need, for 8 doubles or 16 floats per register.
template <typename T>
struct Avx512;

template <>
struct Avx512<double> {
  using Vec = __m512d;
  using Mask = __mmask8;
  static constexpr int kLanes = 8;
  VRNET_AVX512 Vec set1(double x) { return _mm512_set1_pd(x); }
  VRNET_AVX512 Vec load(const double* x) { return _mm512_loadu_pd(x); }
  VRNET_AVX512 Vec load(Mask lanes, const double* x) { return _mm512_maskz_loadu_pd(lanes, x); }
  VRNET_AVX512 void store(double* x, Vec a) { _mm512_storeu_pd(x, a); }
  VRNET_AVX512 void store(Mask lanes, double* x, Vec a) { _mm512_mask_storeu_pd(x, lanes, a); }
  VRNET_AVX512 Vec add(Vec a, Vec b) { return _mm512_add_pd(a, b); }
  VRNET_AVX512 Vec sub(Vec a, Vec b) { return _mm512_sub_pd(a, b); }
  VRNET_AVX512 Vec mul(Vec a, Vec b) { return _mm512_mul_pd(a, b); }
  VRNET_AVX512 Vec blend(Mask take_b, Vec a, Vec b) { return _mm512_mask_blend_pd(take_b, a, b); }
  VRNET_AVX512 Mask less(Vec a, Vec b) { return _mm512_cmp_pd_mask(a, b, _CMP_LT_OQ); }
  VRNET_AVX512 Mask less_equal(Vec a, Vec b) { return _mm512_cmp_pd_mask(a, b, _CMP_LE_OQ); }
  VRNET_AVX512 Mask equal(Vec a, Vec b) { return _mm512_cmp_pd_mask(a, b, _CMP_EQ_OQ); }
  VRNET_AVX512 Mask finite(Vec a) { return _mm512_cmp_pd_mask(_mm512_sub_pd(a, a), _mm512_setzero_pd(), _CMP_EQ_OQ); }
};

template <>
struct Avx512<float> {
  using Vec = __m512;
  using Mask = __mmask16;
  static constexpr int kLanes = 16;
  VRNET_AVX512 Vec set1(float x) { return _mm512_set1_ps(x); }
  VRNET_AVX512 Vec load(const float* x) { return _mm512_loadu_ps(x); }
  VRNET_AVX512 Vec load(Mask lanes, const float* x) { return _mm512_maskz_loadu_ps(lanes, x); }
  VRNET_AVX512 void store(float* x, Vec a) { _mm512_storeu_ps(x, a); }
  VRNET_AVX512 void store(Mask lanes, float* x, Vec a) { _mm512_mask_storeu_ps(x, lanes, a); }
  VRNET_AVX512 Vec add(Vec a, Vec b) { return _mm512_add_ps(a, b); }
  VRNET_AVX512 Vec sub(Vec a, Vec b) { return _mm512_sub_ps(a, b); }
  VRNET_AVX512 Vec mul(Vec a, Vec b) { return _mm512_mul_ps(a, b); }
  VRNET_AVX512 Vec blend(Mask take_b, Vec a, Vec b) { return _mm512_mask_blend_ps(take_b, a, b); }
  VRNET_AVX512 Mask less(Vec a, Vec b) { return _mm512_cmp_ps_mask(a, b, _CMP_LT_OQ); }
  VRNET_AVX512 Mask less_equal(Vec a, Vec b) { return _mm512_cmp_ps_mask(a, b, _CMP_LE_OQ); }
  VRNET_AVX512 Mask equal(Vec a, Vec b) { return _mm512_cmp_ps_mask(a, b, _CMP_EQ_OQ); }
  VRNET_AVX512 Mask finite(Vec a) { return _mm512_cmp_ps_mask(_mm512_sub_ps(a, a), _mm512_setzero_ps(), _CMP_EQ_OQ); }
};

// The first `count` lanes of a register (all of them when count >= kLanes).
template <typename T>
VRNET_AVX512 typename Avx512<T>::Mask lanes_below(int64_t count) {
  using Mask = typename Avx512<T>::Mask;
  return count >= Avx512<T>::kLanes ? static_cast<Mask>(~Mask{0}) : static_cast<Mask>((uint64_t{1} << count) - 1);
}
#endif

}  // namespace vrnet
