// Fast Point Feature Histograms (Rusu et al. 2009), the definition of vrnet_ext/ops/fpfh.py:
// pass 1, per point, the SPFH: three 11-bin histograms of the Darboux-frame angles (theta, alpha,
// phi) to each other point within the radius, each scaled to sum 100; pass 2, per point,
// FPFH = SPFH + the 1/distance^2-weighted neighbours' SPFH scaled to sum 100 per block (blocks sum
// 200). Each pass is one parallel region over points; memory O(N * 33).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cmath>
#include <vector>

#include "normals/normals.h"

namespace vrnet {
namespace {

constexpr int kBins = 11;
constexpr int kFeatures = 3 * kBins;

template <typename T>
inline T dot3(const T* a, const T* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

template <typename T>
inline void cross(const T* a, const T* b, T* out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

template <typename T>
inline int bin(T value, T low, T span) {
  const int b = static_cast<int>(std::floor((value - low) / span * static_cast<T>(kBins)));
  return b < 0 ? 0 : (b >= kBins ? kBins - 1 : b);
}

// Scales each 11-bin block of h to sum 100 (a block with no counts stays 0).
template <typename T>
inline void scale_blocks(T* h) {
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
inline void pair_angles(const T* ps, const T* ns, const T* pt, const T* nt, T length, T* theta, T* alpha, T* phi) {
  T d[3] = {pt[0] - ps[0], pt[1] - ps[1], pt[2] - ps[2]};
  for (int r = 0; r < 3; ++r) d[r] /= length;
  const bool swap = std::fabs(dot3(ns, d)) < std::fabs(dot3(nt, d)) - static_cast<T>(1e-9);
  const T* u = swap ? nt : ns;
  const T* other = swap ? ns : nt;
  if (swap)
    for (int r = 0; r < 3; ++r) d[r] = -d[r];
  T v[3], w[3];
  cross(d, u, v);
  const T v_length = std::sqrt(dot3(v, v));
  if (!(v_length > 0)) {
    *theta = *alpha = *phi = 0;
    return;
  }
  for (int r = 0; r < 3; ++r) v[r] /= v_length;
  cross(u, v, w);
  *theta = std::atan2(dot3(w, other), dot3(u, other));
  *alpha = dot3(v, other);
  *phi = dot3(u, d);
}

at::Tensor fpfh_cpu(const at::Tensor& points_in, const at::Tensor& normals_in, const at::Tensor& idx_in,
                    const at::Tensor& dist2_in, double radius) {
  check_neighbourhood(points_in, idx_in);
  check_float(normals_in, "normals");
  check_float(dist2_in, "dist2");
  TORCH_CHECK_VALUE(normals_in.sizes() == points_in.sizes(), "normals must have the shape of points ",
                    points_in.sizes(), ", got ", normals_in.sizes());
  TORCH_CHECK_VALUE(dist2_in.sizes() == idx_in.sizes(), "dist2 must have the shape of idx ", idx_in.sizes(),
                    ", got ", dist2_in.sizes());
  TORCH_CHECK_TYPE(normals_in.scalar_type() == points_in.scalar_type() &&
                       dist2_in.scalar_type() == points_in.scalar_type(),
                   "points, normals and dist2 must share a dtype");
  check_same_device(points_in, "points", normals_in, "normals");
  check_same_device(points_in, "points", dist2_in, "dist2");
  TORCH_CHECK_VALUE(std::isfinite(radius) && radius > 0, "radius must be a finite number > 0, got ", radius);
  const at::Tensor points = points_in.contiguous(), normals = normals_in.contiguous();
  const at::Tensor idx = idx_in.contiguous(), dist2 = dist2_in.contiguous();
  check_finite(points, "points");
  check_finite(normals, "normals");
  const int64_t N = points.size(0), k = idx.size(1);
  at::Tensor out = at::empty({N, kFeatures}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "fpfh_cpu", [&] {
    using T = scalar_t;
    const T* p = points.const_data_ptr<T>();
    const T* n = normals.const_data_ptr<T>();
    const int64_t* nb = idx.const_data_ptr<int64_t>();
    const T* d2 = dist2.const_data_ptr<T>();
    const T r2 = static_cast<T>(radius * radius);
    const T pi = static_cast<T>(M_PI);
    std::vector<T> spfh(static_cast<size_t>(N) * kFeatures, 0);
    parallel_ranges(N, 64, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        T* h = spfh.data() + i * kFeatures;
        for (int64_t j = 0; j < k; ++j) {
          if (!(d2[i * k + j] <= r2 && d2[i * k + j] > 0)) continue;  // itself and duplicates have no frame
          const int64_t q = nb[i * k + j];
          T theta, alpha, phi;
          pair_angles(p + 3 * i, n + 3 * i, p + 3 * q, n + 3 * q, std::sqrt(d2[i * k + j]), &theta, &alpha, &phi);
          h[bin<T>(theta, -pi, 2 * pi)] += 1;
          h[kBins + bin<T>(alpha, -1, 2)] += 1;
          h[2 * kBins + bin<T>(phi, -1, 2)] += 1;
        }
        scale_blocks(h);
      }
    });
    T* o = out.mutable_data_ptr<T>();
    parallel_ranges(N, 64, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        // weights 1 / d^2 relative to the nearest other neighbour's (no overflow at any scale)
        T nearest = 0;
        for (int64_t j = 0; j < k; ++j) {
          const T d = d2[i * k + j];
          if (d <= r2 && d > 0 && (nearest == 0 || d < nearest)) nearest = d;
        }
        T mixed[kFeatures] = {0};
        for (int64_t j = 0; j < k; ++j) {
          if (!(d2[i * k + j] <= r2 && d2[i * k + j] > 0)) continue;
          const T w = nearest / d2[i * k + j];
          const T* hq = spfh.data() + nb[i * k + j] * kFeatures;
          for (int f = 0; f < kFeatures; ++f) mixed[f] += w * hq[f];
        }
        scale_blocks(mixed);
        T* h = o + i * kFeatures;
        for (int f = 0; f < kFeatures; ++f) h[f] = spfh[i * kFeatures + f] + mixed[f];
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) { m.impl("fpfh", &fpfh_cpu); }

}  // namespace vrnet
