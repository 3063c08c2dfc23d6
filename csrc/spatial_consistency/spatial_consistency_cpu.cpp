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
//
// On x86-64 CPUs with AVX-512 the graph's rows are built 8 pairs per instruction and the popcounts
// use the POPCNT instruction (chosen at run time; the package is built without -march flags). The
// vector test performs the scalar test's operations in the same order (no FMA contraction), so
// both give the same bits (tests/test_spatial_consistency.py runs both).
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <numeric>
#include <string>
#include <vector>

#include "kabsch/procrustes.h"
#include "spatial_consistency/spatial_consistency.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define VRNET_X86_DISPATCH 1
#endif

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

// Coordinates of the correspondences, one array per axis (px, py, pz, qx, qy, qz), for the graph.
struct Columns {
  std::vector<double> data;
  const double *px, *py, *pz, *qx, *qy, *qz;
  Columns(const double* p, const double* q, int64_t K) : data(6 * K) {
    for (int64_t k = 0; k < K; ++k)
      for (int a = 0; a < 3; ++a) {
        data[a * K + k] = p[3 * k + a];
        data[(3 + a) * K + k] = q[3 * k + a];
      }
    px = data.data(), py = px + K, pz = py + K, qx = pz + K, qy = qx + K, qz = qy + K;
  }
  Columns(const Columns&) = delete;  // the pointers point into this object's own vector
  Columns& operator=(const Columns&) = delete;
};

// | |p_i - p_j| - |q_i - q_j| | < tolerance without square roots: with a, b the squared distances
// and s = a + b - tolerance^2, it holds iff s < 0 or s^2 < 4 a b. Bits of correspondences
// [j0, j0 + count) compatible with i.
uint64_t compatible_word(const Columns& c, int64_t i, int64_t j0, int64_t count, double t2) {
  uint64_t bits = 0;
  for (int64_t l = 0; l < count; ++l) {
    const int64_t j = j0 + l;
    const double dpx = c.px[j] - c.px[i], dpy = c.py[j] - c.py[i], dpz = c.pz[j] - c.pz[i];
    const double dqx = c.qx[j] - c.qx[i], dqy = c.qy[j] - c.qy[i], dqz = c.qz[j] - c.qz[i];
    const double a = dpx * dpx + dpy * dpy + dpz * dpz, b = dqx * dqx + dqy * dqy + dqz * dqz;
    const double s = a + b - t2;
    bits |= static_cast<uint64_t>((s < 0) | (s * s < 4 * a * b)) << l;
  }
  return bits;
}

void compatible_rows(const Columns& c, int64_t K, int64_t words, int64_t begin, int64_t end, double t2,
                     uint64_t* bits) {
  for (int64_t i = begin; i < end; ++i)
    for (int64_t w = 0; w < words; ++w)
      bits[i * words + w] = compatible_word(c, i, 64 * w, std::min<int64_t>(64, K - 64 * w), t2);
}

#ifdef VRNET_X86_DISPATCH
__attribute__((target("avx512f"))) void compatible_rows_avx512(const Columns& c, int64_t K, int64_t words,
                                                               int64_t begin, int64_t end, double t2,
                                                               uint64_t* bits) {
  const __m512d tol2 = _mm512_set1_pd(t2), zero = _mm512_setzero_pd(), four = _mm512_set1_pd(4.0);
  const int64_t full = K / 64;
  for (int64_t i = begin; i < end; ++i) {
    const __m512d pxi = _mm512_set1_pd(c.px[i]), pyi = _mm512_set1_pd(c.py[i]), pzi = _mm512_set1_pd(c.pz[i]);
    const __m512d qxi = _mm512_set1_pd(c.qx[i]), qyi = _mm512_set1_pd(c.qy[i]), qzi = _mm512_set1_pd(c.qz[i]);
    for (int64_t w = 0; w < full; ++w) {
      uint64_t word = 0;
      for (int v = 0; v < 8; ++v) {
        const int64_t j = 64 * w + 8 * v;
        const __m512d dpx = _mm512_sub_pd(_mm512_loadu_pd(c.px + j), pxi);
        const __m512d dpy = _mm512_sub_pd(_mm512_loadu_pd(c.py + j), pyi);
        const __m512d dpz = _mm512_sub_pd(_mm512_loadu_pd(c.pz + j), pzi);
        const __m512d dqx = _mm512_sub_pd(_mm512_loadu_pd(c.qx + j), qxi);
        const __m512d dqy = _mm512_sub_pd(_mm512_loadu_pd(c.qy + j), qyi);
        const __m512d dqz = _mm512_sub_pd(_mm512_loadu_pd(c.qz + j), qzi);
        const __m512d a = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(dpx, dpx), _mm512_mul_pd(dpy, dpy)),
                                        _mm512_mul_pd(dpz, dpz));
        const __m512d b = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(dqx, dqx), _mm512_mul_pd(dqy, dqy)),
                                        _mm512_mul_pd(dqz, dqz));
        const __m512d s = _mm512_sub_pd(_mm512_add_pd(a, b), tol2);
        const __mmask8 close = _mm512_cmp_pd_mask(s, zero, _CMP_LT_OQ) |
                               _mm512_cmp_pd_mask(_mm512_mul_pd(s, s), _mm512_mul_pd(_mm512_mul_pd(four, a), b),
                                                  _CMP_LT_OQ);
        word |= static_cast<uint64_t>(close) << (8 * v);
      }
      bits[i * words + w] = word;
    }
    if (full < words) bits[i * words + full] = compatible_word(c, i, 64 * full, K - 64 * full, t2);
  }
}

__attribute__((target("popcnt"))) int64_t popcount_and_hw(const uint64_t* a, const uint64_t* b, int64_t words) {
  int64_t count = 0;
  for (int64_t w = 0; w < words; ++w) count += __builtin_popcountll(a[w] & b[w]);
  return count;
}

// VRNET_CPU_DISPATCH=generic (read when the library loads) keeps the portable code, for tests.
bool generic_requested() {
  const char* value = std::getenv("VRNET_CPU_DISPATCH");
  return value != nullptr && std::string(value) == "generic";
}

const bool kHasAvx512 = __builtin_cpu_supports("avx512f") && !generic_requested();
const bool kHasPopcnt = __builtin_cpu_supports("popcnt") && !generic_requested();
#endif

Graph compatibility(const double* p, const double* q, int64_t K, double tolerance) {
  Graph g{K, (K + 63) / 64, {}};
  g.bits.assign(static_cast<size_t>(K * g.words), 0);
  const Columns columns(p, q, K);
  const double t2 = tolerance * tolerance;
  parallel_ranges(K, 64, [&](int64_t begin, int64_t end) {
#ifdef VRNET_X86_DISPATCH
    if (kHasAvx512) {
      compatible_rows_avx512(columns, K, g.words, begin, end, t2, g.bits.data());
    } else {
      compatible_rows(columns, K, g.words, begin, end, t2, g.bits.data());
    }
#else
    compatible_rows(columns, K, g.words, begin, end, t2, g.bits.data());
#endif
    for (int64_t i = begin; i < end; ++i) g.bits[i * g.words + (i >> 6)] &= ~(uint64_t{1} << (i & 63));
  });
  return g;
}

int64_t popcount_and(const uint64_t* a, const uint64_t* b, int64_t words) {
#ifdef VRNET_X86_DISPATCH
  if (kHasPopcnt) return popcount_and_hw(a, b, words);
#endif
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
