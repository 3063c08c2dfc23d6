// Fused neighbour gather + reduction: out[b, c, n] = reduce_j values[b, c, idx[b, n, j]].
// For max/min the winning neighbour slot j is kept so backward routes the gradient to it.
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <limits>

#include "gather_reduce/gather_reduce.h"

namespace vrnet {
namespace {

// One (batch, channel) row per task; the reduction is a template parameter so every inner loop
// is specialised.
template <typename scalar_t, Reduce R>
void gather_reduce_rows(const scalar_t* vp, const int64_t* ip, scalar_t* op, int64_t* ap, int64_t B, int64_t C,
                        int64_t M, int64_t N, int64_t k) {
  parallel_ranges(B * C, 1, [&](int64_t begin, int64_t end) {
    for (int64_t bc = begin; bc < end; ++bc) {
      const scalar_t* row = vp + bc * M;
      const int64_t* ib = ip + (bc / C) * N * k;
      for (int64_t n = 0; n < N; ++n) {
        const int64_t* nb = ib + n * k;
        if constexpr (R == Reduce::kMax || R == Reduce::kMin) {
          // max/min compile to maxss/minss (no data-dependent branch); NaN is tracked on the side
          // and propagates like torch.max.
          scalar_t best_v = row[nb[0]];
          bool has_nan = best_v != best_v;
          for (int64_t j = 1; j < k; ++j) {
            const scalar_t v = row[nb[j]];
            best_v = R == Reduce::kMax ? std::max(best_v, v) : std::min(best_v, v);
            has_nan |= v != v;
          }
          int64_t best = 0;  // first neighbour slot holding the extreme (or the first NaN)
          if (has_nan) {
            best_v = std::numeric_limits<scalar_t>::quiet_NaN();
            while (row[nb[best]] == row[nb[best]]) ++best;
          } else {
            while (row[nb[best]] != best_v) ++best;
          }
          op[bc * N + n] = best_v;
          ap[bc * N + n] = best;
        } else {
          scalar_t acc = 0;
          for (int64_t j = 0; j < k; ++j) acc += row[nb[j]];
          op[bc * N + n] = R == Reduce::kMean ? acc / static_cast<scalar_t>(k) : acc;
        }
      }
    }
  });
}

std::tuple<at::Tensor, at::Tensor> gather_reduce_cpu(const at::Tensor& values_in, const at::Tensor& idx_in,
                                                     c10::string_view reduce_name) {
  const Reduce reduce = parse_reduce(reduce_name);
  check_gather_reduce_inputs(values_in, idx_in);
  const at::Tensor values = values_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = values.size(0), C = values.size(1), M = values.size(2);
  const int64_t N = idx.size(1), k = idx.size(2);
  const bool keep_arg = reduce == Reduce::kMax || reduce == Reduce::kMin;
  at::Tensor out = at::empty({B, C, N}, values.options());
  at::Tensor arg = at::empty({keep_arg ? B : 0, C, N}, values.options().dtype(at::kLong));
  AT_DISPATCH_FLOATING_TYPES(values.scalar_type(), "gather_reduce_cpu", [&] {
    const scalar_t* vp = values.const_data_ptr<scalar_t>();
    const int64_t* ip = idx.const_data_ptr<int64_t>();
    scalar_t* op = out.mutable_data_ptr<scalar_t>();
    int64_t* ap = keep_arg ? arg.mutable_data_ptr<int64_t>() : nullptr;
    switch (reduce) {
      case Reduce::kMax: gather_reduce_rows<scalar_t, Reduce::kMax>(vp, ip, op, ap, B, C, M, N, k); break;
      case Reduce::kMin: gather_reduce_rows<scalar_t, Reduce::kMin>(vp, ip, op, ap, B, C, M, N, k); break;
      case Reduce::kSum: gather_reduce_rows<scalar_t, Reduce::kSum>(vp, ip, op, ap, B, C, M, N, k); break;
      case Reduce::kMean: gather_reduce_rows<scalar_t, Reduce::kMean>(vp, ip, op, ap, B, C, M, N, k); break;
    }
  });
  return {out, arg};
}

at::Tensor gather_reduce_backward_cpu(const at::Tensor& grad_in, const at::Tensor& idx_in, const at::Tensor& arg_in,
                                      c10::string_view reduce_name, int64_t num_values) {
  const Reduce reduce = parse_reduce(reduce_name);
  check_gather_reduce_backward_inputs(grad_in, idx_in, arg_in, reduce, num_values);
  const at::Tensor grad = grad_in.contiguous(), idx = idx_in.contiguous(), arg = arg_in.contiguous();
  const int64_t B = grad.size(0), C = grad.size(1), N = grad.size(2), M = num_values, k = idx.size(2);
  at::Tensor grad_values = at::zeros({B, C, M}, grad.options());
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "gather_reduce_backward_cpu", [&] {
    const scalar_t* gp = grad.const_data_ptr<scalar_t>();
    const int64_t* ip = idx.const_data_ptr<int64_t>();
    const bool keep_arg = reduce == Reduce::kMax || reduce == Reduce::kMin;
    const int64_t* ap = keep_arg ? arg.const_data_ptr<int64_t>() : nullptr;
    scalar_t* gv = grad_values.mutable_data_ptr<scalar_t>();
    const scalar_t scale = reduce == Reduce::kMean ? scalar_t(1) / static_cast<scalar_t>(k) : scalar_t(1);
    // One task per (batch, channel) row: the scatter has no races and a fixed order.
    parallel_ranges(B * C, 1, [&](int64_t begin, int64_t end) {
      for (int64_t bc = begin; bc < end; ++bc) {
        const int64_t* ib = ip + (bc / C) * N * k;
        scalar_t* row = gv + bc * M;
        for (int64_t n = 0; n < N; ++n) {
          const scalar_t g = gp[bc * N + n];
          if (ap) {
            row[ib[n * k + ap[bc * N + n]]] += g;
          } else {
            for (int64_t j = 0; j < k; ++j) row[ib[n * k + j]] += g * scale;
          }
        }
      }
    });
  });
  return grad_values;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("gather_reduce", &gather_reduce_cpu);
  m.impl("gather_reduce_backward", &gather_reduce_backward_cpu);
}

}  // namespace vrnet
