// Geometry-structure loss L2 of VRNet: rmse over all (i, j) of |x_i - x_j| - |y_i - y_j|.
// Row by row with exact coordinate differences and double accumulation: O(B N) memory.
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include <vector>

#include "pairwise_distance_loss/pairwise_distance_loss.h"

namespace vrnet {
namespace {

template <typename scalar_t>
inline double pair_dist(const scalar_t* p, int64_t i, int64_t j) {
  const double dx = double(p[3 * i]) - p[3 * j], dy = double(p[3 * i + 1]) - p[3 * j + 1];
  const double dz = double(p[3 * i + 2]) - p[3 * j + 2];
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

at::Tensor pairwise_distance_loss_cpu(const at::Tensor& x_in, const at::Tensor& y_in) {
  check_pairwise_distance_loss_inputs(x_in, y_in);
  const at::Tensor x = x_in.contiguous(), y = y_in.contiguous();
  check_finite(x, "x");
  check_finite(y, "y");
  const int64_t B = x.size(0), N = x.size(1);
  at::Tensor loss = at::empty({B}, x.options());
  // Rows i and N-1-i form one task, balancing the triangular j > i loops.
  const int64_t tasks = (N + 1) / 2;
  std::vector<double> partial(B * tasks, 0.0);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "pairwise_distance_loss_cpu", [&] {
    const scalar_t *xp = x.const_data_ptr<scalar_t>(), *yp = y.const_data_ptr<scalar_t>();
    parallel_ranges(B * tasks, 8, [&](int64_t begin, int64_t end) {
      for (int64_t bt = begin; bt < end; ++bt) {
        const int64_t b = bt / tasks, t = bt % tasks;
        const scalar_t *xb = xp + b * N * 3, *yb = yp + b * N * 3;
        double acc = 0;
        const int64_t rows[2] = {t, N - 1 - t};
        for (int r = 0; r < (rows[0] == rows[1] ? 1 : 2); ++r) {
          const int64_t i = rows[r];
          for (int64_t j = i + 1; j < N; ++j) {
            const double e = pair_dist(xb, i, j) - pair_dist(yb, i, j);
            acc += e * e;
          }
        }
        partial[bt] = acc;
      }
    });
    scalar_t* lp = loss.mutable_data_ptr<scalar_t>();
    for (int64_t b = 0; b < B; ++b) {
      double total = 0;
      for (int64_t t = 0; t < tasks; ++t) total += partial[b * tasks + t];
      lp[b] = std::sqrt(2.0 * total / (double(N) * double(N)));
    }
  });
  return loss;
}

// d loss / d x_i = 2 g / (N^2 loss) sum_j e_ij (x_i - x_j) / |x_i - x_j|, zero where loss or |.| is 0.
std::tuple<at::Tensor, at::Tensor> pairwise_distance_loss_backward_cpu(const at::Tensor& grad_in, const at::Tensor& x_in,
                                                                       const at::Tensor& y_in, const at::Tensor& loss_in) {
  check_pairwise_distance_loss_backward_inputs(grad_in, x_in, y_in, loss_in);
  const at::Tensor grad = grad_in.contiguous(), x = x_in.contiguous(), y = y_in.contiguous();
  const at::Tensor loss = loss_in.contiguous();
  const int64_t B = x.size(0), N = x.size(1);
  at::Tensor gx = at::empty_like(x), gy = at::empty_like(y);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "pairwise_distance_loss_backward_cpu", [&] {
    const scalar_t *xp = x.const_data_ptr<scalar_t>(), *yp = y.const_data_ptr<scalar_t>();
    const scalar_t *gp = grad.const_data_ptr<scalar_t>(), *lp = loss.const_data_ptr<scalar_t>();
    scalar_t *gxp = gx.mutable_data_ptr<scalar_t>(), *gyp = gy.mutable_data_ptr<scalar_t>();
    parallel_ranges(B * N, 16, [&](int64_t begin, int64_t end) {
      for (int64_t bi = begin; bi < end; ++bi) {
        const int64_t b = bi / N, i = bi % N;
        const scalar_t *xb = xp + b * N * 3, *yb = yp + b * N * 3;
        const double l = lp[b];
        const double scale = l > 0 ? 2.0 * double(gp[b]) / (double(N) * double(N) * l) : 0.0;
        double ax[3] = {0, 0, 0}, ay[3] = {0, 0, 0};
        for (int64_t j = 0; j < N; ++j) {
          const double dx = pair_dist(xb, i, j), dy = pair_dist(yb, i, j);
          const double e = dx - dy;
          const double cx = dx > 0 ? e / dx : 0.0, cy = dy > 0 ? e / dy : 0.0;
          for (int a = 0; a < 3; ++a) {
            ax[a] += cx * (double(xb[3 * i + a]) - xb[3 * j + a]);
            ay[a] += cy * (double(yb[3 * i + a]) - yb[3 * j + a]);
          }
        }
        for (int a = 0; a < 3; ++a) {
          gxp[bi * 3 + a] = scale * ax[a];
          gyp[bi * 3 + a] = -scale * ay[a];
        }
      }
    });
  });
  return {gx, gy};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("pairwise_distance_loss", &pairwise_distance_loss_cpu);
  m.impl("pairwise_distance_loss_backward", &pairwise_distance_loss_backward_cpu);
}

}  // namespace vrnet
