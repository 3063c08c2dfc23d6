// Robust rigid fit of putative correspondences by spatial consistency (the idea of SC^2-PCR, Chen et
// al. 2022): two correspondences (p_i, q_i), (p_j, q_j) are compatible when the distances they span
// agree, | |p_i - p_j| - |q_i - q_j| | < tolerance. Inliers of the true motion are all compatible
// with each other; outliers rarely are.
//
//   1. The compatibility graph as a bitset (K rows of ceil(K / 64) words; K^2 / 8 bytes), symmetric:
//      each 64 x 64 block above the diagonal is computed once and mirrored. Decided in float32 on
//      coordinates relative to the first correspondence when the points span at most
//      kFloatGraphExtent tolerances, else in float64.
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
// On x86-64 CPUs with AVX-512 the graph is built 16 (float32) or 8 (float64) pairs per instruction and the second-order
// popcounts take 8 words per instruction (AVX512-VPOPCNTDQ, else POPCNT; chosen at run time; the
// package is built without -march flags). The vector test performs the scalar test's operations in
// the same order (no FMA contraction), so both give the same bits (tests/test_spatial_consistency.py
// runs both).
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <type_traits>
#include <vector>

#include "common/cpu_dispatch.h"
#include "kabsch/procrustes.h"
#include "spatial_consistency/spatial_consistency.h"
#include "spatial_consistency/spatial_consistency_math.h"


namespace vrnet {
namespace {

struct Graph {
  int64_t K, words;
  std::vector<uint64_t> bits;  // row i: bits[i * words, (i + 1) * words)

