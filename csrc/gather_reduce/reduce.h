// The reductions of gather_reduce (free of torch includes: the CUDA kernel header uses it).
#pragma once

namespace vrnet {

enum class Reduce { kMax, kMin, kSum, kMean };

}  // namespace vrnet
