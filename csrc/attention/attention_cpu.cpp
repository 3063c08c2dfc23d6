// attention on the CPU (definition in attention.h).
//
// First, per (batch, head): k and v are checked for non-finite values and, where the matrix products
// run on AMX, packed once with bfloat16 pairs interleaved along the reduced dimension (the B-operand
// layout of the tile products): k^T as [D / 2][M] words, v as [padded M / 2][D] words (an odd M is
// padded with a zero key). Then tasks of (batch, head, kRows queries), claimed by the threads of one
// parallel region: each computes its rows' float32 scores against all M keys, the softmax weights
// (rounded to bfloat16) and their product with v. With AMX (at::native::cpublas::could_pack) both
// products are torch's brgemm micro-kernels, bfloat16 in, float32 out; elsewhere (and with
// VRNET_CPU_DISPATCH=generic) plain loops. The softmax and the final scaling run on AVX-512 with
// AVX512-BF16 where the CPU has them, bit-equal to their portable loops.
//
// Memory: the packed heads (4 M D bytes per head) and each worker's kRows x M float32 scores and
// bfloat16 weights live in buffers their thread keeps between calls, up to kKeptBytes each (fresh
// pages on every call cost more than the arithmetic at the sizes this op is for); larger ones are
// freed at the end of the call. The Python wrapper keeps M bounded (longer key sets go to torch's
// streamed attention).
#include <ATen/native/CPUBlas.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <atomic>
#include <vector>

#include "attention/attention.h"
#include "common/cpu_dispatch.h"