  const uint64_t* row(int64_t i) const { return bits.data() + i * words; }
};

// Coordinates of the correspondences, one array per axis (px, py, pz, qx, qy, qz), in double as
// given, or in float relative to the first correspondence (p - p_0, q - q_0: lengths unchanged).
template <typename T>
struct Columns {
  std::vector<T> data;  // the columns one after another (spatial_consistency_math.h's layout)
  int64_t K;
  const T *px, *py, *pz, *qx, *qy, *qz;
  Columns(const double* p, const double* q, int64_t K) : data(6 * K), K(K) {
    const bool about_first = !std::is_same_v<T, double>;
    for (int64_t k = 0; k < K; ++k)
      for (int a = 0; a < 3; ++a) {
        data[a * K + k] = static_cast<T>(about_first ? p[3 * k + a] - p[a] : p[3 * k + a]);
        data[(3 + a) * K + k] = static_cast<T>(about_first ? q[3 * k + a] - q[a] : q[3 * k + a]);
      }
    px = data.data(), py = px + K, pz = py + K, qx = pz + K, qy = qx + K, qz = qy + K;
  }
  Columns(const Columns&) = delete;  // the pointers point into this object's own vector
  Columns& operator=(const Columns&) = delete;
};

// Bits of correspondences [j0, j0 + count) compatible with i (spatial_consistency_math.h).
template <typename T>
uint64_t compatible_word(const Columns<T>& c, int64_t i, int64_t j0, int64_t count, T t2) {
  uint64_t bits = 0;
  for (int64_t l = 0; l < count; ++l) bits |= static_cast<uint64_t>(compatible(c.data.data(), c.K, i, j0 + l, t2)) << l;
  return bits;
}

// Bits of the 64 x 64 block of rows [64 I, 64 I + 64) and columns [64 J, 64 J + 64), both cut at K:
// out[r] holds row 64 I + r (zero past K).
template <typename T>
void compatible_block(const Columns<T>& c, int64_t K, int64_t I, int64_t J, T t2, uint64_t* out) {
  const int64_t rows = std::min<int64_t>(64, K - 64 * I), cols = std::min<int64_t>(64, K - 64 * J);
  for (int64_t r = 0; r < 64; ++r) out[r] = r < rows ? compatible_word(c, 64 * I + r, 64 * J, cols, t2) : 0;
}

// In place: bit c of word r moves to bit r of word c. Swaps the off-diagonal halves of ever smaller
// blocks (32, 16, ..., 1 bits), with bit 0 the first column.
void transpose64(uint64_t* a) {
  uint64_t low = 0x00000000FFFFFFFFull;  // the first `half` bits of every 2 * half
  for (int half = 32; half != 0; half >>= 1, low ^= low << half)
    for (int k = 0; k < 64; k = ((k | half) + 1) & ~half) {
      const uint64_t swap = ((a[k] >> half) ^ a[k | half]) & low;
      a[k | half] ^= swap;
      a[k] ^= swap << half;
    }
}

#ifdef VRNET_X86_DISPATCH
// Bits of the kLanes pairs (i, j), (i, j + 1), ... whose lanes are set; `at_i` holds p_i and q_i
// (px, py, pz, qx, qy, qz) in every lane. The operations of compatible_word, in the same order.
template <typename T>
VRNET_AVX512 uint64_t compatible_lanes(const Columns<T>& c, const typename Avx512<T>::Vec* at_i, int64_t j,
                                       typename Avx512<T>::Mask lanes, T t2) {
  using V = Avx512<T>;
  const typename V::Vec dpx = V::sub(V::load(lanes, c.px + j), at_i[0]), dpy = V::sub(V::load(lanes, c.py + j), at_i[1]),
                        dpz = V::sub(V::load(lanes, c.pz + j), at_i[2]);
  const typename V::Vec dqx = V::sub(V::load(lanes, c.qx + j), at_i[3]), dqy = V::sub(V::load(lanes, c.qy + j), at_i[4]),
                        dqz = V::sub(V::load(lanes, c.qz + j), at_i[5]);
  const typename V::Vec a = V::add(V::add(V::mul(dpx, dpx), V::mul(dpy, dpy)), V::mul(dpz, dpz));
  const typename V::Vec b = V::add(V::add(V::mul(dqx, dqx), V::mul(dqy, dqy)), V::mul(dqz, dqz));
  const typename V::Vec s = V::sub(V::add(a, b), V::set1(t2));
  return lanes & (V::less(s, V::set1(0)) | V::less(V::mul(s, s), V::mul(V::mul(V::set1(4), a), b)));
}

// compatible_block, kLanes pairs per instruction (the last column block loads only the lanes below K).
template <typename T>
__attribute__((target("avx512f"))) void compatible_block_avx512(const Columns<T>& c, int64_t K, int64_t I, int64_t J,
                                                                T t2, uint64_t* out) {
  using V = Avx512<T>;
  using Mask = typename V::Mask;
  const int64_t rows = std::min<int64_t>(64, K - 64 * I), cols = std::min<int64_t>(64, K - 64 * J);
  for (int64_t r = 0; r < 64; ++r) {
    if (r >= rows) {
      out[r] = 0;
      continue;
    }
    const int64_t i = 64 * I + r;
    const typename V::Vec at_i[6] = {V::set1(c.px[i]), V::set1(c.py[i]), V::set1(c.pz[i]),
                                     V::set1(c.qx[i]), V::set1(c.qy[i]), V::set1(c.qz[i])};
    uint64_t word = 0;
    if (cols == 64) {
      for (int v = 0; v < 64 / V::kLanes; ++v)
        word |= compatible_lanes(c, at_i, 64 * J + V::kLanes * v, static_cast<Mask>(~Mask{0}), t2) << (V::kLanes * v);
    } else {
      for (int64_t first = 0; first < cols; first += V::kLanes) {
        const int64_t lanes = std::min<int64_t>(V::kLanes, cols - first);
        word |= compatible_lanes(c, at_i, 64 * J + first, static_cast<Mask>((uint64_t{1} << lanes) - 1), t2) << first;
      }
    }
    out[r] = word;
  }
}

__attribute__((target("popcnt"))) int64_t popcount_and_popcnt(const uint64_t* a, const uint64_t* b, int64_t words) {
  int64_t count = 0;
  for (int64_t w = 0; w < words; ++w) count += __builtin_popcountll(a[w] & b[w]);
  return count;
}

// 8 words per instruction (AVX512-VPOPCNTDQ).
__attribute__((target("avx512f,avx512vpopcntdq"))) int64_t popcount_and_avx512(const uint64_t* a, const uint64_t* b,
                                                                               int64_t words) {
  __m512i sum = _mm512_setzero_si512();
  int64_t w = 0;
  for (; w + 8 <= words; w += 8)
    sum = _mm512_add_epi64(sum, _mm512_popcnt_epi64(_mm512_and_si512(_mm512_loadu_si512(a + w),
                                                                     _mm512_loadu_si512(b + w))));
  if (w < words) {
    const __mmask8 tail = static_cast<__mmask8>((1u << (words - w)) - 1);
    sum = _mm512_add_epi64(sum, _mm512_popcnt_epi64(_mm512_and_si512(_mm512_maskz_loadu_epi64(tail, a + w),
                                                                     _mm512_maskz_loadu_epi64(tail, b + w))));
  }
  alignas(64) int64_t lanes[8];  // (_mm512_reduce_add_epi64 trips a false warning in GCC 12's header)
  _mm512_store_si512(lanes, sum);
  return std::accumulate(lanes, lanes + 8, int64_t{0});
}

#endif

// The graph is symmetric: each 64 x 64 block above the diagonal is computed once and stored
// transposed below it. Row block I (one task, the longest first) computes blocks J >= I.
template <typename T>
Graph compatibility(const Columns<T>& columns, int64_t K, double tolerance) {
  Graph g{K, (K + 63) / 64, {}};
  g.bits.assign(static_cast<size_t>(K * g.words), 0);
  const T t2 = static_cast<T>(tolerance * tolerance);
  parallel_tasks(g.words, [&](int64_t I) {
    uint64_t block[64];
    for (int64_t J = I; J < g.words; ++J) {
#ifdef VRNET_X86_DISPATCH
      if (kHasAvx512) {
        compatible_block_avx512(columns, K, I, J, t2, block);
      } else {
        compatible_block(columns, K, I, J, t2, block);
      }
#else
      compatible_block(columns, K, I, J, t2, block);
#endif
      for (int64_t r = 0; r < 64 && 64 * I + r < K; ++r) g.bits[(64 * I + r) * g.words + J] = block[r];
      if (J == I) continue;
      transpose64(block);
      for (int64_t r = 0; r < 64 && 64 * J + r < K; ++r) g.bits[(64 * J + r) * g.words + I] = block[r];
    }
    for (int64_t i = 64 * I; i < std::min(K, 64 * I + 64); ++i) g.bits[i * g.words + I] &= ~(uint64_t{1} << (i & 63));
  });
  return g;
}

// The largest coordinate range over the axes of both point sets.
double extent(const double* p, const double* q, int64_t K) {
  double largest = 0;
  for (const double* x : {p, q})
    for (int a = 0; a < 3; ++a) {
      double lo = x[a], hi = x[a];
      for (int64_t k = 1; k < K; ++k) lo = std::min(lo, x[3 * k + a]), hi = std::max(hi, x[3 * k + a]);
      largest = std::max(largest, hi - lo);
    }
  return largest;
}

int64_t popcount_and(const uint64_t* a, const uint64_t* b, int64_t words) {
#ifdef VRNET_X86_DISPATCH
  if (kHasVpopcnt) return popcount_and_avx512(a, b, words);
  if (kHasPopcnt) return popcount_and_popcnt(a, b, words);
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

// Bits of the correspondences [k0, k0 + count) that the fit maps within sqrt(threshold2) of their
// target (spatial_consistency_math.h).
uint64_t inlier_word(const Fit& fit, const Columns<double>& c, int64_t k0, int64_t count, double threshold2) {
  uint64_t bits = 0;
  for (int64_t l = 0; l < count; ++l)
    bits |= static_cast<uint64_t>(maps_within(fit.R, fit.t, c.data.data(), c.K, k0 + l, threshold2)) << l;
  return bits;
}

#ifdef VRNET_X86_DISPATCH
// inlier_word for 64 correspondences, 8 per instruction, the same operations in the same order.
__attribute__((target("avx512f"))) uint64_t inlier_word_avx512(const Fit& fit, const Columns<double>& c, int64_t k0,
                                                                double threshold2) {
  __m512d R[9], t[3];
  for (int e = 0; e < 9; ++e) R[e] = _mm512_set1_pd(fit.R[e]);
  for (int a = 0; a < 3; ++a) t[a] = _mm512_set1_pd(fit.t[a]);
  const __m512d limit = _mm512_set1_pd(threshold2);
  uint64_t bits = 0;
  for (int v = 0; v < 8; ++v) {
    const int64_t k = k0 + 8 * v;
    const __m512d px = _mm512_loadu_pd(c.px + k), py = _mm512_loadu_pd(c.py + k), pz = _mm512_loadu_pd(c.pz + k);
    const __m512d target[3] = {_mm512_loadu_pd(c.qx + k), _mm512_loadu_pd(c.qy + k), _mm512_loadu_pd(c.qz + k)};
    __m512d r2 = _mm512_setzero_pd();
    for (int a = 0; a < 3; ++a) {
      const __m512d moved = _mm512_add_pd(
          _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(R[3 * a], px), _mm512_mul_pd(R[3 * a + 1], py)),
                        _mm512_mul_pd(R[3 * a + 2], pz)),
          t[a]);
      const __m512d d = _mm512_sub_pd(moved, target[a]);
      r2 = a == 0 ? _mm512_mul_pd(d, d) : _mm512_add_pd(r2, _mm512_mul_pd(d, d));
    }
    bits |= static_cast<uint64_t>(_mm512_cmp_pd_mask(r2, limit, _CMP_LT_OQ)) << (8 * v);
  }
  return bits;
}
#endif

// The correspondences the fit maps within `threshold` of their target, as ceil(K / 64) words of bits.
std::vector<uint64_t> inlier_mask(const Fit& fit, const Columns<double>& c, int64_t K, double threshold) {
  std::vector<uint64_t> words((K + 63) / 64);
  for (int64_t w = 0; w < static_cast<int64_t>(words.size()); ++w) {
    const int64_t count = std::min<int64_t>(64, K - 64 * w);
#ifdef VRNET_X86_DISPATCH
    if (kHasAvx512 && count == 64) {
      words[w] = inlier_word_avx512(fit, c, 64 * w, threshold * threshold);
      continue;
    }
#endif
    words[w] = inlier_word(fit, c, 64 * w, count, threshold * threshold);
  }
  return words;
}

int64_t count_inliers(const Fit& fit, const Columns<double>& c, int64_t K, double threshold) {
  int64_t count = 0;
  for (uint64_t word : inlier_mask(fit, c, K, threshold)) count += __builtin_popcountll(word);
  return count;
}

// Indices of the correspondences the fit maps within `threshold` of their target, ascending.
std::vector<int64_t> inliers_of(const Fit& fit, const Columns<double>& c, int64_t K, double threshold) {
  const std::vector<uint64_t> words = inlier_mask(fit, c, K, threshold);
  std::vector<int64_t> out;
  for (int64_t w = 0; w < static_cast<int64_t>(words.size()); ++w)
    for (uint64_t bits = words[w]; bits != 0; bits &= bits - 1) out.push_back(64 * w + __builtin_ctzll(bits));
  return out;
}

// Each correspondence's degree in the graph, and the correspondences by degree, highest first
// (ties: lower index).
struct Degrees {
  std::vector<int64_t> degree, order;
  explicit Degrees(const Graph& g) : degree(g.K), order(g.K) {
    for (int64_t i = 0; i < g.K; ++i) degree[i] = popcount_and(g.row(i), g.row(i), g.words);
    std::iota(order.begin(), order.end(), 0);
    std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return degree[a] > degree[b]; });
  }
};

