// Robust rigid fit of putative correspondences by spatial consistency (the idea of SC^2-PCR, Chen et
// al. 2022): two correspondences (p_i, q_i), (p_j, q_j) are compatible when the distances they span
// agree, | |p_i - p_j| - |q_i - q_j| | < tolerance. Inliers of the true motion are all compatible
// with each other; outliers rarely are.
//
//   1. The compatibility graph as a bitset (K rows of ceil(K / 64) words; K^2 / 8 bytes).
//   2. Seeds: the correspondences of highest degree, none within `tolerance` (source side) of a seed
//      already chosen.
//   3. Per seed, the second-order score of each compatible j: how many correspondences are compatible
//      with both the seed and j (a popcount of two rows ANDed). The seed and its `consensus`
//      best-scored neighbours give a Kabsch fit; a fit scores the correspondences it maps within
//      `inlier_threshold`.
//   4. The best fit (most inliers; ties: the earlier seed) is refitted on its inliers until the
//      count stops growing.
// Deterministic: seeds in parallel, the best picked in seed order.
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <vector>

#include "kabsch/procrustes.h"
#include "spatial_consistency/spatial_consistency.h"

namespace vrnet {
namespace {

struct Graph {
  int64_t K, words;
  std::vector<uint64_t> bits;  // row i: bits[i * words, (i + 1) * words)

  const uint64_t* row(int64_t i) const { return bits.data() + i * words; }
  bool test(int64_t i, int64_t j) const { return (row(i)[j >> 6] >> (j & 63)) & 1u; }
};

double distance(const double* a, const double* b) {
  const double dx = a[0] - b[0], dy = a[1] - b[1], dz = a[2] - b[2];
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

// | |p_i - p_j| - |q_i - q_j| | < tolerance without square roots (so that the loop vectorises): with
// a, b the squared distances and s = a + b - tolerance^2, it holds iff s < 0 or s^2 < 4 a b.
Graph compatibility(const double* p, const double* q, int64_t K, double tolerance) {
  Graph g{K, (K + 63) / 64, {}};
  g.bits.assign(static_cast<size_t>(K * g.words), 0);
  std::vector<double> coords(6 * K);  // px, py, pz, qx, qy, qz: one array each
  for (int64_t k = 0; k < K; ++k)
    for (int a = 0; a < 3; ++a) {
      coords[a * K + k] = p[3 * k + a];
      coords[(3 + a) * K + k] = q[3 * k + a];
    }
  const double *px = coords.data(), *py = px + K, *pz = py + K, *qx = pz + K, *qy = qx + K, *qz = qy + K;
  const double t2 = tolerance * tolerance;
  parallel_ranges(K, 64, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      uint64_t* row = g.bits.data() + i * g.words;
      for (int64_t w = 0; w < g.words; ++w) {
        const int64_t j0 = 64 * w, count = std::min<int64_t>(64, K - j0);
        uint64_t bits = 0;
        for (int64_t l = 0; l < count; ++l) {
          const int64_t j = j0 + l;
          const double dpx = px[j] - px[i], dpy = py[j] - py[i], dpz = pz[j] - pz[i];
          const double dqx = qx[j] - qx[i], dqy = qy[j] - qy[i], dqz = qz[j] - qz[i];
          const double a = dpx * dpx + dpy * dpy + dpz * dpz, b = dqx * dqx + dqy * dqy + dqz * dqz;
          const double s = a + b - t2;
          bits |= static_cast<uint64_t>((s < 0) | (s * s < 4 * a * b)) << l;
        }
        row[w] = bits;
      }
      row[i >> 6] &= ~(uint64_t{1} << (i & 63));
    }
  });
  return g;
}

int64_t popcount_and(const uint64_t* a, const uint64_t* b, int64_t words) {
  int64_t count = 0;
  for (int64_t w = 0; w < words; ++w) count += __builtin_popcountll(a[w] & b[w]);
  return count;
}

struct Fit {
  double R[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1}, t[3] = {0, 0, 0};
  int64_t inliers = -1;
};

// Unweighted Kabsch on the listed correspondences (the solve of the kabsch op, in double).
Fit kabsch_on(const double* p, const double* q, const std::vector<int64_t>& members) {
  Procrustes s;
  s.wsum = static_cast<double>(members.size());
  for (int64_t m : members)
    for (int a = 0; a < 3; ++a) {
      s.src_c[a] += p[3 * m + a] / s.wsum;
      s.tgt_c[a] += q[3 * m + a] / s.wsum;
    }
  for (int64_t m : members)
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c) s.H[3 * a + c] += (p[3 * m + a] - s.src_c[a]) * (q[3 * m + c] - s.tgt_c[c]) / s.wsum;
  s.solve_rotation();
  Fit fit;
  s.write(fit.R, fit.t);
  return fit;
}

