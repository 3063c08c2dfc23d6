// attention: multi-head scaled dot-product attention on bfloat16 heads, for inference.
//
// attention(q (B, H, N, D), k (B, H, M, D), v (B, H, M, D), scale) returns (B, H, N, D) bfloat16
//   out[b, h, i] = sum_j p_ij v[b, h, j] / sum_j p_ij,  p_ij = exp(s_ij - max_j s_ij),
//   s_ij = scale q[b, h, i] . k[b, h, j]
// with the scores, the exponentials and both sums in float32 and p rounded to bfloat16 before its
// product with v, as torch's fused CPU attention does. The output's memory is (B, N, H, D): the
// heads of one point form one row, ready for the output projection. No backward.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>

#include "common/common.h"

namespace vrnet {

inline void check_attention_inputs(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v, double scale) {
  const std::pair<const at::Tensor*, const char*> named[] = {{&q, "q"}, {&k, "k"}, {&v, "v"}};
  for (const auto& [t, name] : named) {
    TORCH_CHECK_TYPE(t->scalar_type() == at::kBFloat16, name, " must be bfloat16, got ", t->scalar_type());
    check_dim(*t, 4, name, "(B, H, L, D)");
    check_same_device(q, "q", *t, name);
  }
  TORCH_CHECK_VALUE(k.size(0) == q.size(0) && k.size(1) == q.size(1) && k.size(3) == q.size(3),
                    "k must have shape (B, H, M, D) = (", q.size(0), ", ", q.size(1), ", M, ", q.size(3), "), got ",
                    k.sizes());
  TORCH_CHECK_VALUE(v.sizes() == k.sizes(), "v must have k's shape ", k.sizes(), ", got ", v.sizes());
  TORCH_CHECK_VALUE(q.size(3) >= 1, "q must have at least one channel per head, got ", q.sizes());
  TORCH_CHECK_VALUE(k.size(2) >= 1, "k must hold at least one key (a softmax over nothing), got ", k.sizes());
  TORCH_CHECK_VALUE(std::isfinite(scale) && scale > 0, "scale must be a finite number > 0, got ", scale);
}

// bfloat16 <-> float32 on raw bits: a bfloat16 is the upper half of a float32.
inline float bf16_bits_to_float(uint16_t bits) {
  const uint32_t word = uint32_t(bits) << 16;
  float value;
  std::memcpy(&value, &word, sizeof(value));
  return value;
}

// Round to nearest, ties to even, with subnormal inputs flushed to a signed zero (what the
// AVX512-BF16 conversion instruction does; finite inputs).
inline uint16_t float_to_bf16_bits(float value) {
  uint32_t word;
  std::memcpy(&word, &value, sizeof(word));
  if ((word & 0x7f800000u) == 0) return uint16_t((word >> 16) & 0x8000u);
  word += 0x7fffu + ((word >> 16) & 1u);
  return uint16_t(word >> 16);
}

inline bool bf16_bits_finite(uint16_t bits) { return (bits & 0x7f80u) != 0x7f80u; }

// 2^x for x <= 0 in float32: x is clamped at kExp2Lowest (2^x is then still a normal float),
// x = n + r with n = round(x) and |r| <= 1/2, 2^r by a cubic fitted on [-1/2, 1/2] (relative error
// < 8e-5, a fiftieth of the bfloat16 rounding the weights then get), times 2^n (exact). The AVX-512
// version performs the same operations (fused multiply-adds included) on 16 lanes: the same bits.
constexpr float kExp2Lowest = -125.0f;
constexpr int kExp2Terms = 4;
constexpr float kExp2Poly[kExp2Terms] = {0.05508868396282196f, 0.24260404706001282f, 0.6932762265205383f,
                                         0.9999289512634277f};

inline float exp2_nonpositive(float x) {
  x = std::max(x, kExp2Lowest);
  const float n = std::nearbyint(x);
  const float r = x - n;
  float p = kExp2Poly[0];
  for (int i = 1; i < kExp2Terms; ++i) p = std::fma(p, r, kExp2Poly[i]);
  return std::ldexp(p, static_cast<int>(n));
}

}  // namespace vrnet
