// Argument checks of the fpfh op, shared by its CPU and CUDA kernels.
#pragma once

#include <cmath>

#include "normals/normals.h"

namespace vrnet {

// points, normals (N, 3) of one dtype; idx (N, k) neighbours and dist2 (N, k) their squared
// distances (kNN); radius finite > 0.
inline void check_fpfh_inputs(const at::Tensor& points, const at::Tensor& normals, const at::Tensor& idx,
                              const at::Tensor& dist2, double radius) {
  check_neighbourhood(points, idx);
  check_float(normals, "normals");
  check_float(dist2, "dist2");
  TORCH_CHECK_VALUE(normals.sizes() == points.sizes(), "normals must have the shape of points ", points.sizes(),
                    ", got ", normals.sizes());
  TORCH_CHECK_VALUE(dist2.sizes() == idx.sizes(), "dist2 must have the shape of idx ", idx.sizes(), ", got ",
                    dist2.sizes());
  TORCH_CHECK_TYPE(normals.scalar_type() == points.scalar_type() && dist2.scalar_type() == points.scalar_type(),
                   "points, normals and dist2 must share a dtype");
  check_same_device(points, "points", normals, "normals");
  check_same_device(points, "points", dist2, "dist2");
  TORCH_CHECK_VALUE(std::isfinite(radius) && radius > 0, "radius must be a finite number > 0, got ", radius);
}

// The op's inputs checked (check_fpfh_inputs), made contiguous, points and normals finite.
struct FpfhInputs {
  at::Tensor points, normals, idx, dist2;
};

inline FpfhInputs checked_fpfh_inputs(const at::Tensor& points, const at::Tensor& normals, const at::Tensor& idx,
                                      const at::Tensor& dist2, double radius) {
  check_fpfh_inputs(points, normals, idx, dist2, radius);
  FpfhInputs in{points.contiguous(), normals.contiguous(), idx.contiguous(), dist2.contiguous()};
  check_finite(in.points, "points");
  check_finite(in.normals, "normals");
  return in;
}

}  // namespace vrnet
