// DGCNN edge tensor out[b, :, n, j] = [x_idx - x_n ; x_n] and its scatter-add backward.
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include "edge_features/edge_features.h"

namespace vrnet {
namespace {

at::Tensor edge_features_cpu(const at::Tensor& x_in, const at::Tensor& idx_in) {
  check_edge_features_inputs(x_in, idx_in);
  const at::Tensor x = x_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = x.size(0), C = x.size(1), N = x.size(2), k = idx.size(2);
  at::Tensor out = at::empty({B, 2 * C, N, k}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "edge_features_cpu", [&] {
    const scalar_t* xp = x.const_data_ptr<scalar_t>();
    const int64_t* ip = idx.const_data_ptr<int64_t>();
    scalar_t* op = out.mutable_data_ptr<scalar_t>();
    parallel_ranges(B * C, 1, [&](int64_t begin, int64_t end) {
      for (int64_t bc = begin; bc < end; ++bc) {
        const int64_t b = bc / C, c = bc % C;
        const scalar_t* row = xp + bc * N;
        const int64_t* ib = ip + b * N * k;
        scalar_t* diff = op + (b * 2 * C + c) * N * k;
        scalar_t* centre = op + (b * 2 * C + C + c) * N * k;
        for (int64_t n = 0; n < N; ++n)
          for (int64_t j = 0; j < k; ++j) {
            diff[n * k + j] = row[ib[n * k + j]] - row[n];
            centre[n * k + j] = row[n];
          }
      }
    });
  });
  return out;
}

// grad_x[c, m] = sum_{(n,j): idx=m} g_diff[c,n,j] + sum_j (g_centre[c,m,j] - g_diff[c,m,j]).
// grad_out is read through its strides: the expanded gradient of a sum or mean (stride 0) is
// never copied into a dense (B, 2C, N, k) tensor.
at::Tensor edge_features_backward_cpu(const at::Tensor& grad, const at::Tensor& idx_in, int64_t num_points) {
  check_edge_features_backward_inputs(grad, idx_in, num_points);
  const at::Tensor idx = idx_in.contiguous();
  const int64_t B = grad.size(0), C = grad.size(1) / 2, N = num_points, k = idx.size(2);
  const int64_t sb = grad.stride(0), sc = grad.stride(1), sn = grad.stride(2), sj = grad.stride(3);
  at::Tensor grad_x = at::zeros({B, C, N}, grad.options());
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "edge_features_backward_cpu", [&] {
    const scalar_t* gp = grad.const_data_ptr<scalar_t>();
    const int64_t* ip = idx.const_data_ptr<int64_t>();
    scalar_t* gx = grad_x.mutable_data_ptr<scalar_t>();
    parallel_ranges(B * C, 1, [&](int64_t begin, int64_t end) {
      for (int64_t bc = begin; bc < end; ++bc) {
        const int64_t b = bc / C, c = bc % C;
        const int64_t* ib = ip + b * N * k;
        const scalar_t* g_diff = gp + b * sb + c * sc;
        const scalar_t* g_centre = gp + b * sb + (C + c) * sc;
        scalar_t* row = gx + bc * N;
        for (int64_t n = 0; n < N; ++n) {
          scalar_t self = 0;
          for (int64_t j = 0; j < k; ++j) {
            const scalar_t gd = g_diff[n * sn + j * sj];
            row[ib[n * k + j]] += gd;
            self += g_centre[n * sn + j * sj] - gd;
          }
          row[n] += self;
        }
      }
    });
  });
  return grad_x;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("edge_features", &edge_features_cpu);
  m.impl("edge_features_backward", &edge_features_backward_cpu);
}

}  // namespace vrnet
