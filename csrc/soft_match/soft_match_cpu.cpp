// Streamed soft matching: out_i = sum_j softmax_j(scale q_i . k_j) v_j by the online-softmax
// recurrence over tiles of kTile key points, so memory is O((N + M) (c + D)) plus one
// kRowBlock x kTile score tile per thread, never the N x M matrix.
//
// Forward, per block of query rows: for each key tile, S = scale Q K^T; the running row maximum m
// and normaliser l are updated (l <- l e^(m_old - m_new) + sum_j e^(s_j - m_new)) and the
// accumulated sum_j e^(s_j - m) v_j is rescaled the same way before adding the tile's share.
//
// Backward (P = e^(S - lse), D_i = dO_i . O_i):
//   dS_ij = P_ij (dO_i . v_j - D_i + dlse_i),  dQ = scale dS K,  dK = scale dS^T Q,  dV = P^T dO.
// dQ is accumulated per query block; dK and dV per key block, in a second pass that recomputes P
// (no atomics, a fixed summation order).
//
// The whole call is one parallel region (parallel_tasks); the tile products are single-threaded
// GEMMs inside a task. Each task runs with denormals flushed to zero (FTZ / DAZ, restored after):
// a sharp row's far weights times its values fall below float32's normal range, where x86 GEMMs
// run several times slower; a flushed term is below 1.2e-38 (float64: 2.2e-308).
#include <ATen/ops/empty.h>
#include <ATen/ops/mm.h>
#include <ATen/ops/mul.h>
#include <ATen/ops/sub.h>
#include <ATen/ops/sum.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <type_traits>
#include <vector>

#include "common/cpu_dispatch.h"
#include "common/denormals.h"
#include "soft_match/soft_match.h"

