// Argument checks and limits of the voxel_downsample op, shared by its CPU and CUDA kernels.
#pragma once

#include <cmath>

#include "common/common.h"

namespace vrnet {

constexpr double kMaxCell = 4611686018427387904.0;  // 2^62: cell coordinates must stay below it

// points (N, 3) float with N >= 1; voxel_size finite and > 0.
inline void check_voxel_downsample_inputs(const at::Tensor& points, double voxel_size) {
  check_float(points, "points");
  check_dim(points, 2, "points", "(N, 3)");
  TORCH_CHECK_VALUE(points.size(1) == 3, "points must have shape (N, 3), got ", points.sizes());
  TORCH_CHECK_VALUE(points.size(0) >= 1, "points: need at least one point, got ", points.sizes());
  TORCH_CHECK_VALUE(std::isfinite(voxel_size) && voxel_size > 0, "voxel_size must be a finite number > 0, got ",
                    voxel_size);
}

}  // namespace vrnet
