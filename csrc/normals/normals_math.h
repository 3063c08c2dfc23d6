// One point's surface normal, shared by the CPU and CUDA kernels (free of torch includes): the
// covariance of the point and its k neighbours in double precision, the singular vector of its
// smallest singular value (svd3x3/svd3x3_math.h), turned to face the viewpoint.
#pragma once

#include "common/host_device.h"
#include "svd3x3/svd3x3_math.h"

namespace vrnet {

// p: (N, 3) points; neighbours: the k indices of point i; view: the viewpoint; out: its normal (3,).
template <typename scalar_t>
VRNET_HOST_DEVICE void normal_one(const scalar_t* p, const int64_t* neighbours, int64_t i, int64_t k,
                                  const double* view, scalar_t* out) {
  double mean[3] = {static_cast<double>(p[3 * i]), static_cast<double>(p[3 * i + 1]),
                    static_cast<double>(p[3 * i + 2])};
  for (int64_t j = 0; j < k; ++j)
    for (int r = 0; r < 3; ++r) mean[r] += p[3 * neighbours[j] + r];
  for (int r = 0; r < 3; ++r) mean[r] /= static_cast<double>(k + 1);
  double cov[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  for (int64_t j = -1; j < k; ++j) {
    const int64_t q = j < 0 ? i : neighbours[j];
    const double d[3] = {p[3 * q] - mean[0], p[3 * q + 1] - mean[1], p[3 * q + 2] - mean[2]};
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) cov[3 * r + c] += d[r] * d[c];
  }
  double U[9], S[3], V[9];
  svd3x3_double(cov, U, S, V);
  const double n[3] = {V[2], V[5], V[8]};  // the singular vector of the smallest singular value
  const double facing = (view[0] - p[3 * i]) * n[0] + (view[1] - p[3 * i + 1]) * n[1] +
                        (view[2] - p[3 * i + 2]) * n[2];
  const double sign = facing < 0 ? -1.0 : 1.0;
  for (int r = 0; r < 3; ++r) out[r] = static_cast<scalar_t>(sign * n[r]);
}

}  // namespace vrnet
