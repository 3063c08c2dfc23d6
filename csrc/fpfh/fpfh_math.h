// Fast Point Feature Histograms (Rusu et al. 2009) per point, shared by the CPU and CUDA kernels
// (free of torch includes), the definition of vrnet_ext/ops/fpfh.py: spfh_one, three 11-bin
// histograms of the Darboux-frame angles (theta, alpha, phi) to each other point within the radius,
// each scaled to sum 100; fpfh_one, SPFH + the 1/distance^2-weighted neighbours' SPFH scaled to sum
// 100 per block (blocks sum 200).
#pragma once

#include <math.h>
#include <stdint.h>

#include "common/host_device.h"

namespace vrnet {
namespace fpfh_detail {

constexpr int kBins = 11;
constexpr int kFeatures = 3 * kBins;

template <typename T>
VRNET_HOST_DEVICE inline T dot(const T* a, const T* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

template <typename T>
VRNET_HOST_DEVICE inline void cross(const T* a, const T* b, T* out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

template <typename T>
VRNET_HOST_DEVICE inline int bin(T value, T low, T span) {
  const int b = static_cast<int>(floor((value - low) / span * static_cast<T>(kBins)));
  return b < 0 ? 0 : (b >= kBins ? kBins - 1 : b);
}

// Scales each 11-bin block of h to sum 100 (a block with no counts stays 0).
template <typename T>
VRNET_HOST_DEVICE inline void scale_blocks(T* h) {
  for (int part = 0; part < 3; ++part) {
    T sum = 0;
    for (int b = 0; b < kBins; ++b) sum += h[part * kBins + b];
    if (!(sum > 0)) continue;
    for (int b = 0; b < kBins; ++b) h[part * kBins + b] = h[part * kBins + b] * static_cast<T>(100) / sum;
  }
}

// The Darboux-frame angles of source point (ps, ns) and target (pt, nt) at distance length > 0, in
// PCL's and Open3D's convention: the frame sits on the point whose normal is closer to the joining
// line d (near-ties keep the order), v = d x u, w = u x v; a normal along d gives (0, 0, 0).
template <typename T>
VRNET_HOST_DEVICE inline void pair_angles(const T* ps, const T* ns, const T* pt, const T* nt, T length, T* theta,
                                          T* alpha, T* phi) {
  T d[3] = {pt[0] - ps[0], pt[1] - ps[1], pt[2] - ps[2]};
  for (int r = 0; r < 3; ++r) d[r] /= length;
  const bool swap = fabs(dot(ns, d)) < fabs(dot(nt, d)) - static_cast<T>(1e-9);
  const T* u = swap ? nt : ns;
  const T* other = swap ? ns : nt;
  if (swap)
    for (int r = 0; r < 3; ++r) d[r] = -d[r];
  T v[3], w[3];
  cross(d, u, v);
  const T v_length = sqrt(dot(v, v));
  if (!(v_length > 0)) {
    *theta = *alpha = *phi = 0;
    return;
  }
  for (int r = 0; r < 3; ++r) v[r] /= v_length;
  cross(u, v, w);
  *theta = atan2(dot(w, other), dot(u, other));
  *alpha = dot(v, other);
  *phi = dot(u, d);
}

// Whether a neighbour at squared distance d2 counts: within the radius, and not the point itself or
// a duplicate of it (they have no frame).
template <typename T>
VRNET_HOST_DEVICE inline bool counts(T d2, T r2) { return d2 <= r2 && d2 > 0; }

}  // namespace fpfh_detail

// The SPFH h (33,) of point i of p, n (N, 3) over its k neighbours nb (k,) at squared distances d2 (k,).
template <typename T>
VRNET_HOST_DEVICE void spfh_one(const T* p, const T* n, const int64_t* nb, const T* d2, int64_t i, int64_t k, T r2,
                                T* h) {
  using namespace fpfh_detail;
  const T pi = static_cast<T>(M_PI);
  for (int f = 0; f < kFeatures; ++f) h[f] = 0;
  for (int64_t j = 0; j < k; ++j) {
    if (!counts(d2[j], r2)) continue;
    const int64_t q = nb[j];
    T theta, alpha, phi;
    pair_angles(p + 3 * i, n + 3 * i, p + 3 * q, n + 3 * q, static_cast<T>(sqrt(d2[j])), &theta, &alpha, &phi);
    h[bin<T>(theta, -pi, 2 * pi)] += 1;
    h[kBins + bin<T>(alpha, -1, 2)] += 1;
    h[2 * kBins + bin<T>(phi, -1, 2)] += 1;
  }
  scale_blocks(h);
}

// The FPFH out (33,) of point i from every point's SPFH spfh (N, 33) and its neighbours nb, d2 (k,):
// weights 1 / d^2 relative to the nearest other neighbour's (no overflow at any scale).
template <typename T>
VRNET_HOST_DEVICE void fpfh_one(const T* spfh, const int64_t* nb, const T* d2, int64_t i, int64_t k, T r2, T* out) {
  using namespace fpfh_detail;
  T nearest = 0;
  for (int64_t j = 0; j < k; ++j)
    if (counts(d2[j], r2) && (nearest == 0 || d2[j] < nearest)) nearest = d2[j];
  T mixed[kFeatures];
  for (int f = 0; f < kFeatures; ++f) mixed[f] = 0;
  for (int64_t j = 0; j < k; ++j) {
    if (!counts(d2[j], r2)) continue;
    const T w = nearest / d2[j];
    const T* hq = spfh + nb[j] * kFeatures;
    for (int f = 0; f < kFeatures; ++f) mixed[f] += w * hq[f];
  }
  scale_blocks(mixed);
  for (int f = 0; f < kFeatures; ++f) out[f] = spfh[i * kFeatures + f] + mixed[f];
}

}  // namespace vrnet
