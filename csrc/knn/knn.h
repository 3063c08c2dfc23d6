// k-nearest-neighbour search shared pieces: argument checks, a bounded sorted top-k buffer (CPU and
// CUDA), and the CPU candidate reservoir.
#pragma once

#include <algorithm>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

#include "common/common.h"

namespace vrnet {

// Largest k the CUDA kernels keep in their per-thread buffers.
constexpr int64_t kCudaMaxK = 256;

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
  TORCH_CHECK_VALUE(query.is_cpu() || k <= kCudaMaxK, "k must be at most ", kCudaMaxK, " on ", query.device(),
                    ", got ", k);
}

// Sorted (ascending by distance, ties by lower index) buffer of the k best candidates,
// stored in caller-owned arrays of length k. Entries start at (+inf, sentinel).
template <typename scalar_t>
struct TopK {
  scalar_t* dist;
  int64_t* idx;
  int64_t k;

  VRNET_HOST_DEVICE void reset(int64_t sentinel) {
    for (int64_t i = 0; i < k; ++i) {
      dist[i] = std::numeric_limits<scalar_t>::infinity();
      idx[i] = sentinel;
    }
  }
  VRNET_HOST_DEVICE static bool less(scalar_t da, int64_t ia, scalar_t db, int64_t ib) {
    return da < db || (da == db && ia < ib);
  }
  VRNET_HOST_DEVICE scalar_t worst() const { return dist[k - 1]; }
  // Inserts (d, j) if it beats the current k-th entry.
  VRNET_HOST_DEVICE void push(scalar_t d, int64_t j) {
    if (!less(d, j, dist[k - 1], idx[k - 1])) return;
    int64_t pos = k - 1;
    while (pos > 0 && less(d, j, dist[pos - 1], idx[pos - 1])) {
      dist[pos] = dist[pos - 1];
      idx[pos] = idx[pos - 1];
      --pos;
    }
    dist[pos] = d;
    idx[pos] = j;
  }
};

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
