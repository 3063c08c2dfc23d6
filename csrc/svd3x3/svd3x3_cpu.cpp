// Batched 3x3 SVD (double internally) and its backward with damped 1/(s_k -+ s_l) terms.
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "common/common.h"
#include "svd3x3/svd3x3.h"

namespace vrnet {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> svd3x3_cpu(const at::Tensor& A_in) {
  check_svd3x3_input(A_in);
  const at::Tensor A = A_in.contiguous();
  check_finite(A, "A");
  const int64_t B = A.size(0);
  at::Tensor U = at::empty({B, 3, 3}, A.options()), V = at::empty({B, 3, 3}, A.options());
  at::Tensor S = at::empty({B, 3}, A.options());
  AT_DISPATCH_FLOATING_TYPES(A.scalar_type(), "svd3x3_cpu", [&] {
    const scalar_t* ap = A.const_data_ptr<scalar_t>();
    scalar_t *up = U.mutable_data_ptr<scalar_t>(), *sp = S.mutable_data_ptr<scalar_t>();
    scalar_t* vp = V.mutable_data_ptr<scalar_t>();
    parallel_ranges(B, 256, [&](int64_t begin, int64_t end) {
      for (int64_t b = begin; b < end; ++b) svd3x3_one(ap + 9 * b, up + 9 * b, sp + 3 * b, vp + 9 * b);
    });
  });
  return {U, S, V};
}

at::Tensor svd3x3_backward_cpu(const at::Tensor& gU_in, const at::Tensor& gS_in, const at::Tensor& gV_in,
                               const at::Tensor& U_in, const at::Tensor& S_in, const at::Tensor& V_in) {
  check_svd3x3_backward_inputs(gU_in, gS_in, gV_in, U_in, S_in, V_in);
  const at::Tensor gU = gU_in.contiguous(), gS = gS_in.contiguous(), gV = gV_in.contiguous();
  const at::Tensor U = U_in.contiguous(), S = S_in.contiguous(), V = V_in.contiguous();
  const int64_t B = U.size(0);
  at::Tensor gA = at::empty({B, 3, 3}, U.options());
  AT_DISPATCH_FLOATING_TYPES(U.scalar_type(), "svd3x3_backward_cpu", [&] {
    const scalar_t *gup = gU.const_data_ptr<scalar_t>(), *gsp = gS.const_data_ptr<scalar_t>();
    const scalar_t *gvp = gV.const_data_ptr<scalar_t>(), *up = U.const_data_ptr<scalar_t>();
    const scalar_t *sp = S.const_data_ptr<scalar_t>(), *vp = V.const_data_ptr<scalar_t>();
    scalar_t* gap = gA.mutable_data_ptr<scalar_t>();
    parallel_ranges(B, 256, [&](int64_t begin, int64_t end) {
      for (int64_t b = begin; b < end; ++b)
        svd3x3_backward_one(gup + 9 * b, gsp + 3 * b, gvp + 9 * b, up + 9 * b, sp + 3 * b, vp + 9 * b, gap + 9 * b);
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
