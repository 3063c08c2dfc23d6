// Shared helpers for the vrnet_ext CPU kernels: argument checks that raise Python
// ValueError/TypeError naming the argument, and a parallel finiteness scan.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <c10/util/Exception.h>

#include <atomic>
#include <cmath>
#include <cstdint>

namespace vrnet {

// Raises ValueError (via TORCH_CHECK_VALUE) if any element of a floating tensor is NaN/Inf.
inline void check_finite(const at::Tensor& t, const char* name) {
  const at::Tensor c = t.contiguous();
  std::atomic<bool> bad{false};
  AT_DISPATCH_FLOATING_TYPES(c.scalar_type(), "check_finite", [&] {
    const scalar_t* p = c.const_data_ptr<scalar_t>();
    at::parallel_for(0, c.numel(), 1 << 16, [&](int64_t begin, int64_t end) {
      bool local = false;
      for (int64_t i = begin; i < end; ++i) local |= !std::isfinite(p[i]);
      if (local) bad.store(true, std::memory_order_relaxed);
    });
  });
  TORCH_CHECK_VALUE(!bad.load(), name, " contains NaN or Inf values");
}

inline void check_float(const at::Tensor& t, const char* name) {
  TORCH_CHECK_TYPE(t.scalar_type() == at::kFloat || t.scalar_type() == at::kDouble, name,
                   " must be float32 or float64, got ", t.scalar_type());
}

inline void check_index(const at::Tensor& t, const char* name) {
  TORCH_CHECK_TYPE(t.scalar_type() == at::kLong, name, " must be int64, got ", t.scalar_type());
}

inline void check_dim(const at::Tensor& t, int64_t dim, const char* name, const char* shape) {
  TORCH_CHECK_VALUE(t.dim() == dim, name, " must have shape ", shape, ", got ", t.sizes());
}

// Raises ValueError if an index tensor holds values outside [0, upper).
inline void check_index_range(const at::Tensor& idx, int64_t upper, const char* name) {
  const at::Tensor c = idx.contiguous();
  const int64_t* p = c.const_data_ptr<int64_t>();
  std::atomic<bool> bad{false};
  at::parallel_for(0, c.numel(), 1 << 16, [&](int64_t begin, int64_t end) {
    bool local = false;
    for (int64_t i = begin; i < end; ++i) local |= (p[i] < 0) | (p[i] >= upper);
    if (local) bad.store(true, std::memory_order_relaxed);
  });
  TORCH_CHECK_VALUE(!bad.load(), name, " holds indices outside [0, ", upper, ")");
}

}  // namespace vrnet
