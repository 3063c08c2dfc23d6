// Launch geometry and the conversion of a launch's arguments to a kernel's parameters, shared by the
// nvcc launch (common/cuda_utils.cuh) and the emulated one (cuda_emu/launch.h).
#pragma once

#include <ATen/core/Tensor.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <tuple>
#include <type_traits>
#include <utility>

#include "common/cuda_device.cuh"

namespace vrnet {

inline unsigned int blocks_for(int64_t work, int threads = kThreads) {
  return static_cast<unsigned int>(std::max<int64_t>(1, (work + threads - 1) / threads));
}

struct LaunchConfig {
  dim3 grid;
  dim3 block;
  std::size_t shared_bytes = 0;
};

// One thread per item of `work`, `threads` per block.
inline LaunchConfig per_item(int64_t work, int threads = kThreads) {
  return {dim3(blocks_for(work, threads)), dim3(threads), 0};
}

namespace launch_detail {

template <typename Kernel>
struct KernelParams;
template <typename... Params>
struct KernelParams<void (*)(Params...)> {
  using type = std::tuple<Params...>;
};

// A tensor argument becomes the data pointer of the parameter's type (an undefined tensor: nullptr);
// anything else is passed on as it is.
template <typename Param, typename Arg>
Param convert(Arg&& arg) {
  if constexpr (std::is_same_v<std::decay_t<Arg>, at::Tensor>) {
    static_assert(std::is_pointer_v<Param>, "a tensor can only be passed for a pointer parameter");
    using Element = std::remove_pointer_t<Param>;
    using Plain = std::remove_const_t<Element>;
    if (!arg.defined()) return nullptr;
    if constexpr (std::is_arithmetic_v<Plain>) {
      if constexpr (std::is_const_v<Element>) return arg.template const_data_ptr<Plain>();
      else return arg.template mutable_data_ptr<Plain>();
    } else {  // a struct laid out in a buffer of plain numbers (e.g. doubles)
      TORCH_CHECK(arg.is_contiguous() && arg.nbytes() % sizeof(Plain) == 0,
                  "a buffer passed for a struct pointer must be contiguous and hold whole structs");
      return reinterpret_cast<Param>(arg.data_ptr());
    }
  } else {
    return static_cast<Param>(std::forward<Arg>(arg));
  }
}

}  // namespace launch_detail

// Launches Kernel with the arguments converted to its parameters (defined by cuda_utils.cuh for nvcc,
// by cuda_emu/launch.h for the emulator).
template <auto Kernel, typename Params, typename... Args, std::size_t... I>
void launch_indexed(const LaunchConfig& config, std::index_sequence<I...>, Args&&... args);

// `Kernel<<<config.grid, config.block, config.shared_bytes, stream>>>(args...)`, each at::Tensor
// argument passed as its data pointer.
template <auto Kernel, typename... Args>
void launch(const LaunchConfig& config, Args&&... args) {
  using Params = typename launch_detail::KernelParams<decltype(Kernel)>::type;
  static_assert(std::tuple_size_v<Params> == sizeof...(Args), "wrong number of kernel arguments");
  launch_indexed<Kernel, Params>(config, std::index_sequence_for<Args...>{}, std::forward<Args>(args)...);
}

}  // namespace vrnet
