// Argument checks of the spatial_consistency op, shared by its CPU and CUDA kernels.
#pragma once

#include "common/common.h"

namespace vrnet {

// Correspondences at most: the compatibility graph is K^2 / 8 bytes (8 MB at 8192).
constexpr int64_t kMaxCorrespondences = 1 << 15;

// The graph is decided in float32 (on coordinates relative to the first correspondence) when the
// points' extent is at most this many tolerances: float32 then moves the boundary of the test by
// under 1 % of the tolerance (tested); larger extents are decided in float64.
constexpr double kFloatGraphExtent = 128;

inline void check_spatial_consistency_inputs(const at::Tensor& src, const at::Tensor& tgt, double tolerance,
                                             double inlier_threshold, int64_t seeds, int64_t consensus) {
  TORCH_CHECK_TYPE(src.scalar_type() == at::kDouble, "src must be float64, got ", src.scalar_type());
  TORCH_CHECK_TYPE(tgt.scalar_type() == at::kDouble, "tgt must be float64, got ", tgt.scalar_type());
  TORCH_CHECK_VALUE(src.dim() == 2 && src.size(1) == 3, "src must have shape (K, 3), got ", src.sizes());
  TORCH_CHECK_VALUE(tgt.sizes() == src.sizes(), "tgt must have the shape of src ", src.sizes(), ", got ",
                    tgt.sizes());
  TORCH_CHECK_VALUE(src.size(0) >= 3, "src needs at least 3 correspondences, got ", src.size(0));
  TORCH_CHECK_VALUE(src.size(0) <= kMaxCorrespondences, "src holds ", src.size(0),
                    " correspondences; at most ", kMaxCorrespondences, " (the compatibility graph grows as K^2)");
  TORCH_CHECK_VALUE(std::isfinite(tolerance) && tolerance > 0, "tolerance must be a positive number, got ", tolerance);
  TORCH_CHECK_VALUE(std::isfinite(inlier_threshold) && inlier_threshold > 0,
                    "inlier_threshold must be a positive number, got ", inlier_threshold);
  TORCH_CHECK_VALUE(seeds >= 1, "seeds must be >= 1, got ", seeds);
  TORCH_CHECK_VALUE(consensus >= 2, "consensus must be >= 2, got ", consensus);
  check_same_device(src, "src", tgt, "tgt");
}

}  // namespace vrnet
