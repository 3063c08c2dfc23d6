// soft_match: the op's contract and argument checks.
//
// soft_match(query (B, N, c), key (B, M, c), values (B, M, D), scale) returns
//   out    (B, N, D)  softmax_j(scale q_i . k_j) v_j
//   lse    (B, N)     log sum_j exp(scale q_i . k_j)       (the softmax's normaliser)
//   argmax (B, N)     int64, the first j with the largest score (the row's peak)
// without ever holding the N x M score matrix.
#pragma once

#include <cmath>

#include "common/common.h"

namespace vrnet {

inline void check_soft_match_inputs(const at::Tensor& query, const at::Tensor& key, const at::Tensor& values,
                                    double scale) {
  check_float(query, "query");
  check_float(key, "key");
  check_float(values, "values");
  check_dim(query, 3, "query", "(B, N, c)");
  check_dim(key, 3, "key", "(B, M, c)");
  check_dim(values, 3, "values", "(B, M, D)");
  check_same_device(query, "query", key, "key");
  check_same_device(query, "query", values, "values");
  TORCH_CHECK_TYPE(key.scalar_type() == query.scalar_type() && values.scalar_type() == query.scalar_type(),
                   "query, key and values must share a dtype, got ", query.scalar_type(), ", ", key.scalar_type(),
                   ", ", values.scalar_type());
  TORCH_CHECK_VALUE(key.size(0) == query.size(0) && values.size(0) == query.size(0),
                    "query, key and values must have the same batch size, got ", query.size(0), ", ", key.size(0),
                    ", ", values.size(0));
  TORCH_CHECK_VALUE(key.size(2) == query.size(2), "key must have query's feature size c = ", query.size(2), ", got ",
                    key.sizes());
  TORCH_CHECK_VALUE(query.size(2) >= 1, "query must have at least one feature channel, got ", query.sizes());
  TORCH_CHECK_VALUE(key.size(1) >= 1, "key must hold at least one point (a softmax over nothing), got ",
                    key.sizes());
  TORCH_CHECK_VALUE(values.size(1) == key.size(1), "values must have one row per key point (M = ", key.size(1),
                    "), got ", values.sizes());
  TORCH_CHECK_VALUE(std::isfinite(scale), "scale must be finite, got ", scale);
}

// soft_match_backward(grad_out, grad_lse, query, key, values, out, lse, scale): the forward's inputs
// and outputs with the gradients of out (B, N, D) and lse (B, N).
inline void check_soft_match_backward_inputs(const at::Tensor& grad_out, const at::Tensor& grad_lse,
                                             const at::Tensor& query, const at::Tensor& key,
                                             const at::Tensor& values, const at::Tensor& out, const at::Tensor& lse,
                                             double scale) {
  check_soft_match_inputs(query, key, values, scale);
  const int64_t B = query.size(0), N = query.size(1), D = values.size(2);
  check_like(grad_out, "grad_out", {B, N, D}, query, "query");
  check_like(out, "out", {B, N, D}, query, "query");
  check_like(grad_lse, "grad_lse", {B, N}, query, "query");
  check_like(lse, "lse", {B, N}, query, "query");
}

}  // namespace vrnet
