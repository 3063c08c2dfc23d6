// Batched 3x3 SVD (double internally) and its backward with damped 1/(s_k -+ s_l) terms.
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/common.h"
#include "svd3x3/svd3x3.h"

namespace vrnet {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> svd3x3_cpu(const at::Tensor& A_in) {
  check_float(A_in, "A");
  TORCH_CHECK_VALUE(A_in.dim() == 3 && A_in.size(1) == 3 && A_in.size(2) == 3,
                    "A must have shape (B, 3, 3), got ", A_in.sizes());
  const at::Tensor A = A_in.contiguous();
  check_finite(A, "A");
  const int64_t B = A.size(0);
  at::Tensor U = at::empty({B, 3, 3}, A.options()), V = at::empty({B, 3, 3}, A.options());
  at::Tensor S = at::empty({B, 3}, A.options());
  AT_DISPATCH_FLOATING_TYPES(A.scalar_type(), "svd3x3_cpu", [&] {
    const scalar_t* ap = A.const_data_ptr<scalar_t>();
    scalar_t *up = U.mutable_data_ptr<scalar_t>(), *sp = S.mutable_data_ptr<scalar_t>();
    scalar_t* vp = V.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, B, 256, [&](int64_t begin, int64_t end) {
      for (int64_t b = begin; b < end; ++b) {
        double a[9], u[9], s[3], v[9];
        for (int i = 0; i < 9; ++i) a[i] = ap[9 * b + i];
        svd3x3_double(a, u, s, v);
        for (int i = 0; i < 9; ++i) { up[9 * b + i] = u[i]; vp[9 * b + i] = v[i]; }
        for (int i = 0; i < 3; ++i) sp[3 * b + i] = s[i];
      }
    });
  });
  return {U, S, V};
}

// gA = U [ (skew(U^T gU) S + S skew(V^T gV)) / (s_k^2 - s_j^2) + diag(gS) ] V^T.
at::Tensor svd3x3_backward_cpu(const at::Tensor& gU_in, const at::Tensor& gS_in, const at::Tensor& gV_in,
                               const at::Tensor& U_in, const at::Tensor& S_in, const at::Tensor& V_in) {
  const at::Tensor gU = gU_in.contiguous(), gS = gS_in.contiguous(), gV = gV_in.contiguous();
  const at::Tensor U = U_in.contiguous(), S = S_in.contiguous(), V = V_in.contiguous();
  const int64_t B = U.size(0);
  at::Tensor gA = at::empty({B, 3, 3}, U.options());
  AT_DISPATCH_FLOATING_TYPES(U.scalar_type(), "svd3x3_backward_cpu", [&] {
    const scalar_t *gup = gU.const_data_ptr<scalar_t>(), *gsp = gS.const_data_ptr<scalar_t>();
    const scalar_t *gvp = gV.const_data_ptr<scalar_t>(), *up = U.const_data_ptr<scalar_t>();
    const scalar_t *sp = S.const_data_ptr<scalar_t>(), *vp = V.const_data_ptr<scalar_t>();
    scalar_t* gap = gA.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, B, 256, [&](int64_t begin, int64_t end) {
      for (int64_t b = begin; b < end; ++b) {
        const scalar_t *u = up + 9 * b, *v = vp + 9 * b, *gu = gup + 9 * b, *gv = gvp + 9 * b;
        const scalar_t *s = sp + 3 * b, *gs = gsp + 3 * b;
        double utgu[9], vtgv[9];
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) {
            double a = 0, c = 0;
            for (int r = 0; r < 3; ++r) {
              a += double(u[3 * r + i]) * gu[3 * r + j];
              c += double(v[3 * r + i]) * gv[3 * r + j];
            }
            utgu[3 * i + j] = a;
            vtgv[3 * i + j] = c;
          }
        const double eps = 1e-12 + 1e-9 * std::fabs(double(s[0]));
        double inner[9];
        for (int j = 0; j < 3; ++j)
          for (int k = 0; k < 3; ++k) {
            if (j == k) { inner[3 * j + k] = gs[j]; continue; }
            const double sk_u = (utgu[3 * j + k] - utgu[3 * k + j]) * s[k];
            const double sj_v = s[j] * (vtgv[3 * j + k] - vtgv[3 * k + j]);
            inner[3 * j + k] = (sk_u + sj_v) * damped_inverse(double(s[k]) - s[j], eps) *
                               damped_inverse(double(s[k]) + s[j], eps);
          }
        for (int i = 0; i < 3; ++i)
          for (int l = 0; l < 3; ++l) {
            double acc = 0;
            for (int j = 0; j < 3; ++j)
              for (int k = 0; k < 3; ++k) acc += double(u[3 * i + j]) * inner[3 * j + k] * v[3 * l + k];
            gap[9 * b + 3 * i + l] = acc;
          }
      }
    });
  });
  return gA;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("svd3x3", &svd3x3_cpu);
  m.impl("svd3x3_backward", &svd3x3_backward_cpu);
}

}  // namespace vrnet