namespace vrnet {
namespace {

constexpr int64_t kRowBlock = 128;  // rows one task owns (query rows forward, key rows in backward pass 2)
constexpr int64_t kTile = 512;      // rows of the other side streamed per step

// A (rows, width) contiguous view on the first rows * width elements of a flat buffer.
at::Tensor tile_view(const at::Tensor& buffer, int64_t rows, int64_t width) {
  return buffer.narrow(0, 0, rows * width).view({rows, width});
}

// The smallest exponent handed to torch's vectorised exp: from it up the exponential is a normal
// number (e^-87 = 1.6e-38 in float32, e^-708 = 3.3e-308 in float64); below it torch's kernel leaves
// its vector path for one 10-50x slower (subnormal or zero results), which a sharp matching hits on
// almost every score. A finite exponent under the floor is raised to it: that weight, at most
// 1.7e-38 (float32) of the row's largest (which is 1), stands for one at least as small. Exponents
// of -inf (overflowed scores) stay: they weigh exactly 0.
template <typename scalar_t>
constexpr scalar_t kExpFloor = std::is_same_v<scalar_t, float> ? scalar_t(-87) : scalar_t(-708);

template <typename scalar_t>
scalar_t floor_exponent(scalar_t x) {
  return x >= kExpFloor<scalar_t> || x == -std::numeric_limits<scalar_t>::infinity() ? x : kExpFloor<scalar_t>;
}

// The forward's row operations on one tile row, portable and (where the CPU has AVX-512, chosen at
// run time) kLanes values per instruction with the same results: each value scaled by one multiply,
// the first position of the largest value (NaN never wins; -inf or NaN only: position 0), one
// subtraction per value (the difference raised to kExpFloor, as floor_exponent), and a sum in 16
// interleaved partial sums (value j into sum j % 16) added pairwise at the end, an order both paths
// share.
constexpr int64_t kSumLanes = 16;

template <typename scalar_t>
scalar_t pairwise_total(const scalar_t* partial) {
  scalar_t level[kSumLanes];
  std::copy(partial, partial + kSumLanes, level);
  for (int64_t width = kSumLanes / 2; width >= 1; width /= 2)
    for (int64_t l = 0; l < width; ++l) level[l] = level[2 * l] + level[2 * l + 1];
  return level[0];
}

template <typename scalar_t>
std::pair<scalar_t, int64_t> scale_and_max_portable(scalar_t* row, int64_t width, scalar_t scale) {
  scalar_t best = -std::numeric_limits<scalar_t>::infinity();
  int64_t at = 0;
  for (int64_t j = 0; j < width; ++j) {
    row[j] *= scale;
    if (row[j] > best) best = row[j], at = j;
  }
  return {best, at};
}

template <typename scalar_t>
scalar_t interleaved_sum_portable(const scalar_t* row, int64_t width) {
  scalar_t partial[kSumLanes] = {};
  for (int64_t j = 0; j < width; ++j) partial[j % kSumLanes] += row[j];
  return pairwise_total(partial);
}

#ifdef VRNET_X86_DISPATCH
template <typename scalar_t>
__attribute__((target("avx512f"))) std::pair<scalar_t, int64_t> scale_and_max_avx512(scalar_t* row, int64_t width,
                                                                                     scalar_t scale) {
  using V = Avx512<scalar_t>;
  const typename V::Vec factor = V::set1(scale);
  typename V::Vec best = V::set1(-std::numeric_limits<scalar_t>::infinity());
  for (int64_t j0 = 0; j0 < width; j0 += V::kLanes) {
    const typename V::Mask valid = lanes_below<scalar_t>(width - j0);
    const typename V::Vec scaled = V::mul(V::load(valid, row + j0), factor);
    V::store(valid, row + j0, scaled);
    best = V::blend(valid & V::less(best, scaled), best, scaled);
  }
  alignas(64) scalar_t lanes[V::kLanes];
  V::store(lanes, best);
  scalar_t top = lanes[0];
  for (int l = 1; l < V::kLanes; ++l)
    if (lanes[l] > top) top = lanes[l];
  if (top == -std::numeric_limits<scalar_t>::infinity()) return {top, 0};
  for (int64_t j = 0;; ++j)
    if (row[j] == top) return {top, j};
}

template <typename scalar_t>
__attribute__((target("avx512f"))) void subtract_avx512(scalar_t* row, int64_t width, scalar_t shift) {
  using V = Avx512<scalar_t>;
  const typename V::Vec by = V::set1(shift), floor = V::set1(kExpFloor<scalar_t>);
  const typename V::Vec minus_inf = V::set1(-std::numeric_limits<scalar_t>::infinity());
  for (int64_t j0 = 0; j0 < width; j0 += V::kLanes) {
    const typename V::Mask valid = lanes_below<scalar_t>(width - j0);
    const typename V::Vec x = V::sub(V::load(valid, row + j0), by);
    const typename V::Mask raise = static_cast<typename V::Mask>(~(V::less_equal(floor, x) | V::equal(x, minus_inf)));
    V::store(valid, row + j0, V::blend(raise, x, floor));
  }
}

template <typename scalar_t>
__attribute__((target("avx512f"))) scalar_t interleaved_sum_avx512(const scalar_t* row, int64_t width) {
  using V = Avx512<scalar_t>;
  constexpr int kParts = kSumLanes / V::kLanes;
  typename V::Vec partial[kParts];
  for (int p = 0; p < kParts; ++p) partial[p] = V::set1(0);
  for (int64_t j0 = 0; j0 < width; j0 += kSumLanes)
    for (int p = 0; p < kParts; ++p) {
      const int64_t first = j0 + p * V::kLanes;
      if (first >= width) break;
      const typename V::Mask valid = lanes_below<scalar_t>(width - first);
      partial[p] = V::blend(valid, partial[p], V::add(partial[p], V::load(valid, row + first)));
    }
  alignas(64) scalar_t lanes[kSumLanes];
  for (int p = 0; p < kParts; ++p) V::store(lanes + p * V::kLanes, partial[p]);
  return pairwise_total(lanes);
}
#endif

template <typename scalar_t>
std::pair<scalar_t, int64_t> scale_and_max(scalar_t* row, int64_t width, scalar_t scale) {
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) return scale_and_max_avx512(row, width, scale);
#endif
  return scale_and_max_portable(row, width, scale);
}

template <typename scalar_t>
void subtract(scalar_t* row, int64_t width, scalar_t shift) {
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) return subtract_avx512(row, width, shift);
#endif
  for (int64_t j = 0; j < width; ++j) row[j] = floor_exponent(row[j] - shift);
}

