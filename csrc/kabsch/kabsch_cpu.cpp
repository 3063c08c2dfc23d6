// Weighted Kabsch / Procrustes on CPU: R, t = argmin sum_i w_i |R x_i + t - y_i|^2 over proper
// rotations. Weights enter once (normalised to sum 1), centroids and covariance are fused, the 3x3
// solve runs in double (kabsch/kabsch.h holds the solve and the backward shared with CUDA).
// robust_kabsch: the same solve, then reweighting steps on one problem's points (median by
// selection, weights in double), no tensor op per step.
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include <algorithm>
#include <vector>

#include "kabsch/kabsch.h"

namespace vrnet {
namespace {

// Two passes over one problem's points: centroids, then the centred covariance; then the solve.
template <typename scalar_t, typename weight_t>
Procrustes solve(const scalar_t* x, const scalar_t* y, const weight_t* w, int64_t n) {
  Procrustes p;
  p.wscale = 0;
  for (int64_t i = 0; i < n; ++i) p.wscale = std::max(p.wscale, double(w[i]));
  for (int64_t i = 0; i < n; ++i) p.wsum += w[i] / p.wscale;
  for (int64_t i = 0; i < n; ++i)
    for (int a = 0; a < 3; ++a) {
      p.src_c[a] += w[i] / p.wscale * double(x[3 * i + a]);
      p.tgt_c[a] += w[i] / p.wscale * double(y[3 * i + a]);
    }
  for (int a = 0; a < 3; ++a) {
    p.src_c[a] /= p.wsum;
    p.tgt_c[a] /= p.wsum;
  }
  for (int64_t i = 0; i < n; ++i) {
    const double wi = w[i] / p.wscale / p.wsum;
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c) p.H[3 * a + c] += wi * (x[3 * i + a] - p.src_c[a]) * (y[3 * i + c] - p.tgt_c[c]);
  }
  p.solve_rotation();
  return p;
}

template <typename scalar_t>
void check_weights(const scalar_t* w, int64_t n, int64_t b) {
  double total = 0;
  for (int64_t i = 0; i < n; ++i) {
    TORCH_CHECK_VALUE(w[i] >= 0, "weights must be non-negative (batch ", b, ", point ", i, " is ", double(w[i]), ")");
    total += w[i];
  }
  TORCH_CHECK_VALUE(total > 0, "weights of batch ", b, " sum to zero: at least one point needs a positive weight");
}

// A forward's common part: the inputs made contiguous and checked (finite; per problem non-negative
// weights with a positive sum), the outputs allocated, then solve_range(x, y, w, N, R, t, begin, end)
// on typed pointers for ranges of problems of at least `grain`.
template <typename SolveRange>
std::tuple<at::Tensor, at::Tensor> solve_problems(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                  const at::Tensor& weights_in, int64_t grain,
                                                  const SolveRange& solve_range) {
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  check_finite(src, "src");
  check_finite(tgt, "tgt");
  check_finite(weights, "weights");
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor R = at::empty({B, 3, 3}, src.options()), t = at::empty({B, 3}, src.options());
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_cpu", [&] {
    const scalar_t *xp = src.const_data_ptr<scalar_t>(), *yp = tgt.const_data_ptr<scalar_t>();
    const scalar_t* wp = weights.const_data_ptr<scalar_t>();
    for (int64_t b = 0; b < B; ++b) check_weights(wp + b * N, N, b);
    scalar_t *rp = R.mutable_data_ptr<scalar_t>(), *tp = t.mutable_data_ptr<scalar_t>();
    parallel_ranges(B, grain, [&](int64_t begin, int64_t end) { solve_range(xp, yp, wp, N, rp, tp, begin, end); });
  });
  return {R, t};
}

std::tuple<at::Tensor, at::Tensor> kabsch_cpu(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                              const at::Tensor& weights_in) {
  check_kabsch_inputs(src_in, tgt_in, weights_in);
  const int64_t grain = std::max<int64_t>(1, 4096 / src_in.size(1));
  return solve_problems(src_in, tgt_in, weights_in, grain,
                        [](const auto* x, const auto* y, const auto* w, int64_t N, auto* R, auto* t, int64_t begin,
                           int64_t end) {
                          for (int64_t b = begin; b < end; ++b)
                            solve(x + b * N * 3, y + b * N * 3, w + b * N, N).write(R + 9 * b, t + 3 * b);
                        });
}

