// The per-pair tests of spatial consistency, shared by the CPU and CUDA kernels (free of torch
// includes), each rounded the same way on both (common/exact_math.h): the CPU's vector code performs
// the same operations in the same order. Coordinates come as six columns of K values each, px, py,
// pz, qx, qy, qz (cols[a * K + k]).
#pragma once

#include <cmath>
#include <cstdint>

#include "common/exact_math.h"

namespace vrnet {

// |a - b| of two points (3 doubles each).
VRNET_HOST_DEVICE inline double point_distance(const double* a, const double* b) {
  const double dx = sub_rn(a[0], b[0]), dy = sub_rn(a[1], b[1]), dz = sub_rn(a[2], b[2]);
  return sqrt(add_rn(add_rn(mul_rn(dx, dx), mul_rn(dy, dy)), mul_rn(dz, dz)));
}

// Whether correspondences i and j are compatible, | |p_i - p_j| - |q_i - q_j| | < tolerance, without
// square roots: with a, b the squared distances and s = a + b - tolerance^2 (t2), s < 0 or s^2 < 4 a b.
template <typename T>
VRNET_HOST_DEVICE inline bool compatible(const T* cols, int64_t K, int64_t i, int64_t j, T t2) {
  T a = 0, b = 0;
  for (int axis = 0; axis < 3; ++axis) {
    const T dp = sub_rn(cols[axis * K + j], cols[axis * K + i]);
    const T dq = sub_rn(cols[(3 + axis) * K + j], cols[(3 + axis) * K + i]);
    a = axis == 0 ? mul_rn(dp, dp) : add_rn(a, mul_rn(dp, dp));
    b = axis == 0 ? mul_rn(dq, dq) : add_rn(b, mul_rn(dq, dq));
  }
  const T s = sub_rn(add_rn(a, b), t2);
  return (s < 0) | (mul_rn(s, s) < mul_rn(mul_rn(T(4), a), b));
}

// Whether the fit y = R x + t (R row-major) maps correspondence k within sqrt(threshold2) of its target.
VRNET_HOST_DEVICE inline bool maps_within(const double* R, const double* t, const double* cols, int64_t K, int64_t k,
                                          double threshold2) {
  const double px = cols[k], py = cols[K + k], pz = cols[2 * K + k];
  double r2 = 0;
  for (int a = 0; a < 3; ++a) {
    const double turned = add_rn(add_rn(mul_rn(R[3 * a], px), mul_rn(R[3 * a + 1], py)), mul_rn(R[3 * a + 2], pz));
    const double moved = add_rn(turned, t[a]);
    const double d = sub_rn(moved, cols[(3 + a) * K + k]);
    r2 = a == 0 ? mul_rn(d, d) : add_rn(r2, mul_rn(d, d));
  }
  return r2 < threshold2;
}

}  // namespace vrnet
