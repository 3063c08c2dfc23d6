// k-nearest-neighbour search shared pieces: a bounded sorted top-k buffer.
#pragma once

#include <cstdint>
#include <limits>

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

}  // namespace vrnet