// The weighted solve, then options.iterations steps: residuals r_i, s = robust_pair_scale(median r),
// weights w_i * robust_weight(r_i / s), solve again. A step whose weights all vanish (possible only in
// Welsch's tail) ends the problem's steps. `scratch` holds 3 n doubles.
template <typename scalar_t>
Procrustes robust_solve(const scalar_t* x, const scalar_t* y, const scalar_t* w, int64_t n, const RobustOptions& options,
                        double* scratch) {
  Procrustes p = solve(x, y, w, n);
  double *residual = scratch, *selected = scratch + n, *weight = scratch + 2 * n;
  const int64_t middle = (n - 1) / 2;  // the lower median, as torch.median
  for (int64_t step = 0; step < options.iterations; ++step) {
    for (int64_t i = 0; i < n; ++i) residual[i] = procrustes_residual(p, x + 3 * i, y + 3 * i);
    std::copy(residual, residual + n, selected);
    std::nth_element(selected, selected + middle, selected + n);
    const double pair_scale = robust_pair_scale(options, selected[middle]);
    double largest = 0;
    for (int64_t i = 0; i < n; ++i) {
      weight[i] = double(w[i]) * robust_weight(options.kernel, residual[i] / pair_scale);
      largest = std::max(largest, weight[i]);
    }
    if (!(largest > 0)) break;
    p = solve(x, y, weight, n);
  }
  return p;
}

std::tuple<at::Tensor, at::Tensor> robust_kabsch_cpu(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                     const at::Tensor& weights_in, int64_t iterations,
                                                     c10::string_view kernel, double scale, double min_scale) {
  const RobustOptions options =
      check_robust_kabsch_inputs(src_in, tgt_in, weights_in, iterations, kernel, scale, min_scale);
  return solve_problems(src_in, tgt_in, weights_in, 1,
                        [&](const auto* x, const auto* y, const auto* w, int64_t N, auto* R, auto* t, int64_t begin,
                            int64_t end) {
                          std::vector<double> scratch(3 * N);
                          for (int64_t b = begin; b < end; ++b)
                            robust_solve(x + b * N * 3, y + b * N * 3, w + b * N, N, options, scratch.data())
                                .write(R + 9 * b, t + 3 * b);
                        });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> kabsch_backward_cpu(const at::Tensor& gR_in, const at::Tensor& gt_in,
                                                                   const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                                   const at::Tensor& weights_in) {
  check_kabsch_backward_inputs(gR_in, gt_in, src_in, tgt_in, weights_in);
  const at::Tensor gR = gR_in.contiguous(), gt = gt_in.contiguous();
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous(), weights = weights_in.contiguous();
  const int64_t B = src.size(0), N = src.size(1);
  at::Tensor g_src = at::empty_like(src), g_tgt = at::empty_like(tgt), g_w = at::empty_like(weights);
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "kabsch_backward_cpu", [&] {
    const scalar_t *xp = src.const_data_ptr<scalar_t>(), *yp = tgt.const_data_ptr<scalar_t>();
    const scalar_t *wp = weights.const_data_ptr<scalar_t>(), *grp = gR.const_data_ptr<scalar_t>();
    const scalar_t* gtp = gt.const_data_ptr<scalar_t>();
    scalar_t *gxp = g_src.mutable_data_ptr<scalar_t>(), *gyp = g_tgt.mutable_data_ptr<scalar_t>();
    scalar_t* gwp = g_w.mutable_data_ptr<scalar_t>();
    parallel_ranges(B, std::max<int64_t>(1, 4096 / N), [&](int64_t begin, int64_t end) {
      for (int64_t b = begin; b < end; ++b) {
        const scalar_t *x = xp + b * N * 3, *y = yp + b * N * 3, *w = wp + b * N;
        const Procrustes p = solve(x, y, w, N);
        const ProcrustesGrad grad(p, grp + 9 * b, gtp + 3 * b);
        // The per-point terms stay in double until the end (in a float32 output buffer they
        // overflow for coordinates ~1e20 and the weight gradient came out wrong).
        std::vector<double> g_what(N);
        double weighted_mean = 0;
        for (int64_t i = 0; i < N; ++i) {
          g_what[i] = grad.point(p, x + 3 * i, y + 3 * i, w[i], gxp + (b * N + i) * 3, gyp + (b * N + i) * 3);
          weighted_mean += w[i] / p.wscale / p.wsum * g_what[i];
        }
        const double total_weight = p.wscale * p.wsum;  // may overflow to inf: the gradient is then ~0
        for (int64_t i = 0; i < N; ++i)
          gwp[b * N + i] = static_cast<scalar_t>(finish_weight_grad(g_what[i], weighted_mean, total_weight));
      }
    });
  });
  return {g_src, g_tgt, g_w};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("kabsch", &kabsch_cpu);
  m.impl("kabsch_backward", &kabsch_backward_cpu);
  m.impl("robust_kabsch", &robust_kabsch_cpu);
}

}  // namespace vrnet
