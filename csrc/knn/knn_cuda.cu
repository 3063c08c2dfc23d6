// Torch glue of the CUDA kNN op (kernels: knn_kernels.cuh). C = 3 with at least kGridMinRef
// reference points: the CPU's uniform grid (its box and edge read once per cloud: one host
// synchronisation), the points sorted by cell on the device, one thread per query searching it.
// Smaller C = 3 clouds: the tiled exact scan. float32 rows of 4 to 128 values with k <= 32 on GPUs with
// TF32 tensor cores: candidates from tensor-core products, ranked exactly and proven (knn_kernels.cuh).
// Otherwise rows of up to 128 floats (64 doubles) with k <= 32: the tiled exact scan. Larger C or k:
// cuBLAS dot products of the clouds centred on the reference mean, over bounded chunks (never the
// N x M matrix), merged into per-query candidate buffers, then re-ranked by exact distance with an
// exhaustive scan where the rounding of the expanded formula could matter (the CPU's definition).
// k > 64: bounded chunks of query rows, exact distances sorted (stable). Same results and
// tie-breaking (ascending distance, then lower index) as the CPU kernel.
#include <ATen/ops/amax.h>
#include <ATen/ops/amin.h>
#include <ATen/ops/bmm.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/where.h>
#include <ATen/ops/sub.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <limits>
#include <vector>

#include "common/cuda_utils.cuh"
#include "common/tensor_core.cuh"
#include "knn/knn.h"
#include "knn/knn_kernels.cuh"

