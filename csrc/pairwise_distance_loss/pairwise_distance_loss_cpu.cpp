// Geometry-structure loss L2 of VRNet: rmse over all (i, j) of |x_i - x_j| - |y_i - y_j|.
//
// Row by row with exact coordinate differences and double accumulation: O(B N) memory. Each cloud
// is first copied to double coordinate planes (x, y, z arrays per batch element; the float to
// double conversion is exact), so that a row's partners are read kLanes at a time. Every sum over a
// row's partners runs in kLanes interleaved partial sums (partner j adds to lane (j - first) mod
// kLanes) reduced in one fixed pairwise order: the AVX-512 loops (8 doubles per register) and the
// portable ones perform the same operations per lane and agree bit for bit.
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "common/cpu_dispatch.h"
#include "pairwise_distance_loss/pairwise_distance_loss.h"

namespace vrnet {
namespace {

constexpr int kLanes = 8;

// Coordinate planes of one cloud: x[n], y[n], z[n] for n < N.
struct Planes {
  const double *x, *y, *z;
};

// (B, N, 3) points -> B consecutive blocks of 3 planes of N doubles.
template <typename scalar_t>
std::vector<double> to_planes(const scalar_t* points, int64_t B, int64_t N) {
  std::vector<double> planes(B * 3 * N);
  for (int64_t b = 0; b < B; ++b)
    for (int64_t n = 0; n < N; ++n)
      for (int a = 0; a < 3; ++a) planes[(b * 3 + a) * N + n] = double(points[(b * N + n) * 3 + a]);
  return planes;
}

Planes planes_of(const std::vector<double>& planes, int64_t b, int64_t N) {
  const double* base = planes.data() + b * 3 * N;
  return {base, base + N, base + 2 * N};
}

double reduce_lanes(double* lanes) {  // fixed pairwise order, shared by both paths
  for (int width = kLanes / 2; width >= 1; width /= 2)
    for (int l = 0; l < width; ++l) lanes[l] += lanes[l + width];
  return lanes[0];
}

inline double distance(const Planes& p, int64_t i, int64_t j) {
  const double dx = p.x[i] - p.x[j], dy = p.y[i] - p.y[j], dz = p.z[i] - p.z[j];
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

// The portable loops run whole blocks of kLanes partners with a fixed lane count into local sums
// (which alias nothing: loops compilers turn into vector code), then the remainder.

// lanes[(j - first) % kLanes] += (|x_i - x_j| - |y_i - y_j|)^2 for first <= j < N.
void add_row_squares_portable(const Planes& x, const Planes& y, int64_t i, int64_t first, int64_t N, double* lanes) {
  double sums[kLanes];
  std::copy(lanes, lanes + kLanes, sums);
  const auto add = [&](int64_t j, int l) {
    const double e = distance(x, i, j) - distance(y, i, j);
    sums[l] += e * e;
  };
  int64_t j0 = first;
  for (; j0 + kLanes <= N; j0 += kLanes)
    for (int l = 0; l < kLanes; ++l) add(j0 + l, l);
  for (int l = 0; j0 + l < N; ++l) add(j0 + l, l);
  std::copy(sums, sums + kLanes, lanes);
}

// The gradient sums of row i over every j: gx += c_x (x_i - x_j), gy += c_y (y_i - y_j) with
// e = |x_i - x_j| - |y_i - y_j|, c_x = e / |x_i - x_j| (0 where that is 0), c_y = e / |y_i - y_j|
// (likewise); lane (j mod kLanes) of each of the 6 sums.
// The quotients divide by 1 where a distance is 0 and then take 0: a select, not a branch.
void add_row_gradients_portable(const Planes& x, const Planes& y, int64_t i, int64_t N, double (*gx)[kLanes],
                                double (*gy)[kLanes]) {
  double sx[3][kLanes], sy[3][kLanes];
  for (int a = 0; a < 3; ++a) {
    std::copy(gx[a], gx[a] + kLanes, sx[a]);
    std::copy(gy[a], gy[a] + kLanes, sy[a]);
  }
  const double xi[3] = {x.x[i], x.y[i], x.z[i]}, yi[3] = {y.x[i], y.y[i], y.z[i]};
  const auto add = [&](int64_t j, int l) {
    const double dx = distance(x, i, j), dy = distance(y, i, j);
    const double e = dx - dy;
    const double qx = e / (dx > 0 ? dx : 1.0), qy = e / (dy > 0 ? dy : 1.0);
    const double cx = dx > 0 ? qx : 0.0, cy = dy > 0 ? qy : 0.0;
    sx[0][l] += cx * (xi[0] - x.x[j]);
    sx[1][l] += cx * (xi[1] - x.y[j]);
    sx[2][l] += cx * (xi[2] - x.z[j]);
    sy[0][l] += cy * (yi[0] - y.x[j]);
    sy[1][l] += cy * (yi[1] - y.y[j]);
    sy[2][l] += cy * (yi[2] - y.z[j]);
  };
  int64_t j0 = 0;
  for (; j0 + kLanes <= N; j0 += kLanes)
    for (int l = 0; l < kLanes; ++l) add(j0 + l, l);
  for (int l = 0; j0 + l < N; ++l) add(j0 + l, l);
  for (int a = 0; a < 3; ++a) {
    std::copy(sx[a], sx[a] + kLanes, gx[a]);
    std::copy(sy[a], sy[a] + kLanes, gy[a]);
  }
}

#ifdef VRNET_X86_DISPATCH
#define VRNET_AVX512_FN __attribute__((target("avx512f")))

struct Diff {  // coordinate differences of point i and 8 partners, and their distance
  __m512d dx, dy, dz, dist;
};

VRNET_AVX512_FN static inline Diff diff_avx512(const Planes& p, int64_t i, int64_t j0, __mmask8 lanes) {
  const __m512d dx = _mm512_sub_pd(_mm512_set1_pd(p.x[i]), _mm512_maskz_loadu_pd(lanes, p.x + j0));
  const __m512d dy = _mm512_sub_pd(_mm512_set1_pd(p.y[i]), _mm512_maskz_loadu_pd(lanes, p.y + j0));
  const __m512d dz = _mm512_sub_pd(_mm512_set1_pd(p.z[i]), _mm512_maskz_loadu_pd(lanes, p.z + j0));
  const __m512d sq = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(dx, dx), _mm512_mul_pd(dy, dy)), _mm512_mul_pd(dz, dz));
  return {dx, dy, dz, _mm512_sqrt_pd(sq)};
}

VRNET_AVX512_FN static inline __mmask8 block_lanes(int64_t remaining) {
  return remaining >= kLanes ? __mmask8(0xff) : static_cast<__mmask8>((1u << remaining) - 1);
}

VRNET_AVX512_FN void add_row_squares_avx512(const Planes& x, const Planes& y, int64_t i, int64_t first, int64_t N,
                                            double* lanes) {
  __m512d sums = _mm512_loadu_pd(lanes);
  for (int64_t j0 = first; j0 < N; j0 += kLanes) {
    const __mmask8 valid = block_lanes(N - j0);
    const __m512d e = _mm512_sub_pd(diff_avx512(x, i, j0, valid).dist, diff_avx512(y, i, j0, valid).dist);
    sums = _mm512_mask_add_pd(sums, valid, sums, _mm512_mul_pd(e, e));
  }
  _mm512_storeu_pd(lanes, sums);
}

// Row i's partners j0 .. j0 + 7 land in lanes 0 .. 7: blocks start at multiples of kLanes.
VRNET_AVX512_FN void add_row_gradients_avx512(const Planes& x, const Planes& y, int64_t i, int64_t N,
                                              double (*gx)[kLanes], double (*gy)[kLanes]) {
  __m512d ax[3], ay[3];
  for (int a = 0; a < 3; ++a) {
    ax[a] = _mm512_loadu_pd(gx[a]);
    ay[a] = _mm512_loadu_pd(gy[a]);
  }
  const __m512d zero = _mm512_setzero_pd();
  for (int64_t j0 = 0; j0 < N; j0 += kLanes) {
    const __mmask8 valid = block_lanes(N - j0);
    const Diff dx = diff_avx512(x, i, j0, valid), dy = diff_avx512(y, i, j0, valid);
    const __m512d e = _mm512_sub_pd(dx.dist, dy.dist);
    const __m512d cx = _mm512_maskz_div_pd(_mm512_cmp_pd_mask(dx.dist, zero, _CMP_GT_OQ), e, dx.dist);
    const __m512d cy = _mm512_maskz_div_pd(_mm512_cmp_pd_mask(dy.dist, zero, _CMP_GT_OQ), e, dy.dist);
    ax[0] = _mm512_mask_add_pd(ax[0], valid, ax[0], _mm512_mul_pd(cx, dx.dx));
    ax[1] = _mm512_mask_add_pd(ax[1], valid, ax[1], _mm512_mul_pd(cx, dx.dy));
    ax[2] = _mm512_mask_add_pd(ax[2], valid, ax[2], _mm512_mul_pd(cx, dx.dz));
    ay[0] = _mm512_mask_add_pd(ay[0], valid, ay[0], _mm512_mul_pd(cy, dy.dx));
    ay[1] = _mm512_mask_add_pd(ay[1], valid, ay[1], _mm512_mul_pd(cy, dy.dy));
    ay[2] = _mm512_mask_add_pd(ay[2], valid, ay[2], _mm512_mul_pd(cy, dy.dz));
  }
  for (int a = 0; a < 3; ++a) {
    _mm512_storeu_pd(gx[a], ax[a]);
    _mm512_storeu_pd(gy[a], ay[a]);
  }
}
#endif

void add_row_squares(const Planes& x, const Planes& y, int64_t i, int64_t first, int64_t N, double* lanes) {
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) return add_row_squares_avx512(x, y, i, first, N, lanes);
#endif
  add_row_squares_portable(x, y, i, first, N, lanes);
}