// Indices of the correspondences the fit maps within `threshold` of their target.
std::vector<int64_t> inliers_of(const Fit& fit, const double* p, const double* q, int64_t K, double threshold) {
  std::vector<int64_t> out;
  for (int64_t k = 0; k < K; ++k) {
    double r2 = 0;
    for (int a = 0; a < 3; ++a) {
      const double moved = fit.R[3 * a] * p[3 * k] + fit.R[3 * a + 1] * p[3 * k + 1] + fit.R[3 * a + 2] * p[3 * k + 2] +
                           fit.t[a];
      r2 += (moved - q[3 * k + a]) * (moved - q[3 * k + a]);
    }
    if (r2 < threshold * threshold) out.push_back(k);
  }
  return out;
}

std::vector<int64_t> choose_seeds(const Graph& g, const double* p, int64_t wanted, double tolerance) {
  std::vector<int64_t> degree(g.K), order(g.K);
  for (int64_t i = 0; i < g.K; ++i) degree[i] = popcount_and(g.row(i), g.row(i), g.words);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return degree[a] > degree[b]; });
  std::vector<int64_t> seeds;
  for (int64_t i : order) {
    if (static_cast<int64_t>(seeds.size()) >= wanted || degree[i] < 2) break;
    const bool near = std::any_of(seeds.begin(), seeds.end(), [&](int64_t s) { return distance(p + 3 * i, p + 3 * s) < tolerance; });
    if (!near) seeds.push_back(i);
  }
  return seeds;
}

// The seed and its `consensus` compatible neighbours of highest second-order score (ties: lower index).
std::vector<int64_t> consensus_of(const Graph& g, int64_t seed, int64_t consensus) {
  std::vector<std::pair<int64_t, int64_t>> scored;  // (-score, j)
  const uint64_t* row = g.row(seed);
  for (int64_t j = 0; j < g.K; ++j)
    if (g.test(seed, j)) scored.emplace_back(-popcount_and(row, g.row(j), g.words), j);
  const size_t keep = std::min<size_t>(scored.size(), static_cast<size_t>(consensus));
  std::partial_sort(scored.begin(), scored.begin() + keep, scored.end());
  std::vector<int64_t> members{seed};
  for (size_t i = 0; i < keep; ++i) members.push_back(scored[i].second);
  return members;
}

std::tuple<at::Tensor, at::Tensor> spatial_consistency_cpu(const at::Tensor& src_in, const at::Tensor& tgt_in,
                                                           double tolerance, double inlier_threshold, int64_t seeds,
                                                           int64_t consensus) {
  check_spatial_consistency_inputs(src_in, tgt_in, tolerance, inlier_threshold, seeds, consensus);
  const at::Tensor src = src_in.contiguous(), tgt = tgt_in.contiguous();
  check_finite(src, "src");
  check_finite(tgt, "tgt");
  const int64_t K = src.size(0);
  const double *p = src.const_data_ptr<double>(), *q = tgt.const_data_ptr<double>();
  const Graph graph = compatibility(p, q, K, tolerance);
  const std::vector<int64_t> chosen = choose_seeds(graph, p, seeds, tolerance);
  std::vector<Fit> fits(chosen.size());
  parallel_tasks(static_cast<int64_t>(chosen.size()), [&](int64_t s) {
    const std::vector<int64_t> members = consensus_of(graph, chosen[s], consensus);
    if (members.size() < 3) return;
    fits[s] = kabsch_on(p, q, members);
    fits[s].inliers = static_cast<int64_t>(inliers_of(fits[s], p, q, K, inlier_threshold).size());
  });
  Fit best;
  for (const Fit& fit : fits)
    if (fit.inliers > best.inliers) best = fit;
  std::vector<int64_t> members = best.inliers >= 3 ? inliers_of(best, p, q, K, inlier_threshold) : std::vector<int64_t>{};
  for (int round = 0; round < 10 && members.size() >= 3; ++round) {  // refit on the inliers while they grow
    Fit refit = kabsch_on(p, q, members);
    std::vector<int64_t> grown = inliers_of(refit, p, q, K, inlier_threshold);
    if (grown.size() < members.size()) break;
    const bool same = grown == members;
    best = refit;
    members.swap(grown);
    if (same) break;
  }
  at::Tensor transform = at::zeros({4, 4}, src.options());
  at::Tensor mask = at::zeros({K}, src.options().dtype(at::kBool));
  double* T = transform.mutable_data_ptr<double>();
  for (int a = 0; a < 3; ++a) {
    for (int c = 0; c < 3; ++c) T[4 * a + c] = best.R[3 * a + c];
    T[4 * a + 3] = best.t[a];
  }
  T[15] = 1;
  bool* m = mask.mutable_data_ptr<bool>();
  for (int64_t k : members) m[k] = true;
  return {transform, mask};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) { m.impl("spatial_consistency", &spatial_consistency_cpu); }

}  // namespace vrnet