namespace vrnet {
namespace {

constexpr int64_t kChunkElements = 8 << 20;  // dot-product chunk budget (B x queries x refs)

// Calls fn(std::integral_constant<int, KMAX>) with the smallest register buffer that holds k <= kLargest
// (8, 16, 32 or 64 slots; ptxas: no local memory up to 64).
template <int kLargest = kCudaRegisterK, typename Fn>
void dispatch_kmax(int64_t k, Fn&& fn) {
  static_assert(kCudaRegisterK == 64 && (kLargest == 32 || kLargest == 64), "the buffer sizes below end at 64");
  if (k <= 8) fn(std::integral_constant<int, 8>{});
  else if (k <= 16) fn(std::integral_constant<int, 16>{});
  else if (kLargest == 32 || k <= 32) fn(std::integral_constant<int, 32>{});
  else if constexpr (kLargest == 64) fn(std::integral_constant<int, 64>{});
}

LaunchConfig per_query(int64_t N, int64_t B) { return {dim3(blocks_for(N), static_cast<unsigned int>(B)), dim3(kThreads), 0}; }
// A warp per query row (knn_exact_rows_kernel).
LaunchConfig per_query_warp(int64_t N, int64_t B) {
  return {dim3(blocks_for(32 * N), static_cast<unsigned int>(B)), dim3(kThreads), 0};
}

// k > kCudaRegisterK: rows of queries in chunks of at most kChunkElements differences, exact squared
// distances, each row sorted (stable, so equal distances keep index order).
void knn_by_sorting(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self, at::Tensor& dist,
                    at::Tensor& idx) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  const int64_t rows = std::min<int64_t>(N, std::max<int64_t>(1, kChunkElements / (B * M * C)));
  for (int64_t q0 = 0; q0 < N; q0 += rows) {
    const int64_t count = std::min(rows, N - q0);
    const at::Tensor diff = query.narrow(1, q0, count).unsqueeze(2).sub(ref.unsqueeze(1));  // (B, n, M, C)
    // channel c into partial sum c % 8, the partials added pairwise: the CPU's squared_distance
    std::vector<at::Tensor> partial(8);
    for (int64_t c = 0; c < C; ++c) {
      const at::Tensor square = diff.select(-1, c).square();
      partial[c % 8] = partial[c % 8].defined() ? partial[c % 8].add(square) : square;
    }
    for (at::Tensor& p : partial)
      if (!p.defined()) p = at::zeros_like(partial[0]);
    at::Tensor d = partial[0].add(partial[1]).add(partial[2].add(partial[3]))
                       .add(partial[4].add(partial[5]).add(partial[6].add(partial[7])));
    if (exclude_self) d.diagonal(q0, 1, 2).fill_(std::numeric_limits<double>::infinity());
    const auto [sorted, order] = d.sort(/*stable=*/true, /*dim=*/-1, /*descending=*/false);
    dist.narrow(1, q0, count).copy_(sorted.narrow(-1, 0, k));
    idx.narrow(1, q0, count).copy_(order.narrow(-1, 0, k));
  }
}

constexpr int64_t kGridMinRef = 8192;  // C = 3 reference clouds of this size or more: the grid search

// One cloud (query (N, 3), ref (M, 3)) through the grid of knn/grid.h, laid out as the CPU lays it
// out: the robust box from the reference's quantiles (in double), the grid over the points inside
// it, the points sorted by cell (stable: as the CPU's counting sort), the far strays last.
template <typename scalar_t>
void knn_grid_one(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self, at::Tensor dist,
                  at::Tensor idx) {
  const int64_t N = query.size(0), M = ref.size(0);
  const at::Tensor points = ref.to(at::kDouble);
  const RobustRanks ranks(M);
  at::Tensor box_low, box_high;
  if (ranks.widen) {
    const at::Tensor sorted = std::get<0>(points.sort(/*dim=*/0, /*descending=*/false));
    const at::Tensor q_low = sorted.select(0, ranks.low), q_high = sorted.select(0, ranks.high);
    const at::Tensor margin = q_high.sub(q_low).mul(0.5);
    box_low = q_low.sub(margin), box_high = q_high.add(margin);
  } else {
    box_low = at::amin(points, 0), box_high = at::amax(points, 0);
  }
  const at::Tensor inside = points.ge(box_low).logical_and(points.le(box_high)).all(1).contiguous();
  const at::Tensor column = inside.unsqueeze(1);
  const double inf = std::numeric_limits<double>::infinity();
  const at::Tensor fetched = at::cat({at::where(column, points, inf).amin(0), at::where(column, points, -inf).amax(0),
                                      inside.sum().to(at::kDouble).reshape({1})}).cpu();
  const double* host = fetched.const_data_ptr<double>();
  const int64_t inliers = static_cast<int64_t>(host[6]);
  const GridShape grid = GridShape::fit(host, host + 3, inliers);
  at::Tensor cell = at::empty({M}, ref.options().dtype(at::kLong));
  launch<knn_grid_cells_kernel<scalar_t>>(per_item(M), ref, inside, M, grid, cell);
  const auto [sorted_cell, order] = cell.sort(/*stable=*/true, /*dim=*/0, /*descending=*/false);
  const at::Tensor start = at::searchsorted(sorted_cell, at::arange(grid.cells() + 1, cell.options())).contiguous();
  const at::Tensor xyz = ref.index_select(0, order).contiguous();
  dispatch_kmax(k, [&](auto kmax) {
    launch<knn_grid_kernel<scalar_t, decltype(kmax)::value>>(per_item(N), query, xyz, order.contiguous(), start,
                                                             inliers, grid, N, M, k, exclude_self, dist, idx);
  });
}

constexpr int64_t kTiledMaxK = 32;          // knn_tiled_kernel: register buffers up to 32 slots ...
constexpr int64_t kTiledMaxRowBytes = 512;  // ... and query rows of up to 128 floats / 64 doubles in registers

// C > 3 rows that fit in registers: the exact tiled scan with the smallest buffer and row that fit.
template <typename scalar_t>
void knn_tiled(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self, at::Tensor& dist,
               at::Tensor& idx) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  const auto run = [&](auto kmax, auto cmax) {
    launch<knn_tiled_kernel<scalar_t, decltype(kmax)::value, decltype(cmax)::value>>(
        per_query(N, B), query, ref, N, M, C, k, exclude_self, dist, idx);
  };
  const auto with_rows = [&](auto kmax) {
    if (C <= 32) run(kmax, std::integral_constant<int, 32>{});
    else if (C <= 64) run(kmax, std::integral_constant<int, 64>{});
    else if constexpr (sizeof(scalar_t) == 4) run(kmax, std::integral_constant<int, 128>{});
  };
  static_assert(kTiledMaxK == 32, "the register buffers below end at 32 slots");
  dispatch_kmax<32>(k, with_rows);
}

