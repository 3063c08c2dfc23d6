// Fast Point Feature Histograms on the CPU (per point: fpfh/fpfh_math.h, shared with the CUDA
// kernel): pass 1 every point's SPFH, pass 2 every point's FPFH from its neighbours' SPFH. Each pass
// is one parallel region over points; memory O(N * 33).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "fpfh/fpfh.h"
#include "fpfh/fpfh_math.h"

namespace vrnet {
namespace {

at::Tensor fpfh_cpu(const at::Tensor& points_in, const at::Tensor& normals_in, const at::Tensor& idx_in,
                    const at::Tensor& dist2_in, double radius) {
  const FpfhInputs in = checked_fpfh_inputs(points_in, normals_in, idx_in, dist2_in, radius);
  const at::Tensor &points = in.points, &normals = in.normals, &idx = in.idx, &dist2 = in.dist2;
  const int64_t N = points.size(0), k = idx.size(1);
  at::Tensor out = at::empty({N, fpfh_detail::kFeatures}, points.options());
  at::Tensor spfh = at::empty({N, fpfh_detail::kFeatures}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "fpfh_cpu", [&] {
    using T = scalar_t;
    const T* p = points.const_data_ptr<T>();
    const T* n = normals.const_data_ptr<T>();
    const int64_t* nb = idx.const_data_ptr<int64_t>();
    const T* d2 = dist2.const_data_ptr<T>();
    const T r2 = static_cast<T>(radius * radius);
    T* h = spfh.mutable_data_ptr<T>();
    parallel_ranges(N, 64, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i)
        spfh_one(p, n, nb + i * k, d2 + i * k, i, k, r2, h + i * fpfh_detail::kFeatures);
    });
    T* o = out.mutable_data_ptr<T>();
    parallel_ranges(N, 64, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i)
        fpfh_one<T>(h, nb + i * k, d2 + i * k, i, k, r2, o + i * fpfh_detail::kFeatures);
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) { m.impl("fpfh", &fpfh_cpu); }

}  // namespace vrnet
