// k-nearest-neighbour search shared pieces: argument checks and the CPU candidate reservoir (the
// top-k buffers are in knn/topk.h).
#pragma once

#include <algorithm>
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

// Candidate buffer for scans over many candidates: anything at or below the threshold is appended;
// when the buffer fills, nth_element keeps the k best by (distance, index) and the threshold drops
// to the k-th of them. Amortised O(1) per candidate instead of an insertion sort.
template <typename scalar_t>
struct Reservoir {
  std::vector<std::pair<scalar_t, int64_t>> items;
  int64_t k = 0;
  size_t capacity = 0;
  scalar_t threshold = std::numeric_limits<scalar_t>::infinity();

  void reset(int64_t k_) {
    k = k_;
    capacity = static_cast<size_t>(2 * k_ + 64);
    items.clear();
    items.reserve(capacity);
    threshold = std::numeric_limits<scalar_t>::infinity();
  }
  void add(scalar_t d, int64_t j) {
    items.emplace_back(d, j);
    if (items.size() >= capacity) shrink();
  }
  void shrink() {
    if (items.size() <= static_cast<size_t>(k)) return;
    std::nth_element(items.begin(), items.begin() + (k - 1), items.end());
    items.resize(k);
    threshold = items[k - 1].first;
    for (const auto& item : items) threshold = std::max(threshold, item.first);
  }
  // Writes the k best, ascending by (distance, index).
  void finish(scalar_t* dist, int64_t* idx) {
    shrink();
    std::sort(items.begin(), items.end());
    for (int64_t i = 0; i < k; ++i) {
      dist[i] = items[i].first;
      idx[i] = items[i].second;
    }
  }
};

}  // namespace vrnet