// float32 feature rows of up to kKnnTensorCoreMaxC values, k <= kKnnTensorCoreMaxK, on a GPU with TF32
// tensor cores: candidates by tensor-core products of the clouds centred on the reference mean, then
// their exact ranking, proven or replaced by an exhaustive scan (knn_kernels.cuh).
bool fits_tensor_cores(const at::Tensor& query, int64_t k) {
  const int64_t C = query.size(2);
  return query.scalar_type() == at::kFloat && C > 3 && C <= kKnnTensorCoreMaxC && k <= kKnnTensorCoreMaxK &&
         compute_capability_major() >= kTensorCoreMajor;
}

// query (B, N, C) and ref (B, M, C) less the reference cloud's mean (in float64, rounded to scalar_t), their
// squared norms (B, N), (B, M) and each cloud's largest reference norm (B): the centred clouds both
// approximate searches (GEMM chunks, tensor cores) take their dot products of.
struct CentredClouds {
  at::Tensor query, ref, query_norm, ref_norm, ref_norm_max;
};

template <typename scalar_t>
CentredClouds centre_on_reference(const at::Tensor& query, const at::Tensor& ref) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  at::Tensor mean = at::empty({B, C}, query.options().dtype(at::kDouble));
  launch<knn_mean_kernel<scalar_t>>(
      LaunchConfig{dim3(static_cast<unsigned int>(B), static_cast<unsigned int>((C + 31) / 32)),
                   dim3(32, kKnnMeanSlices), 0},
      ref, M, C, mean);
  CentredClouds out{at::empty_like(query), at::empty_like(ref), at::empty({B, N}, query.options()),
                    at::empty({B, M}, query.options()), at::Tensor()};
  launch<knn_centre_kernel<scalar_t>>(per_query(N, B), query, mean, N, C, out.query, out.query_norm);
  launch<knn_centre_kernel<scalar_t>>(per_query(M, B), ref, mean, M, C, out.ref, out.ref_norm);
  out.ref_norm_max = at::amax(out.ref_norm, 1).contiguous();
  return out;
}

// The tensor-core search up to its proof: dist, idx written for every row (proven or not); returns the
// rows (B, N) int32 whose ranking is not proven, which knn_exact_rows_kernel then scans whole.
at::Tensor knn_tensor_core_ranking(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self,
                                   at::Tensor& dist, at::Tensor& idx) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  const int64_t row_tiles = (N + kKnnTensorCoreRows - 1) / kKnnTensorCoreRows;
  TORCH_CHECK_VALUE(B * row_tiles < (int64_t{1} << 31), "knn: too many query rows (B * N = ", B * N, ")");
  const auto [query_c, ref_c, query_norm, ref_norm, ref_norm_max] = centre_on_reference<float>(query, ref);
  at::Tensor cand_dist = at::empty({B, N, kKnnRowCandidates}, query.options());
  at::Tensor cand_idx = at::empty({B, N, kKnnRowCandidates}, query.options().dtype(at::kInt));
  const LaunchConfig config{dim3(static_cast<unsigned int>(B * row_tiles)), dim3(kKnnTensorCoreWarps * 32),
                            sizeof(float) * static_cast<std::size_t>(knn_tensor_core_shared_floats(C))};
  launch<knn_tensor_core_kernel>(config, query_c, ref_c, query_norm, ref_norm, N, M, static_cast<int>(C),
                                 exclude_self, row_tiles, cand_dist, cand_idx);
  at::Tensor unproven = at::empty({B, N}, query.options().dtype(at::kInt));
  static_assert(kKnnTensorCoreMaxK == 32, "the register buffers below end at 32 slots");
  dispatch_kmax<32>(k, [&](auto kmax) {
    launch<knn_tensor_core_rerank_kernel<decltype(kmax)::value>>(per_query(N, B), query, ref, cand_dist, cand_idx,
                                                                 query_norm, ref_norm_max, N, M, C, k, dist, idx,
                                                                 unproven);
  });
  return unproven;
}

