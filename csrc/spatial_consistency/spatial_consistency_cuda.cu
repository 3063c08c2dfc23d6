// Torch glue of the CUDA spatial_consistency op (kernels: spatial_consistency_kernels.cuh). No host
// synchronisation but the finite-input check (skipped inside vrnet_ext.ops.trusted_values()): the
// graph's precision is chosen on the device, the correspondences are ordered by degree and each
// seed's neighbours picked by torch's sort and top-k on the device.
#include <ATen/ops/empty.h>
#include <ATen/ops/topk.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "spatial_consistency/spatial_consistency.h"
#include "spatial_consistency/spatial_consistency_kernels.cuh"

namespace vrnet {
namespace {

LaunchConfig one_block() { return {dim3(1), dim3(kScThreads), 0}; }

std::tuple<at::Tensor, at::Tensor> spatial_consistency_cuda(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                            double tolerance, double inlier_threshold, int64_t seeds,
                                                            int64_t consensus) {
  check_spatial_consistency_inputs(src_in, tgt_in, tolerance, inlier_threshold, seeds, consensus);
  VRNET_CUDA_GUARD(src_in);
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous();
  if (device_values_checked()) check_on_device({finite_condition(src, "src"), finite_condition(tgt, "tgt")});
  const int64_t K = src.size(0), words = (K + 63) / 64;
  const int64_t S = std::min(seeds, K), top = std::min(consensus, K);  // a seed is a correspondence
  const at::TensorOptions longs = src.options().dtype(at::kLong);

  at::Tensor cols_d = at::empty({6 * K}, src.options()), cols_f = at::empty({6 * K}, src.options().dtype(at::kFloat));
  launch<sc_columns_kernel>(per_item(K), src, tgt, K, cols_d, cols_f);
  const auto [low, high] = at::aminmax(at::cat({src, tgt}, 1), 0);
  const at::Tensor in_float = high.sub(low).max().le(kFloatGraphExtent * tolerance);

  at::Tensor graph = at::empty({K, words}, longs), degree = at::empty({K}, longs);
  launch<sc_graph_kernel>(per_item(K * words), cols_d, cols_f, in_float, K, words, tolerance, graph);
  launch<sc_degree_kernel>(per_item(K), graph, K, words, degree);
  const at::Tensor order = std::get<1>(degree.sort(/*stable=*/true, /*dim=*/0, /*descending=*/true)).contiguous();

  at::Tensor chosen = at::empty({S}, longs), chosen_count = at::empty({1}, longs);
  launch<sc_seeds_kernel>(one_block(), src, order, degree, K, S, tolerance, chosen, chosen_count);
  at::Tensor keys = at::empty({S, K}, longs);
  launch<sc_scores_kernel>(LaunchConfig{dim3(static_cast<unsigned int>(S)), dim3(kScThreads), 0}, graph, chosen,
                           chosen_count, K, words, keys);
  const at::Tensor top_keys = std::get<0>(keys.topk(top, /*dim=*/1, /*largest=*/true, /*sorted=*/true)).contiguous();

  at::Tensor fits = at::empty({S, kFitDoubles}, src.options()), fit_ok = at::empty({S}, longs);
  launch<sc_fits_kernel>(per_item(S, 128), src, tgt, chosen, chosen_count, top_keys, S, top, fits, fit_ok);
  at::Tensor counts = at::zeros({S}, longs);
  launch<sc_count_kernel>(LaunchConfig{dim3(blocks_for(K), static_cast<unsigned int>(S)), dim3(kThreads), 0}, cols_d,
                          fits, fit_ok, K, inlier_threshold * inlier_threshold, counts);

  at::Tensor transform = at::empty({4, 4}, src.options()), mask = at::empty({K}, src.options().dtype(at::kBool));
  launch<sc_refine_kernel>(one_block(), cols_d, fits, fit_ok, counts, S, K, words,
                           inlier_threshold * inlier_threshold, transform, mask);
  return {transform, mask};
}

}  // namespace

VRNET_CUDA_IMPL(m) { m.impl("spatial_consistency", &spatial_consistency_cuda); }

}  // namespace vrnet
