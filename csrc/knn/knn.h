// k-nearest-neighbour search shared pieces: argument checks and the CPU candidate reservoir (the
// top-k buffers are in knn/topk.h).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

#include "common/common.h"
#include "knn/topk.h"

namespace vrnet {

// Largest k the CUDA kernels keep in per-thread register buffers (larger k: chunked sort).
constexpr int64_t kCudaRegisterK = 64;

inline void check_knn_inputs(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self) {
  check_float(query, "query");
  check_float(ref, "ref");
  check_dim(query, 3, "query", "(B, N, C)");
  check_dim(ref, 3, "ref", "(B, M, C)");
  check_same_device(query, "query", ref, "ref");
  TORCH_CHECK_TYPE(query.scalar_type() == ref.scalar_type(), "query and ref must share a dtype");
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  TORCH_CHECK_VALUE(ref.size(0) == B && ref.size(2) == C, "ref must have shape (B, M, C) = (", B, ", M, ", C,
                    "), got ", ref.sizes());
  const int64_t available = exclude_self ? M - 1 : M;
  TORCH_CHECK_VALUE(k >= 1 && k <= available, "k must be in [1, ", available, "], got ", k);
  TORCH_CHECK_VALUE(!exclude_self || N == M, "exclude_self=True needs query and ref to be the same cloud");
  TORCH_CHECK_VALUE(query.is_cpu() || M < (int64_t(1) << 31), "ref must have fewer than 2^31 points on ",
                    query.device(), ", got ", M);
  TORCH_CHECK_VALUE(query.is_cpu() || B <= 65535, "query must have at most 65535 clouds per call on ", query.device(),
                    ", got ", B);
}

// knn_backward(grad_dist2, query, ref, idx): the forward's inputs and outputs, consistent.
inline void check_knn_backward_inputs(const at::Tensor& grad, const at::Tensor& query, const at::Tensor& ref,
                                      const at::Tensor& idx) {
  check_float(query, "query");
  check_dim(query, 3, "query", "(B, N, C)");
  check_dim(ref, 3, "ref", "(B, M, C)");
  check_like(ref, "ref", {query.size(0), ref.size(1), query.size(2)}, query, "query");
  check_index(idx, "idx");
  check_dim(idx, 3, "idx", "(B, N, k)");
  check_same_device(query, "query", idx, "idx");
  TORCH_CHECK_VALUE(idx.size(0) == query.size(0) && idx.size(1) == query.size(1), "idx must have shape (B, N, k) = (",
                    query.size(0), ", ", query.size(1), ", k), got ", idx.sizes());
  check_like(grad, "grad_dist2", idx.sizes(), query, "query");
  check_index_range(idx, ref.size(1), "idx");
}

// sum_c (q_c - r_c)^2 in 8 interleaved partial sums (channel c into sum c % 8) added pairwise at
// the end: a fixed order, and 8 independent chains instead of one C-long chain of dependent adds.
template <typename scalar_t>
scalar_t squared_distance(const scalar_t* q, const scalar_t* r, int64_t C) {
  scalar_t partial[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  int64_t c = 0;
  for (; c + 8 <= C; c += 8)
    for (int l = 0; l < 8; ++l) {
      const scalar_t diff = q[c + l] - r[c + l];
      partial[l] += diff * diff;
    }
  for (int l = 0; c < C; ++c, ++l) {
    const scalar_t diff = q[c] - r[c];
    partial[l] += diff * diff;
  }
  return ((partial[0] + partial[1]) + (partial[2] + partial[3])) + ((partial[4] + partial[5]) + (partial[6] + partial[7]));
}

// The k-th smallest of `count` (at most kMaxBoundValues, >= k) values that are numbers or +inf.
constexpr int64_t kMaxBoundValues = 16;

template <typename scalar_t>
scalar_t kth_smallest(const scalar_t* values, int64_t count, int64_t k) {
  scalar_t copy[kMaxBoundValues];
  std::copy(values, values + count, copy);
  std::nth_element(copy, copy + (k - 1), copy + count);
  return copy[k - 1];
}

// Candidate buffer for the GEMM-tiled CPU search. Candidates arrive with *approximate* squared
// distances (|q|^2 + |r|^2 - 2 q.r on centred coordinates, wrong by up to `slack`); the buffer keeps
// every candidate that could still be among the k nearest: those at or below the k-th smallest
// approximate distance plus 2 * slack. When it fills, nth_element finds that k-th distance and
// drops the rest. `finish` recomputes the survivors' distances exactly (sum of squared coordinate
// differences) and writes the k best by (exact distance, index): the result is the exact kNN as
// long as the approximation error stays within `slack`. Non-finite approximate distances (squared
// norms that overflow) count as +inf, so a row always holds at least k candidates.
template <typename scalar_t>
struct Reservoir {
  std::vector<std::pair<scalar_t, int64_t>> items;
  int64_t k = 0;
  size_t capacity = 0;
  scalar_t slack = 0;
  scalar_t threshold = std::numeric_limits<scalar_t>::infinity();  // k-th approximate distance + 2 slack

  void reset(int64_t k_, scalar_t slack_) {
    k = k_;
    slack = slack_;
    capacity = static_cast<size_t>(2 * k_ + 64);
    items.clear();
    items.reserve(capacity);
    threshold = std::numeric_limits<scalar_t>::infinity();
  }
  // Lowers the threshold to the k-th smallest of `count` (a few) distances of distinct candidates
  // (+ 2 slack): the k-th smallest of all candidates lies at or under it.
  void bound(const scalar_t* distances, int64_t count) {
    if (count < k) return;
    const scalar_t limit = kth_smallest(distances, count, k) + 2 * slack;
    if (limit < threshold) threshold = limit;
  }
  void add(scalar_t d, int64_t j) {
    items.emplace_back(d, j);
    if (items.size() >= capacity) shrink();
  }
  void shrink() {
    if (items.size() <= static_cast<size_t>(k)) return;
    std::nth_element(items.begin(), items.begin() + (k - 1), items.end());
    threshold = std::min(threshold, items[k - 1].first + 2 * slack);
    if (!std::isfinite(threshold)) {  // overflowing norms: keep k (valid indices, no longer the nearest)
      items.resize(k);
      return;
    }
    auto keep_end = std::partition(items.begin() + k, items.end(),
                                   [this](const std::pair<scalar_t, int64_t>& item) { return item.first <= threshold; });
    items.erase(keep_end, items.end());
    // Many candidates within the slack of the k-th (ties, a large slack): grow instead of thrashing.
    if (items.size() * 2 > capacity) capacity = items.size() * 2;
  }
  // Writes the k best by exact distance (ties by lower index) for the query row `q` of C values;
  // `ref` holds the reference rows (C values each) that the candidates index.
  // Every buffered candidate over the threshold is dropped first (the threshold never lies under
  // the k-th approximate distance + 2 slack, so the k nearest stay).
  void finish(const scalar_t* q, const scalar_t* ref, int64_t C, scalar_t* dist, int64_t* idx) {
    if (std::isfinite(threshold)) {
      items.erase(std::remove_if(items.begin(), items.end(),
                                 [this](const std::pair<scalar_t, int64_t>& item) { return !(item.first <= threshold); }),
                  items.end());
    } else {
      shrink();
    }
    for (auto& item : items) item.first = squared_distance(q, ref + item.second * C, C);
    std::partial_sort(items.begin(), items.begin() + k, items.end());
    for (int64_t i = 0; i < k; ++i) {
      dist[i] = items[i].first;
      idx[i] = items[i].second;
    }
  }
};

}  // namespace vrnet