void knn_tensor_cores(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self, at::Tensor& dist,
                      at::Tensor& idx) {
  const at::Tensor unproven = knn_tensor_core_ranking(query, ref, k, exclude_self, dist, idx);
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  dispatch_kmax<32>(k, [&](auto kmax) {
    launch<knn_exact_rows_kernel<float, decltype(kmax)::value>>(per_query_warp(N, B), query, ref, unproven, N, M, C,
                                                                k, exclude_self, dist, idx);
  });
}

// Diagnostics: the rows (B, N) bool the tensor-core search would scan whole (see knn_tensor_core_ranking).
at::Tensor knn_unproven_rows_cuda(const at::Tensor& query_in, const at::Tensor& ref_in, int64_t k, bool exclude_self) {
  check_knn_inputs(query_in, ref_in, k, exclude_self);
  VRNET_CUDA_GUARD(query_in);
  const at::Tensor query = query_in.contiguous(), ref = ref_in.contiguous();
  TORCH_CHECK_VALUE(fits_tensor_cores(query, k), "knn_unproven_rows: the tensor-core search takes float32 rows of 4 ",
                    "to ", kKnnTensorCoreMaxC, " values and k <= ", kKnnTensorCoreMaxK,
                    " on a GPU of compute capability ", kTensorCoreMajor, ".0 or later");
  const int64_t B = query.size(0), N = query.size(1);
  at::Tensor dist = at::empty({B, N, k}, query.options());
  at::Tensor idx = at::empty({B, N, k}, query.options().dtype(at::kLong));
  if (B * N == 0) return at::empty({B, N}, query.options().dtype(at::kBool));
  return knn_tensor_core_ranking(query, ref, k, exclude_self, dist, idx).to(at::kBool);
}

template <typename scalar_t>
void knn_features(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self, at::Tensor& dist,
                  at::Tensor& idx) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  // Candidates kept per query before the exact re-ranking (a margin over k for near-ties).
  const int64_t width = std::min<int64_t>(kCudaRegisterK, std::max<int64_t>(k, 2 * k + 16));
  const scalar_t relative_error = static_cast<scalar_t>(8 * (C + 2)) * std::numeric_limits<scalar_t>::epsilon();
  const auto [query_c, ref_c, query_norm, ref_norm, ref_norm_max] = centre_on_reference<scalar_t>(query, ref);
  at::Tensor cand_dist = at::empty({B, N, width}, query.options());
  at::Tensor cand_idx = at::empty({B, N, width}, query.options().dtype(at::kLong));
  const int64_t query_chunk = std::min<int64_t>(N, std::max<int64_t>(1, kChunkElements / (B * std::min<int64_t>(M, 1024))));
  const int64_t ref_chunk = std::min<int64_t>(M, std::max<int64_t>(1, kChunkElements / (B * query_chunk)));
  dispatch_kmax(width, [&](auto kmax) {
    constexpr int KMAX = decltype(kmax)::value;
    for (int64_t q0 = 0; q0 < N; q0 += query_chunk) {
      const int64_t query_count = std::min(query_chunk, N - q0);
      const at::Tensor query_t = query_c.narrow(1, q0, query_count).transpose(1, 2);  // (B, C, n)
      for (int64_t r0 = 0; r0 < M; r0 += ref_chunk) {
        const int64_t ref_count = std::min(ref_chunk, M - r0);
        const at::Tensor dots = at::bmm(ref_c.narrow(1, r0, ref_count), query_t).contiguous();  // (B, m, n)
        launch<knn_chunk_kernel<scalar_t, KMAX>>(per_query(query_count, B), dots, query_norm, ref_norm, N, M, q0,
                                                 query_count, r0, ref_count, width, exclude_self, cand_dist,
                                                 cand_idx);
      }
    }
    at::Tensor exhaustive = at::empty({B, N}, query.options().dtype(at::kInt));
    launch<knn_rerank_kernel<scalar_t, KMAX>>(per_query(N, B), query, ref, cand_dist, cand_idx, query_norm,
                                              ref_norm_max, N, M, C, width, k, relative_error, dist, idx, exhaustive);
    launch<knn_exact_rows_kernel<scalar_t, KMAX>>(per_query_warp(N, B), query, ref, exhaustive, N, M, C, k,
                                                  exclude_self, dist, idx);
  });
}