std::vector<int64_t> choose_seeds(const Degrees& d, const double* p, int64_t wanted, double tolerance) {
  std::vector<int64_t> seeds;
  for (int64_t i : d.order) {
    if (static_cast<int64_t>(seeds.size()) >= wanted || d.degree[i] < 2) break;
    const bool near = std::any_of(seeds.begin(), seeds.end(),
                                  [&](int64_t s) { return point_distance(p + 3 * i, p + 3 * s) < tolerance; });
    if (!near) seeds.push_back(i);
  }
  return seeds;
}

// The seed and its `consensus` compatible neighbours of highest second-order score (ties: lower
// index), best first. A score is at most the neighbour's degree, so the neighbours are visited by
// degree and the visit stops once no later one can enter the best `consensus`.
std::vector<int64_t> consensus_of(const Graph& g, const Degrees& d, int64_t seed, int64_t consensus) {
  std::vector<std::pair<int64_t, int64_t>> best;  // (-score, j), a max-heap: the worst kept on top
  const uint64_t* row = g.row(seed);
  for (int64_t j : d.order) {
    const bool full = static_cast<int64_t>(best.size()) == consensus;
    if (full && d.degree[j] < -best.front().first) break;
    if (!((row[j >> 6] >> (j & 63)) & 1u)) continue;
    const std::pair<int64_t, int64_t> candidate{-popcount_and(row, g.row(j), g.words), j};
    if (full && !(candidate < best.front())) continue;
    if (full) {
      std::pop_heap(best.begin(), best.end());
      best.pop_back();
    }
    best.push_back(candidate);
    std::push_heap(best.begin(), best.end());
  }
  std::sort_heap(best.begin(), best.end());
  std::vector<int64_t> members{seed};
  for (const auto& scored : best) members.push_back(scored.second);
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
  const Columns<double> columns(p, q, K);
  const Graph graph = extent(p, q, K) <= kFloatGraphExtent * tolerance ? compatibility(Columns<float>(p, q, K), K, tolerance)
                                                                        : compatibility(columns, K, tolerance);
  const Degrees degrees(graph);
  const std::vector<int64_t> chosen = choose_seeds(degrees, p, seeds, tolerance);
  std::vector<Fit> fits(chosen.size());
  parallel_tasks(static_cast<int64_t>(chosen.size()), [&](int64_t s) {
    const std::vector<int64_t> members = consensus_of(graph, degrees, chosen[s], consensus);
    if (members.size() < 3) return;
    fits[s] = kabsch_on(p, q, members);
    fits[s].inliers = count_inliers(fits[s], columns, K, inlier_threshold);
  });
  Fit best;
  for (const Fit& fit : fits)
    if (fit.inliers > best.inliers) best = fit;
  std::vector<int64_t> members = best.inliers >= 3 ? inliers_of(best, columns, K, inlier_threshold) : std::vector<int64_t>{};
  for (int round = 0; round < 10 && members.size() >= 3; ++round) {  // refit on the inliers while they grow
    Fit refit = kabsch_on(p, q, members);
    std::vector<int64_t> grown = inliers_of(refit, columns, K, inlier_threshold);
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
