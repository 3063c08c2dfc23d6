// Torch glue of the CUDA fpfh op (kernels: fpfh_kernels.cuh).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "fpfh/fpfh.h"
#include "fpfh/fpfh_kernels.cuh"

namespace vrnet {
namespace {

at::Tensor fpfh_cuda(const at::Tensor& points_in, const at::Tensor& normals_in, const at::Tensor& idx_in,
                     const at::Tensor& dist2_in, double radius) {
  check_fpfh_inputs(points_in, normals_in, idx_in, dist2_in, radius);
  VRNET_CUDA_GUARD(points_in);
  const at::Tensor points = points_in.contiguous(), normals = normals_in.contiguous();
  const at::Tensor idx = idx_in.contiguous(), dist2 = dist2_in.contiguous();
  check_finite(points, "points");
  check_finite(normals, "normals");
  const int64_t N = points.size(0), k = idx.size(1);
  at::Tensor out = at::empty({N, fpfh_detail::kFeatures}, points.options());
  if (N == 0) return out;
  at::Tensor spfh = at::empty({N, fpfh_detail::kFeatures}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "fpfh_cuda", [&] {
    const scalar_t r2 = static_cast<scalar_t>(radius * radius);
    launch<spfh_kernel<scalar_t>>(per_item(N, 128), points, normals, idx, dist2, N, k, r2, spfh);
    launch<fpfh_kernel<scalar_t>>(per_item(N, 128), spfh, idx, dist2, N, k, r2, out);
  });
  return out;
}

}  // namespace

VRNET_CUDA_IMPL(m) { m.impl("fpfh", &fpfh_cuda); }

}  // namespace vrnet
