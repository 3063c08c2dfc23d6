// k-nearest-neighbour search shared pieces: a bounded sorted top-k buffer.
#pragma once

#include <algorithm>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

namespace vrnet {

// Sorted (ascending by distance, ties by lower index) buffer of the k best candidates,
// stored in caller-owned arrays of length k. Entries start at (+inf, sentinel).
template <typename scalar_t>
struct TopK {
  scalar_t* dist;
  int64_t* idx;
  int64_t k;

  void reset(int64_t sentinel) {
    for (int64_t i = 0; i < k; ++i) {
      dist[i] = std::numeric_limits<scalar_t>::infinity();
      idx[i] = sentinel;
    }
  }
  static bool less(scalar_t da, int64_t ia, scalar_t db, int64_t ib) {
    return da < db || (da == db && ia < ib);
  }
  scalar_t worst() const { return dist[k - 1]; }
  // Inserts (d, j) if it beats the current k-th entry.
  void push(scalar_t d, int64_t j) {
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
