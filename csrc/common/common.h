// Shared helpers for the vrnet_ext kernels: argument checks that raise Python ValueError/TypeError
// naming the argument (one implementation for CPU and CUDA tensors), and the host/device marker
// for math shared by the CPU and CUDA kernels.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/aminmax.h>
#include <ATen/ops/cat.h>
#include <ATen/ops/isfinite.h>
#include <c10/util/Exception.h>

#include "common/host_device.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

namespace vrnet {

// Runs fn(task) for every task in [0, tasks) inside ONE parallel region; the threads claim tasks one
// at a time from a shared counter. A static split makes every thread wait at the join for the one
// whose core another process is using (10x slower kernels on a shared machine); with claiming,
// that thread simply does fewer tasks. Tasks must be independent.
template <typename F>
void parallel_tasks(int64_t tasks, const F& fn) {
  std::atomic<int64_t> next{0};
  at::parallel_for(0, std::min<int64_t>(tasks, at::get_num_threads()), 1, [&](int64_t, int64_t) {
    for (int64_t task = next++; task < tasks; task = next++) fn(task);
  });
}

// at::parallel_for's signature with parallel_tasks' scheduling: [0, total) is cut into chunks of at
// least `grain` items (about 8 per thread) that the threads claim one at a time; fn(begin, end)
// gets one chunk per call. Items must be independent (each kernel writes its own outputs).
template <typename F>
void parallel_ranges(int64_t total, int64_t grain, const F& fn) {
  if (total <= 0) return;
  const int64_t per_chunk = (total + 8 * at::get_num_threads() - 1) / (8 * at::get_num_threads());
  const int64_t chunk = std::max<int64_t>(std::max<int64_t>(grain, 1), per_chunk);
  const int64_t chunks = (total + chunk - 1) / chunk;
  parallel_tasks(chunks, [&](int64_t c) { fn(c * chunk, std::min(total, (c + 1) * chunk)); });
}

// Checks that read the values of tensors on an accelerator (NaN / Inf, index ranges, weights) are
// host synchronisations. vrnet_ext.ops.trusted_values() suspends them in its thread (this depth,
// set through vrnet_ext._C) for values that come from checked inputs through the ops. CPU tensors
// are always checked: no synchronisation there, and the CPU kernels' memory accesses rely on it.
inline int& value_checks_suspended() {
  static thread_local int depth = 0;
  return depth;
}

inline bool device_values_checked() { return value_checks_suspended() == 0; }

// Conditions computed on an accelerator (one-element bool tensors), fetched with ONE synchronisation;
// raises ValueError with the message of the first that is false. Callers build the conditions only
// when device_values_checked().
using DeviceCondition = std::pair<at::Tensor, std::string>;

inline void check_on_device(const std::vector<DeviceCondition>& conditions) {
  std::vector<at::Tensor> flags;
  for (const auto& condition : conditions) flags.push_back(condition.first.reshape({1}));
  const at::Tensor host = at::cat(flags).cpu();
  const bool* ok = host.const_data_ptr<bool>();
  for (size_t i = 0; i < conditions.size(); ++i) TORCH_CHECK_VALUE(ok[i], conditions[i].second);
}

// "every element of t is finite", for check_on_device.
inline DeviceCondition finite_condition(const at::Tensor& t, const char* name) {
  return {at::isfinite(t).all(), std::string(name) + " contains NaN or Inf values"};
}

// Raises ValueError (via TORCH_CHECK_VALUE) if any element of a floating tensor is NaN/Inf.
inline void check_finite(const at::Tensor& t, const char* name) {
  if (!t.is_cpu()) {
    if (device_values_checked()) check_on_device({finite_condition(t, name)});
    return;
  }
  const at::Tensor c = t.contiguous();
  std::atomic<bool> bad{false};
  AT_DISPATCH_FLOATING_TYPES(c.scalar_type(), "check_finite", [&] {
    const scalar_t* p = c.const_data_ptr<scalar_t>();
    parallel_ranges(c.numel(), 1 << 16, [&](int64_t begin, int64_t end) {
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

// Raises ValueError unless `t` lives on the device of `first` (kernels read both directly).
inline void check_same_device(const at::Tensor& first, const char* first_name, const at::Tensor& t,
                              const char* name) {
  TORCH_CHECK_VALUE(t.device() == first.device(), name, " is on ", t.device(), " but ", first_name, " is on ",
                    first.device());
}

inline void check_dim(const at::Tensor& t, int64_t dim, const char* name, const char* shape) {
  TORCH_CHECK_VALUE(t.dim() == dim, name, " must have shape ", shape, ", got ", t.sizes());
}

// Backward kernels are registered ops that anyone can call with any tensors: each checks that a
// gradient or saved tensor has exactly the expected sizes, the dtype and the device of `like`.
inline void check_like(const at::Tensor& t, const char* name, at::IntArrayRef sizes, const at::Tensor& like,
                       const char* like_name) {
  TORCH_CHECK_VALUE(t.sizes() == sizes, name, " must have shape ", sizes, ", got ", t.sizes());
  TORCH_CHECK_TYPE(t.scalar_type() == like.scalar_type(), name, " must have the dtype of ", like_name, " (",
                   like.scalar_type(), "), got ", t.scalar_type());
  check_same_device(like, like_name, t, name);
}

// Raises ValueError if an index tensor holds values outside [0, upper).
inline void check_index_range(const at::Tensor& idx, int64_t upper, const char* name) {
  if (!idx.is_cpu()) {
    if (idx.numel() == 0 || !device_values_checked()) return;
    const auto [lo, hi] = at::aminmax(idx);
    check_on_device({{lo.ge(0).logical_and(hi.lt(upper)),
                      std::string(name) + " holds indices outside [0, " + std::to_string(upper) + ")"}});
    return;
  }
  const at::Tensor c = idx.contiguous();
  const int64_t* p = c.const_data_ptr<int64_t>();
  std::atomic<bool> bad{false};
  parallel_ranges(c.numel(), 1 << 16, [&](int64_t begin, int64_t end) {
    bool local = false;
    for (int64_t i = begin; i < end; ++i) local |= (p[i] < 0) | (p[i] >= upper);
    if (local) bad.store(true, std::memory_order_relaxed);
  });
  TORCH_CHECK_VALUE(!bad.load(), name, " holds indices outside [0, ", upper, ")");
}

}  // namespace vrnet