template <typename scalar_t>
scalar_t interleaved_sum(const scalar_t* row, int64_t width) {
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) return interleaved_sum_avx512(row, width);
#endif
  return interleaved_sum_portable(row, width);
}

template <typename scalar_t>
void soft_match_forward(const at::Tensor& query, const at::Tensor& key, const at::Tensor& values, scalar_t scale,
                        at::Tensor& out, at::Tensor& lse, at::Tensor& argmax) {
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1), D = values.size(2);
  const int64_t blocks = (N + kRowBlock - 1) / kRowBlock;
  parallel_tasks(B * blocks, [&](int64_t task) {
    const ScopedFlushDenormals flush;
    const int64_t b = task / blocks, q0 = (task % blocks) * kRowBlock, rows = std::min(N, q0 + kRowBlock) - q0;
    const at::Tensor q_rows = query.select(0, b).narrow(0, q0, rows);
    at::Tensor acc = out.select(0, b).narrow(0, q0, rows);  // contiguous (rows, D)
    acc.zero_();
    const at::Tensor buffer = at::empty({rows * std::min(M, kTile)}, query.options());
    std::vector<scalar_t> row_max(rows, -std::numeric_limits<scalar_t>::infinity()), row_sum(rows, 0);
    std::vector<scalar_t> rescale(rows);
    int64_t* arg = argmax.mutable_data_ptr<int64_t>() + b * N + q0;
    scalar_t* acc_p = acc.mutable_data_ptr<scalar_t>();
    for (int64_t k0 = 0; k0 < M; k0 += kTile) {
      const int64_t width = std::min(M, k0 + kTile) - k0;
      at::Tensor scores = tile_view(buffer, rows, width);
      at::mm_out(scores, q_rows, key.select(0, b).narrow(0, k0, width).t());
      scalar_t* s = scores.mutable_data_ptr<scalar_t>();
      for (int64_t i = 0; i < rows; ++i) {
        scalar_t* row = s + i * width;
        const auto [tile_max, tile_arg] = scale_and_max(row, width, scale);
        if (k0 == 0 || tile_max > row_max[i]) arg[i] = k0 + tile_arg;  // the first maximum wins ties
        const scalar_t new_max = std::max(row_max[i], tile_max);
        // scores of -inf (overflowed) weigh 0; while every score so far is -inf nothing has accumulated
        const bool none_yet = row_max[i] == -std::numeric_limits<scalar_t>::infinity();
        rescale[i] = k0 == 0 || none_yet ? scalar_t(0) : std::exp(row_max[i] - new_max);
        row_max[i] = new_max;
        const scalar_t shift = new_max == -std::numeric_limits<scalar_t>::infinity() ? scalar_t(0) : new_max;
        subtract(row, width, shift);
      }
      scores.exp_();
      for (int64_t i = 0; i < rows; ++i) {
        row_sum[i] = row_sum[i] * rescale[i] + interleaved_sum(s + i * width, width);
        for (int64_t d = 0; d < D; ++d) acc_p[i * D + d] *= rescale[i];
      }
      acc.addmm_(scores, values.select(0, b).narrow(0, k0, width));
    }
    scalar_t* lse_p = lse.mutable_data_ptr<scalar_t>() + b * N + q0;
    for (int64_t i = 0; i < rows; ++i) {
      for (int64_t d = 0; d < D; ++d) acc_p[i * D + d] /= row_sum[i];
      lse_p[i] = row_max[i] + std::log(row_sum[i]);
    }
  });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_cpu(const at::Tensor& query_in, const at::Tensor& key_in,
                                                              const at::Tensor& values_in, double scale) {
  check_soft_match_inputs(query_in, key_in, values_in, scale);
  // detach(): the tasks slice these tensors on OpenMP worker threads, where autograd's thread-local
  // state is not that of this (below-autograd) call; tensors without autograd history are safe there.
  const at::Tensor query = query_in.contiguous().detach(), key = key_in.contiguous().detach();
  const at::Tensor values = values_in.contiguous().detach();
  check_finite(query, "query");
  check_finite(key, "key");
  check_finite(values, "values");
  const int64_t B = query.size(0), N = query.size(1), D = values.size(2);
  at::Tensor out = at::empty({B, N, D}, query.options());
  at::Tensor lse = at::empty({B, N}, query.options());
  at::Tensor argmax = at::empty({B, N}, query.options().dtype(at::kLong));
  AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "soft_match_cpu", [&] {
    soft_match_forward<scalar_t>(query, key, values, static_cast<scalar_t>(scale), out, lse, argmax);
  });
  TORCH_CHECK_VALUE(at::isfinite(lse).all().item<bool>(),
                    "soft_match scores overflow: scale * query . key is not finite (scale ", scale, ")");
  return {out, lse, argmax};
}

