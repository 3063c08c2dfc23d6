// launch<kernel>(config, args...) under the CPU emulator: the arguments converted as on a GPU, the
// extents of the tensor arguments handed to the sanitizer, the kernel run by cuda_emu's runtime.
// Included by common/cuda_utils.cuh only when VRNET_CUDA_EMULATION is defined.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstddef>
#include <tuple>
#include <type_traits>
#include <utility>
#include <vector>

#include "common/kernel_args.h"
#include "cuda_emu/cuda_emu.h"

namespace vrnet {

inline cudaStream_t current_stream() { return nullptr; }
inline int compute_capability_major() { return 9; }  // the emulator runs what an sm_90 GPU runs

namespace emu {

// Memory a launch may touch: a tensor argument (read-only when the parameter points to const).
struct Extent {
  const void* base;
  std::size_t bytes;
  bool writable;
  int argument;
};

using Trampoline = void (*)(void* params);

// Runs kernel `name` (the compiler's spelling of the instantiation) over grid x block: pass 1 with
// the sanitizer in a seeded block order, pass 2 concurrently on restored tensors, then compares them.
// Raises c10::Error listing the findings, if any.
void launch_kernel(const char* name, Trampoline trampoline, void* params, std::size_t params_bytes, dim3 grid,
                   dim3 block, std::size_t shared_bytes, const std::vector<Extent>& extents);

template <auto Kernel>
const char* kernel_name() {
  return __PRETTY_FUNCTION__;
}

template <typename Param, typename Arg>
void add_extent(std::vector<Extent>& extents, int argument, const Arg& arg) {
  if constexpr (std::is_same_v<std::decay_t<Arg>, at::Tensor>) {
    if (!arg.defined() || arg.numel() == 0) return;
    int64_t last = 0;
    for (int64_t d = 0; d < arg.dim(); ++d) last += (arg.size(d) - 1) * arg.stride(d);
    extents.push_back({arg.data_ptr(), static_cast<std::size_t>(last + 1) * arg.element_size(),
                       !std::is_const_v<std::remove_pointer_t<Param>>, argument});
  } else {
    static_assert(!std::is_pointer_v<std::decay_t<Arg>>,
                  "pass tensors, not raw pointers, so that the emulator knows the memory's extent");
  }
}

}  // namespace emu

template <auto Kernel, typename Params, typename... Args, std::size_t... I>
void launch_indexed(const LaunchConfig& config, std::index_sequence<I...>, Args&&... args) {
  std::vector<emu::Extent> extents;
  (emu::add_extent<std::tuple_element_t<I, Params>>(extents, static_cast<int>(I), args), ...);
  Params params(launch_detail::convert<std::tuple_element_t<I, Params>>(std::forward<Args>(args))...);
  const emu::Trampoline trampoline = [](void* p) { std::apply(Kernel, *static_cast<Params*>(p)); };
  emu::launch_kernel(emu::kernel_name<Kernel>(), trampoline, &params, sizeof(params), config.grid, config.block,
                     config.shared_bytes, extents);
}

}  // namespace vrnet