void add_row_gradients(const Planes& x, const Planes& y, int64_t i, int64_t N, double (*gx)[kLanes],
                       double (*gy)[kLanes]) {
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) return add_row_gradients_avx512(x, y, i, N, gx, gy);
#endif
  add_row_gradients_portable(x, y, i, N, gx, gy);
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
    const std::vector<double> x_planes = to_planes(x.const_data_ptr<scalar_t>(), B, N);
    const std::vector<double> y_planes = to_planes(y.const_data_ptr<scalar_t>(), B, N);
    parallel_ranges(B * tasks, 8, [&](int64_t begin, int64_t end) {
      for (int64_t bt = begin; bt < end; ++bt) {
        const int64_t b = bt / tasks, t = bt % tasks;
        const Planes xb = planes_of(x_planes, b, N), yb = planes_of(y_planes, b, N);
        double lanes[kLanes] = {};
        const int64_t rows[2] = {t, N - 1 - t};
        for (int r = 0; r < (rows[0] == rows[1] ? 1 : 2); ++r) add_row_squares(xb, yb, rows[r], rows[r] + 1, N, lanes);
        partial[bt] = reduce_lanes(lanes);
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
    const std::vector<double> x_planes = to_planes(x.const_data_ptr<scalar_t>(), B, N);
    const std::vector<double> y_planes = to_planes(y.const_data_ptr<scalar_t>(), B, N);
    const scalar_t *gp = grad.const_data_ptr<scalar_t>(), *lp = loss.const_data_ptr<scalar_t>();
    scalar_t *gxp = gx.mutable_data_ptr<scalar_t>(), *gyp = gy.mutable_data_ptr<scalar_t>();
    parallel_ranges(B * N, 16, [&](int64_t begin, int64_t end) {
      for (int64_t bi = begin; bi < end; ++bi) {
        const int64_t b = bi / N, i = bi % N;
        const double l = lp[b];
        const double scale = l > 0 ? 2.0 * double(gp[b]) / (double(N) * double(N) * l) : 0.0;
        double ax[3][kLanes] = {}, ay[3][kLanes] = {};
        add_row_gradients(planes_of(x_planes, b, N), planes_of(y_planes, b, N), i, N, ax, ay);
        for (int a = 0; a < 3; ++a) {
          gxp[bi * 3 + a] = scale * reduce_lanes(ax[a]);
          gyp[bi * 3 + a] = -scale * reduce_lanes(ay[a]);
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
