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
  VRNET_CUDA_GUARD(points_in);
  const FpfhInputs in = checked_fpfh_inputs(points_in, normals_in, idx_in, dist2_in, radius);
  const at::Tensor &points = in.points, &normals = in.normals, &idx = in.idx, &dist2 = in.dist2;
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