// The backward's tile for a block of `rows` rows of one side against `width` rows of the other:
// probs = exp(scale own other^T - lse), grads = probs * (own_grad other_grad^T + shift), i.e. P and
// dS of those pairs. lse and shift belong to the query side: indexed by row (own = queries, pass 1)
// or by column (own = keys, pass 2). The results are views on the two flat buffers.
template <typename scalar_t>
std::pair<at::Tensor, at::Tensor> score_tile(const at::Tensor& own, const at::Tensor& own_grad, const at::Tensor& other,
                                             const at::Tensor& other_grad, const at::Tensor& prob_buffer,
                                             const at::Tensor& grad_buffer, const scalar_t* lse, const scalar_t* shift,
                                             scalar_t scale, bool query_by_column) {
  const int64_t rows = own.size(0), width = other.size(0);
  at::Tensor probs = tile_view(prob_buffer, rows, width), grads = tile_view(grad_buffer, rows, width);
  at::mm_out(probs, own, other.t());
  at::mm_out(grads, own_grad, other_grad.t());
  scalar_t* p = probs.mutable_data_ptr<scalar_t>();
  for (int64_t i = 0; i < rows; ++i)
    for (int64_t j = 0; j < width; ++j)
      p[i * width + j] = floor_exponent(p[i * width + j] * scale - lse[query_by_column ? j : i]);
  probs.exp_();
  scalar_t* g = grads.mutable_data_ptr<scalar_t>();
  for (int64_t i = 0; i < rows; ++i)
    for (int64_t j = 0; j < width; ++j)
      g[i * width + j] = p[i * width + j] * (g[i * width + j] + shift[query_by_column ? j : i]);
  return {probs, grads};
}

