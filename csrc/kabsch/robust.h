// The reweighting steps of the robust_kabsch op, shared by its CPU and CUDA kernels: the robust
// weight w(u) of a residual u in units of the pair's scale (the same kernels as
// vrnet_ext/geometry/robust.py), the scale of a pair, and the residual under a solved Procrustes.
// Free of torch includes (the CUDA kernel header uses it).
#pragma once

#include <cmath>

#include "kabsch/procrustes.h"

namespace vrnet {

enum class RobustKernel : int { kCauchy = 0, kGemanMcClure = 1, kWelsch = 2 };

// What every reweighting step needs: the kernel, s = max(scale x median residual, min_scale), steps.
struct RobustOptions {
  RobustKernel kernel;
  double scale, min_scale;
  int64_t iterations;
};

// w(u): Cauchy 1 / (1 + u^2), Geman-McClure 1 / (1 + u^2)^2, Welsch exp(-u^2); 1 at u = 0.
VRNET_HOST_DEVICE inline double robust_weight(RobustKernel kernel, double u) {
  const double squared = u * u;
  switch (kernel) {
    case RobustKernel::kCauchy:
      return 1.0 / (1.0 + squared);
    case RobustKernel::kGemanMcClure:
      return 1.0 / ((1.0 + squared) * (1.0 + squared));
    default:
      return exp(-squared);
  }
}

VRNET_HOST_DEVICE inline double robust_pair_scale(const RobustOptions& options, double median_residual) {
  const double s = options.scale * median_residual;
  return s > options.min_scale ? s : options.min_scale;
}

// |R x + t - y| for the solved problem p (t = tgt_c - R src_c), in double.
template <typename scalar_t>
VRNET_HOST_DEVICE double procrustes_residual(const Procrustes& p, const scalar_t* x, const scalar_t* y) {
  double sum = 0;
  for (int a = 0; a < 3; ++a) {
    double moved = p.tgt_c[a] - double(y[a]);
    for (int c = 0; c < 3; ++c) moved += p.R[3 * a + c] * (double(x[c]) - p.src_c[c]);
    sum += moved * moved;
  }
  return sqrt(sum);
}

}  // namespace vrnet
