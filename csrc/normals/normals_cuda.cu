// Torch glue of the CUDA normals op (kernel: normals_kernels.cuh).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "normals/normals.h"
#include "normals/normals_kernels.cuh"

namespace vrnet {
namespace {

at::Tensor normals_cuda(const at::Tensor& points_in, const at::Tensor& idx_in, at::ArrayRef<double> viewpoint) {
  check_normals_inputs(points_in, idx_in, viewpoint);
  VRNET_CUDA_GUARD(points_in);
  const at::Tensor points = points_in.contiguous(), idx = idx_in.contiguous();
  check_finite(points, "points");
  const int64_t N = points.size(0), k = idx.size(1);
  at::Tensor out = at::empty({N, 3}, points.options());
  if (N == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "normals_cuda", [&] {
    launch<normals_kernel<scalar_t>>(per_item(N, 128), points, idx, N, k, viewpoint[0], viewpoint[1], viewpoint[2],
                                     out);
  });
  return out;
}

}  // namespace

VRNET_CUDA_IMPL(m) { m.impl("normals", &normals_cuda); }

}  // namespace vrnet