namespace vrnet {
namespace {

constexpr int64_t kRows = 64;  // queries per task
constexpr int kSumLanes = 16;  // the softmax sum runs in 16 interleaved partial sums

// One (B, H, L, D) bfloat16 tensor with unit channel stride, as raw bits.
struct Heads {
  const uint16_t* data;
  int64_t stride_b, stride_h, stride_l;
  const uint16_t* row(int64_t b, int64_t h, int64_t l) const {
    return data + b * stride_b + h * stride_h + l * stride_l;
  }
};

Heads heads_of(const at::Tensor& t) {
  return {reinterpret_cast<const uint16_t*>(t.const_data_ptr<at::BFloat16>()), t.stride(0), t.stride(1), t.stride(2)};
}

// AMX tile products for this head size (the packed v has D columns: the micro-kernel takes 16 to 64).
bool products_on_amx(int64_t D) {
  static const bool available = !cpu_dispatch_generic() && at::native::cpublas::could_pack(at::kBFloat16);
  return available && D % 16 == 0 && D <= 64;
}

// Whether rows [l0, l1) of head (b, h) hold only finite values (an OR over integer words, which the
// compiler vectorises: a bfloat16 is non-finite when its exponent bits are all set).
bool rows_finite(const Heads& t, int64_t b, int64_t h, int64_t l0, int64_t l1, int64_t D) {
  uint32_t flags = 0;
  for (int64_t l = l0; l < l1; ++l) {
    const uint16_t* row = t.row(b, h, l);
    for (int64_t c = 0; c < D; ++c) flags |= (uint32_t(row[c]) & 0x7f80u) + 0x80u;  // bit 15: exponent all ones
  }
  return (flags & 0x8000u) == 0;
}

float sum_lanes(float* partial) {  // fixed pairwise order, shared by both softmax paths
  for (int width = kSumLanes / 2; width >= 1; width /= 2)
    for (int l = 0; l < width; ++l) partial[l] += partial[l + width];
  return partial[0];
}

// One row of scores s_j: p_j = bf16(2^x_j) with x_j = c s_j - c max_k s_k and c = scale log2(e) (so
// p_j = exp(scale (s_j - max_k s_k))) for j < M, and p_M = 0 when padded_M > M; returns the float32
// sum of the unrounded exponentials, summed in kSumLanes interleaved partial sums.
float softmax_row_portable(const float* scores, int64_t M, int64_t padded_M, float c, uint16_t* weights) {
  float top = -std::numeric_limits<float>::infinity();
  for (int64_t j = 0; j < M; ++j) top = std::max(top, scores[j]);
  top *= c;
  float partial[kSumLanes] = {};
  for (int64_t j = 0; j < M; ++j) {
    const float e = exp2_nonpositive(std::fma(scores[j], c, -top));
    weights[j] = float_to_bf16_bits(e);
    partial[j % kSumLanes] += e;
  }
  if (padded_M > M) weights[M] = 0;
  return sum_lanes(partial);
}

// out[c] = bf16(products[c] * inverse) for c < D.
void scale_row_portable(const float* products, float inverse, int64_t D, uint16_t* out) {
  for (int64_t c = 0; c < D; ++c) out[c] = float_to_bf16_bits(products[c] * inverse);
}

#ifdef VRNET_X86_DISPATCH
const bool kHasAvx512Bf16 = kHasAvx512 && __builtin_cpu_supports("avx512bf16");

#define VRNET_AVX512_BF16 __attribute__((target("avx512f,avx512bw,avx512vl,avx512bf16")))

VRNET_AVX512_BF16 static inline __m512 exp2_nonpositive_avx512(__m512 x) {
  x = _mm512_max_ps(x, _mm512_set1_ps(kExp2Lowest));
  const __m512 n = _mm512_roundscale_ps(x, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  const __m512 r = _mm512_sub_ps(x, n);
  __m512 p = _mm512_set1_ps(kExp2Poly[0]);
  for (int i = 1; i < kExp2Terms; ++i) p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(kExp2Poly[i]));
  return _mm512_scalef_ps(p, n);
}

// softmax_row_portable on 16 lanes (the conversion rounds to nearest even and flushes subnormals,
// as float_to_bf16_bits does).
VRNET_AVX512_BF16 float softmax_row_avx512(const float* scores, int64_t M, int64_t padded_M, float c,
                                           uint16_t* weights) {
  const __m512 c_v = _mm512_set1_ps(c);
  const int64_t full = M - M % kSumLanes;
  const __mmask16 tail = static_cast<__mmask16>((1u << (M - full)) - 1);
  __m512 top_v = _mm512_set1_ps(-std::numeric_limits<float>::infinity());
  for (int64_t j0 = 0; j0 < full; j0 += kSumLanes) top_v = _mm512_max_ps(top_v, _mm512_loadu_ps(scores + j0));
  if (tail != 0) top_v = _mm512_mask_max_ps(top_v, tail, top_v, _mm512_maskz_loadu_ps(tail, scores + full));
  const __m512 top = _mm512_set1_ps(_mm512_reduce_max_ps(top_v) * c);
  __m512 sums = _mm512_setzero_ps();
  for (int64_t j0 = 0; j0 < full; j0 += kSumLanes) {
    const __m512 e = exp2_nonpositive_avx512(_mm512_fmsub_ps(_mm512_loadu_ps(scores + j0), c_v, top));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(weights + j0), (__m256i)_mm512_cvtneps_pbh(e));
    sums = _mm512_add_ps(sums, e);
  }
  if (tail != 0) {
    const __m512 e = exp2_nonpositive_avx512(_mm512_fmsub_ps(_mm512_maskz_loadu_ps(tail, scores + full), c_v, top));
    _mm256_mask_storeu_epi16(weights + full, tail, (__m256i)_mm512_cvtneps_pbh(e));
    sums = _mm512_mask_add_ps(sums, tail, sums, e);
  }
  if (padded_M > M) weights[M] = 0;
  float partial[kSumLanes];
  _mm512_storeu_ps(partial, sums);
  return sum_lanes(partial);
}

VRNET_AVX512_BF16 void scale_row_avx512(const float* products, float inverse, int64_t D, uint16_t* out) {
  const __m512 inverse_v = _mm512_set1_ps(inverse);
  for (int64_t c0 = 0; c0 < D; c0 += 16) {
    const __mmask16 lanes = D - c0 >= 16 ? __mmask16(0xffff) : static_cast<__mmask16>((1u << (D - c0)) - 1);
    const __m512 scaled = _mm512_mul_ps(_mm512_maskz_loadu_ps(lanes, products + c0), inverse_v);
    _mm256_mask_storeu_epi16(out + c0, lanes, (__m256i)_mm512_cvtneps_pbh(scaled));
  }
}
#endif

float softmax_row(const float* scores, int64_t M, int64_t padded_M, float c, uint16_t* weights) {
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512Bf16) return softmax_row_avx512(scores, M, padded_M, c, weights);
#endif
  return softmax_row_portable(scores, M, padded_M, c, weights);
}

