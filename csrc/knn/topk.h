// Sorted top-k buffers (ascending by distance, ties by lower index) shared by the CPU and CUDA kNN
// kernels. Header-only and free of torch includes so that tests/cpp can compile it alone.
#pragma once

#include <cstdint>
#include <limits>

#include "common/host_device.h"

namespace vrnet {

// The k best candidates in caller-owned arrays of length k (any k); entries start at (+inf, sentinel).
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
    if (d > dist[k - 1]) return;  // the common case, one compare (NaN never gets here either way)
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

// The KMAX best candidates in member arrays, for a compile-time KMAX >= k: the first k entries are
// then the k best. Every array index is a compile-time constant once the loops are unrolled, so on
// the GPU the buffer lives in registers rather than in local memory; insertion is a branch-free
// chain of KMAX predicated moves. Indices are int32 (callers check M < 2^31).
template <typename scalar_t, int KMAX>
struct RegisterTopK {
  scalar_t dist[KMAX];
  int32_t idx[KMAX];

  VRNET_HOST_DEVICE void reset(int32_t sentinel) {
    VRNET_UNROLL
    for (int i = 0; i < KMAX; ++i) {
      dist[i] = std::numeric_limits<scalar_t>::infinity();
      idx[i] = sentinel;
    }
  }
  VRNET_HOST_DEVICE scalar_t worst() const { return dist[KMAX - 1]; }
  // Drops the best entry; the others move up, an empty (+inf, sentinel) entry comes in last.
  VRNET_HOST_DEVICE void pop_front(int32_t sentinel) {
    VRNET_UNROLL
    for (int i = 0; i + 1 < KMAX; ++i) {
      dist[i] = dist[i + 1];
      idx[i] = idx[i + 1];
    }
    dist[KMAX - 1] = std::numeric_limits<scalar_t>::infinity();
    idx[KMAX - 1] = sentinel;
  }
  VRNET_HOST_DEVICE void push(scalar_t d, int32_t j) {
    if (!TopK<scalar_t>::less(d, j, dist[KMAX - 1], idx[KMAX - 1])) return;
    bool placed = false;
    VRNET_UNROLL
    for (int i = KMAX - 1; i > 0; --i) {
      if (!placed) {
        if (TopK<scalar_t>::less(d, j, dist[i - 1], idx[i - 1])) {
          dist[i] = dist[i - 1];
          idx[i] = idx[i - 1];
        } else {
          dist[i] = d;
          idx[i] = j;
          placed = true;
        }
      }
    }
    if (!placed) {
      dist[0] = d;
      idx[0] = j;
    }
  }
};

}  // namespace vrnet
