// Voxel downsampling: the mean of the points in each occupied voxel of edge voxel_size, voxels
// counted from the cloud's minimum corner, rows in lexicographic (x, y, z) voxel order (the order of
// the reference's torch.unique). One pass over the points with an open-addressing hash table of
// the voxel coordinates (O(N) memory, sums in double in point order), then the V occupied voxels
// sorted. Cell coordinates are computed in the points' dtype, as the reference does.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "voxel_downsample/voxel_downsample.h"

namespace vrnet {
namespace {

inline uint64_t mix(uint64_t h) {  // splitmix64's finaliser
  h ^= h >> 30;
  h *= 0xbf58476d1ce4e5b9ULL;
  h ^= h >> 27;
  h *= 0x94d049bb133111ebULL;
  return h ^ (h >> 31);
}

template <typename scalar_t>
at::Tensor downsample(const at::Tensor& points, double voxel_size) {
  const int64_t N = points.size(0);
  const scalar_t* p = points.const_data_ptr<scalar_t>();
  // One serial pass finds the minimum corner and checks finiteness (no parallel region: the op is
  // serial, and a region's join costs a time slice beside a busy process).
  scalar_t low[3] = {p[0], p[1], p[2]};
  bool finite = true;
  for (int64_t i = 0; i < N; ++i)
    for (int a = 0; a < 3; ++a) {
      finite &= std::isfinite(p[3 * i + a]);
      low[a] = std::min(low[a], p[3 * i + a]);
    }
  TORCH_CHECK_VALUE(finite, "points contains NaN or Inf values");
  const scalar_t size = static_cast<scalar_t>(voxel_size);
  int64_t capacity = 16;
  while (capacity < 2 * N) capacity <<= 1;
  std::vector<int64_t> slots(capacity, -1);
  std::vector<int64_t> cells;  // 3 per occupied voxel
  std::vector<double> sums;    // 3 per occupied voxel
  std::vector<int64_t> counts;
  for (int64_t i = 0; i < N; ++i) {
    int64_t c[3];
    for (int a = 0; a < 3; ++a) {
      const double cell = std::floor(static_cast<double>((p[3 * i + a] - low[a]) / size));
      TORCH_CHECK_VALUE(cell < kMaxCell, "voxel_size ", voxel_size,
                        " is too small for this cloud (more than 2^62 voxels along an axis)");
      c[a] = static_cast<int64_t>(cell);
    }
    uint64_t slot = mix(mix(mix(static_cast<uint64_t>(c[0])) ^ static_cast<uint64_t>(c[1])) ^
                        static_cast<uint64_t>(c[2])) & static_cast<uint64_t>(capacity - 1);
    int64_t voxel;
    while (true) {
      voxel = slots[slot];
      if (voxel < 0) {
        voxel = static_cast<int64_t>(counts.size());
        slots[slot] = voxel;
        cells.insert(cells.end(), c, c + 3);
        sums.insert(sums.end(), 3, 0.0);
        counts.push_back(0);
        break;
      }
      if (cells[3 * voxel] == c[0] && cells[3 * voxel + 1] == c[1] && cells[3 * voxel + 2] == c[2]) break;
      slot = (slot + 1) & static_cast<uint64_t>(capacity - 1);
    }
    for (int a = 0; a < 3; ++a) sums[3 * voxel + a] += static_cast<double>(p[3 * i + a]);
    ++counts[voxel];
  }
  const int64_t V = static_cast<int64_t>(counts.size());
  std::vector<int64_t> order(V);
  for (int64_t v = 0; v < V; ++v) order[v] = v;
  std::sort(order.begin(), order.end(), [&](int64_t x, int64_t y) {
    return std::lexicographical_compare(&cells[3 * x], &cells[3 * x + 3], &cells[3 * y], &cells[3 * y + 3]);
  });
  at::Tensor out = at::empty({V, 3}, points.options());
  scalar_t* o = out.mutable_data_ptr<scalar_t>();
  for (int64_t r = 0; r < V; ++r)
    for (int a = 0; a < 3; ++a)
      o[3 * r + a] = static_cast<scalar_t>(sums[3 * order[r] + a] / static_cast<double>(counts[order[r]]));
  return out;
}

at::Tensor voxel_downsample_cpu(const at::Tensor& points_in, double voxel_size) {
  check_voxel_downsample_inputs(points_in, voxel_size);
  const at::Tensor points = points_in.contiguous();
  at::Tensor out;
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "voxel_downsample_cpu",
                             [&] { out = downsample<scalar_t>(points, voxel_size); });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) { m.impl("voxel_downsample", &voxel_downsample_cpu); }

}  // namespace vrnet
