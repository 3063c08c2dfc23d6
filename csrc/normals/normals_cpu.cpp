// Surface normals: for each point, the covariance of itself and its neighbours idx[i, :], and the
// eigenvector of its smallest eigenvalue (double-precision Jacobi, svd3x3.h), turned to face the
// viewpoint. One parallel region over points (parallel_ranges).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "normals/normals.h"
#include "svd3x3/svd3x3.h"

namespace vrnet {
namespace {

at::Tensor normals_cpu(const at::Tensor& points_in, const at::Tensor& idx_in, at::ArrayRef<double> viewpoint) {
  check_neighbourhood(points_in, idx_in);
  TORCH_CHECK_VALUE(viewpoint.size() == 3, "viewpoint must have 3 coordinates, got ", viewpoint.size());
  TORCH_CHECK_VALUE(idx_in.size(1) >= 2, "idx must hold at least 2 neighbours per point, got ", idx_in.sizes());
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
      for (int64_t i = begin; i < end; ++i) {
        double mean[3] = {p[3 * i], p[3 * i + 1], p[3 * i + 2]};
        for (int64_t j = 0; j < k; ++j)
          for (int r = 0; r < 3; ++r) mean[r] += p[3 * nb[i * k + j] + r];
        for (int r = 0; r < 3; ++r) mean[r] /= static_cast<double>(k + 1);
        double cov[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        for (int64_t j = -1; j < k; ++j) {
          const int64_t q = j < 0 ? i : nb[i * k + j];
          const double d[3] = {p[3 * q] - mean[0], p[3 * q + 1] - mean[1], p[3 * q + 2] - mean[2]};
          for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) cov[3 * r + c] += d[r] * d[c];
        }
        double U[9], S[3], V[9];
        svd3x3_double(cov, U, S, V);
        double n[3] = {V[2], V[5], V[8]};  // the singular vector of the smallest singular value
        const double facing = (view[0] - p[3 * i]) * n[0] + (view[1] - p[3 * i + 1]) * n[1] +
                              (view[2] - p[3 * i + 2]) * n[2];
        const double sign = facing < 0 ? -1.0 : 1.0;
        for (int r = 0; r < 3; ++r) o[3 * i + r] = static_cast<scalar_t>(sign * n[r]);
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) { m.impl("normals", &normals_cpu); }

}  // namespace vrnet