std::tuple<at::Tensor, at::Tensor> knn_cuda(const at::Tensor& query_in, const at::Tensor& ref_in, int64_t k,
                                            bool exclude_self) {
  check_knn_inputs(query_in, ref_in, k, exclude_self);
  VRNET_CUDA_GUARD(query_in);
  const at::Tensor query = query_in.contiguous(), ref = ref_in.contiguous();
  if (device_values_checked()) check_on_device({finite_condition(query, "query"), finite_condition(ref, "ref")});
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  at::Tensor dist = at::empty({B, N, k}, query.options());
  at::Tensor idx = at::empty({B, N, k}, query.options().dtype(at::kLong));
  if (N == 0 || B == 0) return {dist, idx};
  if (k > kCudaRegisterK) {
    knn_by_sorting(query, ref, k, exclude_self, dist, idx);
    return {dist, idx};
  }
  if (fits_tensor_cores(query, k)) {
    knn_tensor_cores(query, ref, k, exclude_self, dist, idx);
    return {dist, idx};
  }
  AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "knn_cuda", [&] {
    if (C == 3 && M >= kGridMinRef) {
      for (int64_t b = 0; b < B; ++b)
        knn_grid_one<scalar_t>(query.select(0, b), ref.select(0, b), k, exclude_self, dist.select(0, b),
                               idx.select(0, b));
    } else if (C == 3) {
      dispatch_kmax(k, [&](auto kmax) {
        launch<knn3_kernel<scalar_t, decltype(kmax)::value>>(per_query(N, B), query, ref, N, M, k, exclude_self, dist,
                                                             idx);
      });
    } else if (k <= kTiledMaxK && C * static_cast<int64_t>(sizeof(scalar_t)) <= kTiledMaxRowBytes) {
      knn_tiled<scalar_t>(query, ref, k, exclude_self, dist, idx);
    } else {
      knn_features<scalar_t>(query, ref, k, exclude_self, dist, idx);
    }
  });
  return {dist, idx};
}

std::tuple<at::Tensor, at::Tensor> knn_backward_cuda(const at::Tensor& grad_in, const at::Tensor& query_in,
                                                     const at::Tensor& ref_in, const at::Tensor& idx_in) {
  check_knn_backward_inputs(grad_in, query_in, ref_in, idx_in);
  VRNET_CUDA_GUARD(query_in);
  const at::Tensor grad = grad_in.contiguous(), query = query_in.contiguous();
  const at::Tensor ref = ref_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2), k = idx.size(2);
  at::Tensor grad_query = at::zeros_like(query), grad_ref = at::zeros_like(ref);
  if (B * N == 0) return {grad_query, grad_ref};
  const Incidence inc = build_incidence(idx, M);
  AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "knn_backward_cuda", [&] {
    launch<knn_grad_query_kernel<scalar_t>>(per_item(B * N * C), grad, query, ref, idx, B, N, M, C, k, grad_query);
    launch<knn_grad_ref_kernel<scalar_t>>(per_item(B * M * C), grad, query, ref, inc.order, inc.row_ptr, B, N, M, C,
                                          k, grad_ref);
  });
  return {grad_query, grad_ref};
}

}  // namespace

VRNET_CUDA_IMPL(m) {
  m.impl("knn", &knn_cuda);
  m.impl("knn_backward", &knn_backward_cuda);
  m.impl("knn_unproven_rows", &knn_unproven_rows_cuda);
}

}  // namespace vrnet
