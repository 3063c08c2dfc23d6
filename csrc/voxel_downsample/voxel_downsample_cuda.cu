// Torch glue of the CUDA voxel_downsample op (kernels: voxel_downsample_kernels.cuh). One host
// synchronisation reads the checks (finite points, cells in range) and the largest cell; the number
// of voxels is a second (the output's size).
#include <ATen/ops/amax.h>
#include <ATen/ops/amin.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/nonzero.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "voxel_downsample/voxel_downsample.h"
#include "voxel_downsample/voxel_downsample_kernels.cuh"

namespace vrnet {
namespace {

// The points in lexicographic cell order, each cell's points in input order (N,).
at::Tensor cell_order(const at::Tensor& cells, int64_t largest_cell) {
  const int64_t N = cells.size(0);
  if (largest_cell < (int64_t{1} << kPackedCellBits)) {
    at::Tensor keys = at::empty({N}, cells.options());
    launch<voxel_keys_kernel>(per_item(N), cells, N, keys);
    return std::get<1>(keys.sort(/*stable=*/true, /*dim=*/0, /*descending=*/false));
  }
  at::Tensor order = at::arange(N, cells.options());
  for (int64_t axis = 2; axis >= 0; --axis) {  // least significant first: stable sorts keep the later axes' order
    const at::Tensor column = cells.select(1, axis).index_select(0, order);
    order = order.index_select(0, std::get<1>(column.sort(/*stable=*/true, /*dim=*/0, /*descending=*/false)));
  }
  return order;
}

at::Tensor voxel_downsample_cuda(const at::Tensor& points_in, double voxel_size) {
  check_voxel_downsample_inputs(points_in, voxel_size);
  VRNET_CUDA_GUARD(points_in);
  const at::Tensor points = points_in.contiguous();
  const int64_t N = points.size(0);
  const at::Tensor low = at::amin(points, 0);
  at::Tensor cells = at::empty({N, 3}, points.options().dtype(at::kLong));
  at::Tensor too_far = at::zeros({1}, points.options().dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "voxel_cells_cuda", [&] {
    launch<voxel_cells_kernel<scalar_t>>(per_item(N), points, low, N, voxel_size, kMaxCell, cells, too_far);
  });
  const at::Tensor checks = at::cat({at::isfinite(points).all().reshape({1}).to(at::kLong), too_far.to(at::kLong),
                                     at::amax(cells).reshape({1})}).cpu();
  const int64_t* host = checks.const_data_ptr<int64_t>();
  TORCH_CHECK_VALUE(host[0], "points contains NaN or Inf values");
  TORCH_CHECK_VALUE(!host[1], "voxel_size ", voxel_size,
                    " is too small for this cloud (more than 2^62 voxels along an axis)");
  const at::Tensor order = cell_order(cells, host[2]).contiguous();
  at::Tensor first = at::empty({N}, points.options().dtype(at::kBool));
  launch<voxel_firsts_kernel>(per_item(N), cells, order, N, first);
  const at::Tensor begins = at::nonzero(first).reshape({-1}).contiguous();
  const int64_t V = begins.size(0);
  at::Tensor out = at::empty({V, 3}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "voxel_means_cuda", [&] {
    launch<voxel_means_kernel<scalar_t>>(per_item(V), points, order, begins, N, V, out);
  });
  return out;
}

}  // namespace

VRNET_CUDA_IMPL(m) { m.impl("voxel_downsample", &voxel_downsample_cuda); }

}  // namespace vrnet