void scale_row(const float* products, float inverse, int64_t D, uint16_t* out) {
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512Bf16) return scale_row_avx512(products, inverse, D, out);
#endif
  scale_row_portable(products, inverse, D, out);
}

// Packs head (b, h): keys[(c / 2) M + j] = (k[j][c], k[j][c + 1]) and
// values[(j / 2) D + c] = (v[j][c], v[j + 1][c]) as 32-bit words (v[M] = 0 when M is odd).
void pack_head(const Heads& k, const Heads& v, int64_t b, int64_t h, int64_t M, int64_t padded_M, int64_t D,
               uint32_t* keys, uint32_t* values) {
  for (int64_t j = 0; j < M; ++j) {
    const uint16_t* key = k.row(b, h, j);
    for (int64_t c = 0; c < D; c += 2) keys[(c / 2) * M + j] = uint32_t(key[c]) | (uint32_t(key[c + 1]) << 16);
  }
  for (int64_t j = 0; j < padded_M; j += 2) {
    const uint16_t* first = v.row(b, h, j);
    const uint16_t* second = j + 1 < M ? v.row(b, h, j + 1) : nullptr;
    for (int64_t c = 0; c < D; ++c)
      values[(j / 2) * D + c] = uint32_t(first[c]) | (second ? uint32_t(second[c]) << 16 : 0u);
  }
}

// Runs fn(task) for every task in [0, tasks), claimed one at a time by the threads of ONE parallel
// region (as parallel_tasks), then finish() once on every thread that took part.
template <typename F, typename G>
void claim_tasks(int64_t tasks, const F& fn, const G& finish) {
  std::atomic<int64_t> next{0};
  at::parallel_for(0, std::min<int64_t>(tasks, at::get_num_threads()), 1, [&](int64_t, int64_t) {
    for (int64_t task = next++; task < tasks; task = next++) fn(task);
    finish();
  });
}

// Room for `count` elements: in `kept`, a buffer the thread keeps between calls, when it needs at
// most kKeptBytes, else in `temporary`, freed by its owner at the end of the call.
constexpr size_t kKeptBytes = size_t(4) << 20;

template <typename T>
T* scratch(std::vector<T>& kept, std::vector<T>& temporary, int64_t count) {
  std::vector<T>& buffer = static_cast<size_t>(count) * sizeof(T) <= kKeptBytes ? kept : temporary;
  if (buffer.size() < static_cast<size_t>(count)) buffer.resize(count);
  return buffer.data();
}