template <typename scalar_t>
void soft_match_backward_kernel(const at::Tensor& grad_out, const at::Tensor& query, const at::Tensor& key,
                                const at::Tensor& values, const at::Tensor& lse, const at::Tensor& shift,
                                scalar_t scale, at::Tensor& grad_query, at::Tensor& grad_key,
                                at::Tensor& grad_values) {
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1);
  const scalar_t* lse_all = lse.const_data_ptr<scalar_t>();
  const scalar_t* shift_all = shift.const_data_ptr<scalar_t>();
  // Pass 1: dQ, one task per (cloud, block of query rows), streaming the keys.
  const int64_t query_blocks = (N + kRowBlock - 1) / kRowBlock;
  parallel_tasks(B * query_blocks, [&](int64_t task) {
    const ScopedFlushDenormals flush;
    const int64_t b = task / query_blocks, q0 = (task % query_blocks) * kRowBlock;
    const int64_t rows = std::min(N, q0 + kRowBlock) - q0;
    const at::Tensor q_rows = query.select(0, b).narrow(0, q0, rows);
    const at::Tensor g_rows = grad_out.select(0, b).narrow(0, q0, rows);
    at::Tensor dq = grad_query.select(0, b).narrow(0, q0, rows);
    const at::Tensor prob_buffer = at::empty({rows * std::min(M, kTile)}, query.options());
    const at::Tensor grad_buffer = at::empty({rows * std::min(M, kTile)}, query.options());
    for (int64_t k0 = 0; k0 < M; k0 += kTile) {
      const int64_t width = std::min(M, k0 + kTile) - k0;
      const at::Tensor k_rows = key.select(0, b).narrow(0, k0, width);
      const at::Tensor v_rows = values.select(0, b).narrow(0, k0, width);
      const auto [probs, grads] = score_tile<scalar_t>(q_rows, g_rows, k_rows, v_rows, prob_buffer, grad_buffer,
                                                       lse_all + b * N + q0, shift_all + b * N + q0, scale, false);
      dq.addmm_(grads, k_rows, 1, scale);
    }
  });
  // Pass 2: dK and dV, one task per (cloud, block of key rows), streaming the queries.
  const int64_t key_blocks = (M + kRowBlock - 1) / kRowBlock;
  parallel_tasks(B * key_blocks, [&](int64_t task) {
    const ScopedFlushDenormals flush;
    const int64_t b = task / key_blocks, k0 = (task % key_blocks) * kRowBlock;
    const int64_t rows = std::min(M, k0 + kRowBlock) - k0;
    const at::Tensor k_rows = key.select(0, b).narrow(0, k0, rows);
    const at::Tensor v_rows = values.select(0, b).narrow(0, k0, rows);
    at::Tensor dk = grad_key.select(0, b).narrow(0, k0, rows);
    at::Tensor dv = grad_values.select(0, b).narrow(0, k0, rows);
    const at::Tensor prob_buffer = at::empty({rows * std::min(N, kTile)}, query.options());
    const at::Tensor grad_buffer = at::empty({rows * std::min(N, kTile)}, query.options());
    for (int64_t q0 = 0; q0 < N; q0 += kTile) {
      const int64_t width = std::min(N, q0 + kTile) - q0;
      const at::Tensor q_rows = query.select(0, b).narrow(0, q0, width);
      const at::Tensor g_rows = grad_out.select(0, b).narrow(0, q0, width);
      const auto [probs, grads] = score_tile<scalar_t>(k_rows, v_rows, q_rows, g_rows, prob_buffer, grad_buffer,
                                                       lse_all + b * N + q0, shift_all + b * N + q0, scale, true);
      dk.addmm_(grads, q_rows, 1, scale);
      dv.addmm_(probs, g_rows);
    }
  });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_backward_cpu(
    const at::Tensor& grad_out_in, const at::Tensor& grad_lse_in, const at::Tensor& query_in,
    const at::Tensor& key_in, const at::Tensor& values_in, const at::Tensor& out_in, const at::Tensor& lse_in,
    double scale) {
  check_soft_match_backward_inputs(grad_out_in, grad_lse_in, query_in, key_in, values_in, out_in, lse_in, scale);
  // detached for the worker threads, as in the forward
  const at::Tensor query = query_in.contiguous().detach(), key = key_in.contiguous().detach();
  const at::Tensor values = values_in.contiguous().detach();
  const at::Tensor grad_out = grad_out_in.contiguous().detach(), lse = lse_in.contiguous().detach();
  // shift_i = dlse_i - dO_i . O_i
  const at::Tensor shift = at::sub(grad_lse_in, at::mul(grad_out, out_in).sum(2)).contiguous().detach();
  at::Tensor grad_query = at::zeros_like(query), grad_key = at::zeros_like(key);
  at::Tensor grad_values = at::zeros_like(values);
  if (query.size(1) > 0) {
    AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "soft_match_backward_cpu", [&] {
      soft_match_backward_kernel<scalar_t>(grad_out, query, key, values, lse, shift, static_cast<scalar_t>(scale),
                                           grad_query, grad_key, grad_values);
    });
  }
  return {grad_query, grad_key, grad_values};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("soft_match", &soft_match_cpu);
  m.impl("soft_match_backward", &soft_match_backward_cpu);
}

}  // namespace vrnet
