// Argument checks of the normals op, shared by its CPU and CUDA kernels.
#pragma once

#include "common/common.h"

namespace vrnet {

// points (N, 3) float, idx (N, k) int64 neighbours in [0, N), k >= 2.
inline void check_neighbourhood(const at::Tensor& points, const at::Tensor& idx) {
  check_float(points, "points");
  check_index(idx, "idx");
  check_dim(points, 2, "points", "(N, 3)");
  check_dim(idx, 2, "idx", "(N, k)");
  check_same_device(points, "points", idx, "idx");
  TORCH_CHECK_VALUE(points.size(1) == 3, "points must have shape (N, 3), got ", points.sizes());
  TORCH_CHECK_VALUE(idx.size(0) == points.size(0), "idx must have one row per point (N = ", points.size(0),
                    "), got ", idx.sizes());
  check_index_range(idx, points.size(0), "idx");
}

// check_neighbourhood, a viewpoint of 3 coordinates and at least 2 neighbours per point.
inline void check_normals_inputs(const at::Tensor& points, const at::Tensor& idx, at::ArrayRef<double> viewpoint) {
  check_neighbourhood(points, idx);
  TORCH_CHECK_VALUE(viewpoint.size() == 3, "viewpoint must have 3 coordinates, got ", viewpoint.size());
  TORCH_CHECK_VALUE(idx.size(1) >= 2, "idx must hold at least 2 neighbours per point, got ", idx.sizes());
}

}  // namespace vrnet