at::Tensor attention_cpu(const at::Tensor& q_in, const at::Tensor& k_in, const at::Tensor& v_in, double scale_in) {
  check_attention_inputs(q_in, k_in, v_in, scale_in);
  const auto unit_channels = [](const at::Tensor& t) { return t.stride(3) == 1 ? t : t.contiguous(); };
  const at::Tensor q = unit_channels(q_in), k = unit_channels(k_in), v = unit_channels(v_in);
  const int64_t B = q.size(0), H = q.size(1), N = q.size(2), M = k.size(2), D = q.size(3);
  const int64_t padded_M = M + (M % 2);
  const float c = static_cast<float>(scale_in * 1.4426950408889634);  // scale log2(e): exponentials in base 2
  // (B, N, H, D) in memory: a point's heads form one row for the output projection.
  at::Tensor out = at::empty({B, N, H, D}, q.options()).permute({0, 2, 1, 3});
  if (B * H * N == 0) return out;
  const Heads q_heads = heads_of(q), k_heads = heads_of(k), v_heads = heads_of(v);
  const bool amx = products_on_amx(D);
  const int64_t key_words = (D / 2) * M, value_words = (padded_M / 2) * D;
  thread_local std::vector<uint32_t> packed_kept;
  std::vector<uint32_t> packed_temporary;
  uint32_t* packed = amx ? scratch(packed_kept, packed_temporary, B * H * (key_words + value_words)) : nullptr;
  std::atomic<bool> k_bad{false}, v_bad{false}, q_bad{false};
  parallel_tasks(B * H, [&](int64_t task) {
    const int64_t b = task / H, h = task % H;
    if (!rows_finite(k_heads, b, h, 0, M, D)) k_bad.store(true, std::memory_order_relaxed);
    if (!rows_finite(v_heads, b, h, 0, M, D)) v_bad.store(true, std::memory_order_relaxed);
    if (amx) {
      uint32_t* keys = packed + task * (key_words + value_words);
      pack_head(k_heads, v_heads, b, h, M, padded_M, D, keys, keys + key_words);
    }
  });
  TORCH_CHECK_VALUE(!k_bad.load(), "k contains NaN or Inf values");
  TORCH_CHECK_VALUE(!v_bad.load(), "v contains NaN or Inf values");
  uint16_t* out_data = reinterpret_cast<uint16_t*>(out.mutable_data_ptr<at::BFloat16>());
  const int64_t row_blocks = (N + kRows - 1) / kRows;
  const auto block = [&](int64_t task) {
    const int64_t b = task / (H * row_blocks), h = (task / row_blocks) % H;
    const int64_t i0 = (task % row_blocks) * kRows, rows = std::min(kRows, N - i0);
    if (!rows_finite(q_heads, b, h, i0, i0 + rows, D)) {
      q_bad.store(true, std::memory_order_relaxed);
      return;
    }
    // Written in full before they are read (no zero fill).
    thread_local std::vector<float> scores_kept, sums_kept, products_kept;
    thread_local std::vector<uint16_t> weights_kept;
    std::vector<float> scores_temporary, sums_temporary, products_temporary;
    std::vector<uint16_t> weights_temporary;
    float* scores = scratch(scores_kept, scores_temporary, rows * M);
    float* sums = scratch(sums_kept, sums_temporary, rows);
    float* products = scratch(products_kept, products_temporary, rows * D);
    uint16_t* weights = scratch(weights_kept, weights_temporary, rows * padded_M);
    const uint16_t* q_rows = q_heads.row(b, h, i0);
    const uint32_t* keys = amx ? packed + (b * H + h) * (key_words + value_words) : nullptr;
    if (amx) {
      at::native::cpublas::brgemm(rows, M, D, q_heads.stride_l, M, M, false,
                                  reinterpret_cast<const at::BFloat16*>(q_rows),
                                  reinterpret_cast<const at::BFloat16*>(keys), scores, true);
    } else {
      for (int64_t r = 0; r < rows; ++r)
        for (int64_t j = 0; j < M; ++j) {
          const uint16_t *query = q_rows + r * q_heads.stride_l, *key = k_heads.row(b, h, j);
          float dot = 0;
          for (int64_t i = 0; i < D; ++i) dot += bf16_bits_to_float(query[i]) * bf16_bits_to_float(key[i]);
          scores[r * M + j] = dot;
        }
    }
    for (int64_t r = 0; r < rows; ++r) sums[r] = softmax_row(scores + r * M, M, padded_M, c, weights + r * padded_M);
    if (amx) {
      at::native::cpublas::brgemm(rows, D, padded_M, padded_M, D, D, false,
                                  reinterpret_cast<const at::BFloat16*>(weights),
                                  reinterpret_cast<const at::BFloat16*>(keys + key_words), products, true);
    } else {
      std::fill(products, products + rows * D, 0.0f);
      for (int64_t r = 0; r < rows; ++r)
        for (int64_t j = 0; j < M; ++j) {
          const float p = bf16_bits_to_float(weights[r * padded_M + j]);
          const uint16_t* value = v_heads.row(b, h, j);
          for (int64_t i = 0; i < D; ++i) products[r * D + i] += p * bf16_bits_to_float(value[i]);
        }
    }
    for (int64_t r = 0; r < rows; ++r)
      scale_row(products + r * D, 1.0f / sums[r], D, out_data + ((b * N + i0 + r) * H + h) * D);
  };
  claim_tasks(B * H * row_blocks, block, [&] {
    if (amx) at::native::cpublas::brgemm_release(true);  // the AMX tile state each worker configured
  });
  TORCH_CHECK_VALUE(!q_bad.load(), "q contains NaN or Inf values");
  return out;
}

// Whether attention_cpu's products for heads of `head_channels` run on AMX tiles: where they do not,
// its plain loops are many times slower than torch's own kernel, so the Python wrapper asks first.
bool attention_on_amx(int64_t head_channels) { return products_on_amx(head_channels); }

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) { m.impl("attention", &attention_cpu); }

TORCH_LIBRARY_FRAGMENT(vrnet_ext, m) { m.def("attention_on_amx(int head_channels) -> bool", &attention_on_amx); }

}  // namespace vrnet
