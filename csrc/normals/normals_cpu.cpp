// Surface normals: for each point, the covariance of itself and its neighbours idx[i, :], and the
// eigenvector of its smallest eigenvalue (normals/normals_math.h, shared with the CUDA kernel),
// turned to face the viewpoint. One parallel region over points (parallel_ranges).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "normals/normals.h"
#include "normals/normals_math.h"

namespace vrnet {
namespace {

at::Tensor normals_cpu(const at::Tensor& points_in, const at::Tensor& idx_in, at::ArrayRef<double> viewpoint) {
  check_normals_inputs(points_in, idx_in, viewpoint);
  const at::Tensor points = points_in.contiguous(), idx = idx_in.contiguous();
  check_finite(points, "points");
  const int64_t N = points.size(0), k = idx.size(1);
  at::Tensor out = at::empty({N, 3}, points.options());
  const double view[3] = {viewpoint[0], viewpoint[1], viewpoint[2]};
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "normals_cpu", [&] {
    const scalar_t* p = points.const_data_ptr<scalar_t>();
    const int64_t* nb = idx.const_data_ptr<int64_t>();
    scalar_t* o = out.mutable_data_ptr<scalar_t>();
    parallel_ranges(N, 256, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) normal_one(p, nb + i * k, i, k, view, o + 3 * i);
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) { m.impl("normals", &normals_cpu); }

}  // namespace vrnet
