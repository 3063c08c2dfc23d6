// CPU kNN: a uniform-grid search for 3-D points (reference clouds over one tile) and, for features
// and small clouds, GEMM tiles scanned by a per-query reservoir. Neither materialises the N x M distance matrix.
#include <ATen/ops/empty.h>
#include <ATen/ops/mm.h>
#include <ATen/ops/mean.h>
#include <ATen/ops/sub.h>
#include <ATen/ops/max.h>
#include <ATen/ops/square.h>
#include <ATen/ops/sum.h>
#include <ATen/ops/_to_copy.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <vector>

#include "common/common.h"
#include "common/cpu_dispatch.h"
#include "knn/grid.h"
#include "knn/knn.h"

namespace vrnet {
namespace {

// The 26 cells around a cell, ordered by how many axes they step along (6 faces, 12 edges, 8 corners).
const std::vector<std::array<int64_t, 3>> kNeighbourOffsets = [] {
  std::vector<std::array<int64_t, 3>> offsets;
  for (int steps = 1; steps <= 3; ++steps)
    for (int64_t z = -1; z <= 1; ++z)
      for (int64_t y = -1; y <= 1; ++y)
        for (int64_t x = -1; x <= 1; ++x)
          if (std::abs(x) + std::abs(y) + std::abs(z) == steps) offsets.push_back({x, y, z});
  return offsets;
}();

// Grid over one reference cloud: points sorted by cell (counting sort) with cell offsets.
template <typename scalar_t>
struct Grid : GridShape {
  std::vector<int64_t> start;      // (cells + 1) offsets into the sorted arrays
  std::vector<int64_t> order;      // original index of each sorted point (far strays last)
  std::vector<scalar_t> xyz;       // sorted coordinates, 3 per point
  int64_t far_begin = 0;           // order[far_begin:] are the points outside the grid

  // The box holding every point but far strays (RobustRanks). One point 100 km away must not
  // stretch the cells over 100 km (a quadratic search).
  static std::array<std::array<double, 2>, 3> robust_box(const scalar_t* pts, int64_t m) {
    std::array<std::array<double, 2>, 3> box;
    std::vector<double> values(m);
    const RobustRanks ranks(m);
    for (int a = 0; a < 3; ++a) {
      for (int64_t i = 0; i < m; ++i) values[i] = pts[3 * i + a];
      std::nth_element(values.begin(), values.begin() + ranks.low, values.end());
      const double q_low = values[ranks.low];
      std::nth_element(values.begin(), values.begin() + ranks.high, values.end());
      const double q_high = values[ranks.high];
      const double margin = ranks.widen ? 0.5 * (q_high - q_low) : 0.0;
      box[a] = {q_low - margin, q_high + margin};
    }
    return box;
  }

  // The grid (GridShape::fit) over the points inside robust_box; the others (far strays) are kept
  // apart and scanned by every search.
  void build(const scalar_t* pts, int64_t m) {
    const auto box = robust_box(pts, m);
    std::vector<char> inside(m);
    int64_t inliers = 0;
    double low[3], high[3];
    for (int a = 0; a < 3; ++a) { low[a] = box[a][1]; high[a] = box[a][0]; }
    for (int64_t i = 0; i < m; ++i) {
      bool in = true;
      for (int a = 0; a < 3; ++a) in &= pts[3 * i + a] >= box[a][0] && pts[3 * i + a] <= box[a][1];
      inside[i] = in;
      if (!in) continue;
      ++inliers;
      for (int a = 0; a < 3; ++a) {
        low[a] = std::min(low[a], static_cast<double>(pts[3 * i + a]));
        high[a] = std::max(high[a], static_cast<double>(pts[3 * i + a]));
      }
    }
    static_cast<GridShape&>(*this) = GridShape::fit(low, high, inliers);
    const int64_t cell_count = cells();
    std::vector<int64_t> cid(m);
    start.assign(cell_count + 1, 0);
    for (int64_t i = 0; i < m; ++i) {
      if (!inside[i]) continue;
      cid[i] = cell_id(cell_coord(pts[3 * i], 0), cell_coord(pts[3 * i + 1], 1), cell_coord(pts[3 * i + 2], 2));
      ++start[cid[i] + 1];
    }
    for (int64_t c = 0; c < cell_count; ++c) start[c + 1] += start[c];
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    order.resize(m);
    xyz.resize(3 * m);
    far_begin = inliers;
    int64_t far = inliers;
    for (int64_t i = 0; i < m; ++i) {
      const int64_t pos = inside[i] ? fill[cid[i]]++ : far++;
      order[pos] = i;
      for (int a = 0; a < 3; ++a) xyz[3 * pos + a] = pts[3 * i + a];
    }
  }

  // Offers sorted point p (unless it is the query itself) to the query's top-k.
  void push(const scalar_t* q, int64_t p, int64_t self, TopK<scalar_t>& top) const {
    const int64_t j = order[p];
    if (j == self) return;
    const scalar_t dx = q[0] - xyz[3 * p], dy = q[1] - xyz[3 * p + 1], dz = q[2] - xyz[3 * p + 2];
    top.push(dx * dx + dy * dy + dz * dz, j);
  }

  // Exact kNN of one query by visiting cube shells of cells around the query's cell until no
  // unvisited cell can hold a point closer than the current k-th candidate. A cell whose box lies
  // farther than the current k-th candidate is skipped, and the 26 neighbours of the query's cell
  // are visited faces first (the nearest, on average), so the top-k fills with close points early
  // and most later candidates are rejected in one compare. `shell` is scratch space (box distance,
  // cell id) reused across queries.
  void search(const scalar_t* q, int64_t self, TopK<scalar_t>& top, std::vector<std::pair<double, int64_t>>& shell) const {
    for (int64_t p = far_begin; p < static_cast<int64_t>(order.size()); ++p) push(q, p, self, top);
    const int64_t c[3] = {cell_coord(q[0], 0), cell_coord(q[1], 1), cell_coord(q[2], 2)};
    double outside[3], outside_total = 0;  // squared distance from q to the grid's extent, per axis
    for (int a = 0; a < 3; ++a) {
      outside[a] = outside_sq(q, a);
      outside_total += outside[a];
    }
    for (int64_t r = 0;; ++r) {
      const int64_t z0 = std::max<int64_t>(c[2] - r, 0), z1 = std::min(c[2] + r, dims[2] - 1);
      const int64_t y0 = std::max<int64_t>(c[1] - r, 0), y1 = std::min(c[1] + r, dims[1] - 1);
      const int64_t x0 = std::max<int64_t>(c[0] - r, 0), x1 = std::min(c[0] + r, dims[0] - 1);
      shell.clear();
      if (r == 1) {  // the 26 neighbours, faces first, then edges, then corners (nearest first, no sort)
        for (const auto& offset : kNeighbourOffsets) {
          const int64_t x = c[0] + offset[0], y = c[1] + offset[1], z = c[2] + offset[2];
          if (x < 0 || y < 0 || z < 0 || x >= dims[0] || y >= dims[1] || z >= dims[2]) continue;
          const int64_t id = cell_id(x, y, z);
          if (start[id] != start[id + 1]) shell.emplace_back(cell_distance_sq(q, x, y, z), id);
        }
      }
      for (int64_t z = z0; r != 1 && z <= z1; ++z) {
        const bool z_shell = std::abs(z - c[2]) == r;
        for (int64_t y = y0; y <= y1; ++y) {
          const bool zy_shell = z_shell || std::abs(y - c[1]) == r;
          // Interior rows only contribute their two shell cells (x = c-r and x = c+r).
          const int64_t step = zy_shell ? 1 : std::max<int64_t>(2 * r, 1);
          for (int64_t x = zy_shell ? x0 : c[0] - r; x <= x1; x += step) {
            if (x < x0) continue;
            const int64_t id = cell_id(x, y, z);
            if (start[id] != start[id + 1]) shell.emplace_back(cell_distance_sq(q, x, y, z), id);
          }
        }
      }
      for (const auto& [box_sq, id] : shell) {
        if (box_sq * (1.0 - 1e-5) > static_cast<double>(top.worst())) continue;
        for (int64_t p = start[id]; p < start[id + 1]; ++p) push(q, p, self, top);
      }
      bool more;
      const double bound_sq = beyond_sq(q, c, r, outside, outside_total, &more);
      if (!more) return;
      if (static_cast<double>(top.worst()) < bound_sq * (1.0 - 1e-5)) return;
    }
  }
};

constexpr int64_t kGridQueryBlock = 256;  // queries (in grid order) per task of the grid search

template <typename scalar_t>
void knn_grid(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self,
              at::Tensor& dist, at::Tensor& idx) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1);
  // Every cloud's grid (and the grid order of its queries, so that neighbouring queries share
  // cached cells), then the searches: two parallel regions per call, whatever B is.
  std::vector<Grid<scalar_t>> grids(B), query_orders(B);
  parallel_tasks(B, [&](int64_t b) {
    grids[b].build(ref.const_data_ptr<scalar_t>() + b * M * 3, M);
    query_orders[b].build(query.const_data_ptr<scalar_t>() + b * N * 3, N);
  });
  const int64_t blocks = (N + kGridQueryBlock - 1) / kGridQueryBlock;
  parallel_tasks(B * blocks, [&](int64_t task) {
    const int64_t b = task / blocks, s0 = (task % blocks) * kGridQueryBlock, s1 = std::min(N, s0 + kGridQueryBlock);
    const scalar_t* q = query.const_data_ptr<scalar_t>() + b * N * 3;
    scalar_t* d_out = dist.mutable_data_ptr<scalar_t>() + b * N * k;
    int64_t* i_out = idx.mutable_data_ptr<int64_t>() + b * N * k;
    std::vector<std::pair<double, int64_t>> shell;
    for (int64_t s = s0; s < s1; ++s) {
      const int64_t n = query_orders[b].order[s];
      TopK<scalar_t> top{d_out + n * k, i_out + n * k, k};
      top.reset(M);
      grids[b].search(q + 3 * n, exclude_self ? n : -1, top, shell);
    }
  });
}

constexpr int64_t kQueryBlock = 256;
constexpr int64_t kRefBlock = 1024;

// One query's row of a tile: dist[j] = (|q|^2 + |r_j|^2) - 2 q.r_j from the tile's dot products,
// clamped at 0, +inf where not finite, NaN at column `self` (or -1: none), which then never passes
// a threshold and never counts as a minimum.
template <typename scalar_t>
void row_distances_portable(const scalar_t* dots, const scalar_t* r_norms, scalar_t q_norm, int64_t width,
                            int64_t self, scalar_t* dist) {
  for (int64_t j = 0; j < width; ++j) {
    const scalar_t d = q_norm + r_norms[j] - 2 * dots[j];
    dist[j] = std::isfinite(d) ? std::max<scalar_t>(d, 0) : std::numeric_limits<scalar_t>::infinity();
  }
  if (self >= 0) dist[self] = std::numeric_limits<scalar_t>::quiet_NaN();
}

// Minimum of each of kBoundSubsets interleaved subsets of the row (column j in subset j % kBoundSubsets).
constexpr int64_t kBoundSubsets = kMaxBoundValues;

// Written as a select per column of whole subset-wide blocks, which compilers turn into vector
// minima (x86 `minps` / `minpd` keep the minimum when the column is NaN, as the comparison does).
template <typename scalar_t>
void subset_minima_portable(const scalar_t* dist, int64_t width, scalar_t* minima) {
  std::fill(minima, minima + kBoundSubsets, std::numeric_limits<scalar_t>::infinity());
  int64_t j0 = 0;
  for (; j0 + kBoundSubsets <= width; j0 += kBoundSubsets)
    for (int64_t s = 0; s < kBoundSubsets; ++s) minima[s] = dist[j0 + s] < minima[s] ? dist[j0 + s] : minima[s];
  for (int64_t s = 0; j0 + s < width; ++s) minima[s] = dist[j0 + s] < minima[s] ? dist[j0 + s] : minima[s];
}

// Offers the row's columns at or under the reservoir's threshold, in column order.
template <typename scalar_t>
void offer_row_portable(const scalar_t* dist, int64_t width, int64_t r0, Reservoir<scalar_t>& res) {
  for (int64_t j = 0; j < width; ++j)
    if (dist[j] <= res.threshold) res.add(dist[j], r0 + j);
}

#ifdef VRNET_X86_DISPATCH
// The three row functions above, kLanes columns per instruction, with the same operations in the
// same order (the same distances, minima and offers; the offers of one vector are checked again
// against the threshold, which an earlier offer may have lowered).
template <typename scalar_t>
__attribute__((target("avx512f"))) void row_distances_avx512(const scalar_t* dots, const scalar_t* r_norms,
                                                             scalar_t q_norm, int64_t width, int64_t self,
                                                             scalar_t* dist) {
  using V = Avx512<scalar_t>;
  const typename V::Vec qn = V::set1(q_norm), two = V::set1(2), zero = V::set1(0);
  const typename V::Vec inf = V::set1(std::numeric_limits<scalar_t>::infinity());
  for (int64_t j0 = 0; j0 < width; j0 += V::kLanes) {
    const typename V::Mask valid = lanes_below<scalar_t>(width - j0);
    const typename V::Vec d = V::sub(V::add(qn, V::load(valid, r_norms + j0)), V::mul(two, V::load(valid, dots + j0)));
    const typename V::Vec clamped = V::blend(V::less(d, zero), d, zero);  // std::max(d, 0)
    V::store(valid, dist + j0, V::blend(V::finite(d), inf, clamped));
  }
  if (self >= 0) dist[self] = std::numeric_limits<scalar_t>::quiet_NaN();
}

template <typename scalar_t>
__attribute__((target("avx512f"))) void subset_minima_avx512(const scalar_t* dist, int64_t width, scalar_t* minima) {
  using V = Avx512<scalar_t>;
  static_assert(kBoundSubsets % V::kLanes == 0, "a subset per lane of whole registers");
  constexpr int kParts = kBoundSubsets / V::kLanes;
  const typename V::Vec inf = V::set1(std::numeric_limits<scalar_t>::infinity());
  typename V::Vec lowest[kParts];
  for (int p = 0; p < kParts; ++p) lowest[p] = inf;
  for (int64_t j0 = 0; j0 < width; j0 += kBoundSubsets)
    for (int p = 0; p < kParts; ++p) {
      const int64_t first = j0 + p * V::kLanes;
      if (first >= width) break;
      const typename V::Mask valid = lanes_below<scalar_t>(width - first);
      const typename V::Vec d = V::blend(valid, inf, V::load(valid, dist + first));
      lowest[p] = V::blend(V::less(d, lowest[p]), lowest[p], d);
    }
  for (int p = 0; p < kParts; ++p) V::store(minima + p * V::kLanes, lowest[p]);
}

template <typename scalar_t>
__attribute__((target("avx512f"))) void offer_row_avx512(const scalar_t* dist, int64_t width, int64_t r0,
                                                         Reservoir<scalar_t>& res) {
  using V = Avx512<scalar_t>;
  for (int64_t j0 = 0; j0 < width; j0 += V::kLanes) {
    const typename V::Mask valid = lanes_below<scalar_t>(width - j0);
    for (uint64_t pass = valid & V::less_equal(V::load(valid, dist + j0), V::set1(res.threshold)); pass != 0;
         pass &= pass - 1) {
      const int64_t j = j0 + __builtin_ctzll(pass);
      if (dist[j] <= res.threshold) res.add(dist[j], r0 + j);
    }
  }
}
#endif

// Offers one query's candidates of a tile to its reservoir (`row` is scratch of `width` values).
// A fresh reservoir first takes as its threshold the k-th smallest of the row's kBoundSubsets subset
// minima (+ 2 slack): k distinct columns lie at or under it, so it bounds the k-th smallest
// distance, and most of the row is then rejected in one compare instead of being buffered.
template <typename scalar_t>
void scan_row(const scalar_t* dots, const scalar_t* r_norms, scalar_t q_norm, int64_t width, int64_t r0, int64_t self,
              scalar_t* row, Reservoir<scalar_t>& res) {
  scalar_t minima[kBoundSubsets];
  const bool bound = res.items.empty() && res.k <= kBoundSubsets;
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) {
    row_distances_avx512(dots, r_norms, q_norm, width, self, row);
    if (bound) {
      subset_minima_avx512(row, width, minima);
      res.bound(minima, kBoundSubsets);
    }
    offer_row_avx512(row, width, r0, res);
    return;
  }
#endif
  row_distances_portable(dots, r_norms, q_norm, width, self, row);
  if (bound) {
    subset_minima_portable(row, width, minima);
    res.bound(minima, kBoundSubsets);
  }
  offer_row_portable(row, width, r0, res);
}

// The columns of a row at or under `threshold`, in column order, into `columns` (room for
// kOneTileCandidates + 16): their count, or -1 when there are more than kOneTileCandidates.
constexpr int64_t kOneTileCandidates = 128;

// By blocks of 16 columns: a test of the whole block first (a vector comparison for the compiler;
// a row passes few columns, so most blocks end there), then branch-free within a block that has
// a passing column (every column is written, the count advances past the passing ones; a branch
// per column mispredicts). The count is checked after each block, so at most 15 writes land past
// the limit.
template <typename scalar_t>
int64_t collect_portable(const scalar_t* dist, int64_t width, scalar_t threshold, int32_t* columns) {
  int64_t count = 0;
  for (int64_t j0 = 0; j0 < width && count <= kOneTileCandidates; j0 += 16) {
    const int64_t j1 = std::min(width, j0 + 16);
    int passes = 0;
    for (int64_t j = j0; j < j1; ++j) passes |= dist[j] <= threshold;
    if (!passes) continue;
    for (int64_t j = j0; j < j1; ++j) {
      columns[count] = static_cast<int32_t>(j);
      count += dist[j] <= threshold;
    }
  }
  return count > kOneTileCandidates ? -1 : count;
}

#ifdef VRNET_X86_DISPATCH
template <typename scalar_t>
__attribute__((target("avx512f"))) int64_t collect_avx512(const scalar_t* dist, int64_t width, scalar_t threshold,
                                                          int32_t* columns) {
  using V = Avx512<scalar_t>;
  const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  int64_t count = 0;
  for (int64_t j0 = 0; j0 < width && count <= kOneTileCandidates; j0 += V::kLanes) {
    const typename V::Mask valid = lanes_below<scalar_t>(width - j0);
    const uint32_t pass = valid & V::less_equal(V::load(valid, dist + j0), V::set1(threshold));
    _mm512_mask_compressstoreu_epi32(columns + count, static_cast<__mmask16>(pass),
                                     _mm512_add_epi32(lane, _mm512_set1_epi32(static_cast<int32_t>(j0))));
    count += __builtin_popcount(pass);
  }
  return count > kOneTileCandidates ? -1 : count;
}

// kth_smallest of a row's kBoundSubsets minima on AVX-512: the value v with #(< v) <= k - 1 <
// #(<= v) (one value, whatever the ties, so it equals the portable result).
template <typename scalar_t>
__attribute__((target("avx512f,popcnt"))) scalar_t kth_minimum_avx512(const scalar_t* minima, int64_t k) {
  using V = Avx512<scalar_t>;
  constexpr int kParts = kBoundSubsets / V::kLanes;
  typename V::Vec parts[kParts];
  for (int p = 0; p < kParts; ++p) parts[p] = V::load(minima + p * V::kLanes);
  for (int64_t i = 0; i < kBoundSubsets; ++i) {
    const typename V::Vec value = V::set1(minima[i]);
    int64_t below = 0, at_or_below = 0;
    for (int p = 0; p < kParts; ++p) {
      below += __builtin_popcount(V::less(parts[p], value));
      at_or_below += __builtin_popcount(V::less_equal(parts[p], value));
    }
    if (below <= k - 1 && k - 1 < at_or_below) return minima[i];
  }
  return std::numeric_limits<scalar_t>::infinity();
}
#endif

// Writes the first k of `count` candidates in (exact distance, index) order (`columns` ascending):
// candidate i's place is the number of candidates before it in that order, a permutation, so each
// of the first k places is written once, with no branch on the distances.
template <typename scalar_t>
void rank_candidates_portable(const scalar_t* exact, const int32_t* columns, int64_t count, int64_t k,
                              scalar_t* dist_out, int64_t* idx_out) {
  for (int64_t i = 0; i < count; ++i) {
    int64_t place = 0;
    for (int64_t j = 0; j < count; ++j) place += (exact[j] < exact[i]) | ((exact[j] == exact[i]) & (j < i));
    if (place < k) {
      dist_out[place] = exact[i];
      idx_out[place] = columns[i];
    }
  }
}

#ifdef VRNET_X86_DISPATCH
// rank_candidates_portable with kLanes comparisons per instruction (the same places).
template <typename scalar_t>
__attribute__((target("avx512f,popcnt"))) void rank_candidates_avx512(const scalar_t* exact, const int32_t* columns,
                                                                      int64_t count, int64_t k, scalar_t* dist_out,
                                                                      int64_t* idx_out) {
  using V = Avx512<scalar_t>;
  for (int64_t i = 0; i < count; ++i) {
    const typename V::Vec value = V::set1(exact[i]);
    int64_t place = 0;
    for (int64_t j0 = 0; j0 < count; j0 += V::kLanes) {
      const typename V::Mask valid = lanes_below<scalar_t>(count - j0);
      const typename V::Mask before = i > j0 ? lanes_below<scalar_t>(i - j0) : typename V::Mask{0};
      const typename V::Vec other = V::load(valid, exact + j0);
      place += __builtin_popcount((valid & V::less(other, value)) | (before & V::equal(other, value)));
    }
    if (place < k) {
      dist_out[place] = exact[i];
      idx_out[place] = columns[i];
    }
  }
}
#endif

// Whether a reference cloud of M points is one GEMM tile for a k-nearest search that needs no
// reservoir (most rows are ranked on the stack by knn_row_one_tile).
constexpr bool fits_one_tile(int64_t M, int64_t k) { return M <= kRefBlock && k <= kBoundSubsets; }

// Exact k nearest of one query when the whole reference cloud is one tile of dot products (M <=
// kRefBlock) and k <= kBoundSubsets: the columns under the subset-minima bound (see scan_row) are
// ranked by exact distance, ties by lower index: what the reservoir would return, without one.
// False (nothing written) when the bound is not finite or passes more than kOneTileCandidates
// columns; the caller then uses the reservoir.
template <typename scalar_t>
bool knn_row_one_tile(const scalar_t* dots, const scalar_t* r_norms, scalar_t q_norm, int64_t M, int64_t self,
                      scalar_t slack, const scalar_t* q, const scalar_t* refs, int64_t C, int64_t k, scalar_t* row,
                      scalar_t* dist_out, int64_t* idx_out) {
  scalar_t minima[kBoundSubsets];
  int32_t columns[kOneTileCandidates + 16];
  int64_t count;
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) {
    row_distances_avx512(dots, r_norms, q_norm, M, self, row);
    subset_minima_avx512(row, M, minima);
    const scalar_t threshold = kth_minimum_avx512(minima, k) + 2 * slack;
    if (!std::isfinite(threshold)) return false;
    count = collect_avx512(row, M, threshold, columns);
  } else
#endif
  {
    row_distances_portable(dots, r_norms, q_norm, M, self, row);
    subset_minima_portable(row, M, minima);
    const scalar_t threshold = kth_smallest(minima, kBoundSubsets, k) + 2 * slack;
    if (!std::isfinite(threshold)) return false;
    count = collect_portable(row, M, threshold, columns);
  }
  if (count < 0) return false;
  scalar_t exact[kOneTileCandidates];
  for (int64_t i = 0; i < count; ++i) exact[i] = squared_distance(q, refs + columns[i] * C, C);
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) {
    rank_candidates_avx512(exact, columns, count, k, dist_out, idx_out);
    return true;
  }
#endif
  rank_candidates_portable(exact, columns, count, k, dist_out, idx_out);
  return true;
}

// Exact k nearest of one query row among all M reference rows (exhaustive scan with exact
// differences), for clouds whose squared norms overflow the dtype.
template <typename scalar_t>
void knn_row_exhaustive(const scalar_t* q, const scalar_t* refs, int64_t M, int64_t C, int64_t self, int64_t k,
                        scalar_t* dist, int64_t* idx) {
  TopK<scalar_t> top{dist, idx, k};
  top.reset(M);
  for (int64_t j = 0; j < M; ++j) {
    if (j != self) top.push(squared_distance(q, refs + j * C, C), j);
  }
}

// GEMM-tiled kNN for any C. Both clouds are first shifted by the reference cloud's mean, so that
// |q|^2 + |r|^2 - 2 q.r does not cancel catastrophically for clouds far from the origin; every
// candidate within the rounding bound of that formula is kept (by the reservoir, or on the stack
// for a cloud of one tile) and the survivors are re-ranked by exact distance (see Reservoir).
//
// The whole call is ONE parallel region in which the threads claim (cloud, block of kQueryBlock
// queries) tasks (parallel_tasks); inside a task the tile products run single-threaded. A fork and
// join per tile (thousands per call) made the search 10x slower whenever another process held a
// core: every join waited for a descheduled thread.
template <typename scalar_t>
void knn_tiled(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self,
               at::Tensor& dist, at::Tensor& idx) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  // Rounding of the expanded formula: a few units in the last place of (|q|^2 + |r|^2) per term of
  // the dot product; 8 (C + 2) eps is a generous bound for any summation order the GEMM picks.
  const scalar_t relative_error = static_cast<scalar_t>(8 * (C + 2)) * std::numeric_limits<scalar_t>::epsilon();
  // The same shift for both clouds, rounded once to their dtype: a distance does not depend on it,
  // and each centred coordinate is then exact to half an ulp of its own (small) size.
  const bool same = query.is_same(ref);  // a cloud's own graph (DGCNN): centre and norms once
  const at::Tensor shift = ref.mean(1, /*keepdim=*/true, at::kDouble).to(ref.scalar_type());
  const at::Tensor q_centred = at::sub(query, shift).contiguous();
  const at::Tensor r_centred = same ? q_centred : at::sub(ref, shift).contiguous();
  const at::Tensor q_norms = q_centred.square().sum(2).contiguous();             // (B, N)
  const at::Tensor r_norms = same ? q_norms : r_centred.square().sum(2).contiguous();  // (B, M)
  const at::Tensor r_norm_max = std::get<0>(r_norms.max(1)).contiguous();
  const at::Tensor q_norm_max = same ? r_norm_max : std::get<0>(q_norms.max(1)).contiguous();
  const scalar_t* qn_all = q_norms.const_data_ptr<scalar_t>();
  const scalar_t* rn_all = r_norms.const_data_ptr<scalar_t>();
  const scalar_t* rn_max = r_norm_max.const_data_ptr<scalar_t>();
  const scalar_t* qn_max = q_norm_max.const_data_ptr<scalar_t>();
  const scalar_t* q_all = query.const_data_ptr<scalar_t>();
  const scalar_t* r_all = ref.const_data_ptr<scalar_t>();
  const int64_t blocks = (N + kQueryBlock - 1) / kQueryBlock;
  const bool one_tile = fits_one_tile(M, k);
  parallel_tasks(B * blocks, [&](int64_t task) {
    std::vector<Reservoir<scalar_t>> reservoirs(one_tile ? 1 : std::min(N, kQueryBlock));
    std::vector<scalar_t> row(std::min(M, kRefBlock));
    const int64_t b = task / blocks, q0 = (task % blocks) * kQueryBlock, q1 = std::min(N, q0 + kQueryBlock);
    const scalar_t* q_rows = q_all + b * N * C;
    const scalar_t* r_rows = r_all + b * M * C;
    scalar_t* d_out = dist.mutable_data_ptr<scalar_t>() + b * N * k;
    int64_t* i_out = idx.mutable_data_ptr<int64_t>() + b * N * k;
    if (!std::isfinite(rn_max[b]) || !std::isfinite(qn_max[b])) {
      // Squared norms overflow the dtype (coordinates spread over ~1e19 in float32): the expanded
      // formula is meaningless, so this cloud is searched exhaustively with exact differences.
      for (int64_t n = q0; n < q1; ++n)
        knn_row_exhaustive(q_rows + n * C, r_rows, M, C, exclude_self ? n : -1, k, d_out + n * k, i_out + n * k);
      return;
    }
    const scalar_t* qn = qn_all + b * N;
    const scalar_t* rn = rn_all + b * M;
    const auto slack = [&](int64_t n) {
      const scalar_t value = relative_error * (qn[n] + rn_max[b]);
      return std::isfinite(value) ? value : scalar_t(0);
    };
    const at::Tensor q_tile = q_centred.select(0, b).narrow(0, q0, q1 - q0);
    if (one_tile) {
      const at::Tensor dots = at::mm(q_tile, r_centred.select(0, b).t());
      const scalar_t* dp = dots.const_data_ptr<scalar_t>();
      for (int64_t n = q0; n < q1; ++n) {
        const int64_t self = exclude_self ? n : -1;
        if (knn_row_one_tile(dp + (n - q0) * M, rn, qn[n], M, self, slack(n), q_rows + n * C, r_rows, C, k, row.data(),
                             d_out + n * k, i_out + n * k))
          continue;
        reservoirs[0].reset(k, slack(n));
        scan_row(dp + (n - q0) * M, rn, qn[n], M, 0, self, row.data(), reservoirs[0]);
        reservoirs[0].finish(q_rows + n * C, r_rows, C, d_out + n * k, i_out + n * k);
      }
      return;
    }
    for (int64_t n = q0; n < q1; ++n) reservoirs[n - q0].reset(k, slack(n));
    for (int64_t r0 = 0; r0 < M; r0 += kRefBlock) {
      const int64_t r1 = std::min(M, r0 + kRefBlock), width = r1 - r0;
      // dots[n, j] = q_n . r_j (single-threaded inside this task)
      const at::Tensor dots = at::mm(q_tile, r_centred.select(0, b).narrow(0, r0, width).t());
      const scalar_t* dp = dots.const_data_ptr<scalar_t>();
      for (int64_t n = q0; n < q1; ++n) {
        const int64_t self = exclude_self && n >= r0 && n < r1 ? n - r0 : -1;
        scan_row(dp + (n - q0) * width, rn + r0, qn[n], width, r0, self, row.data(), reservoirs[n - q0]);
      }
    }
    for (int64_t n = q0; n < q1; ++n)
      reservoirs[n - q0].finish(q_rows + n * C, r_rows, C, d_out + n * k, i_out + n * k);
  });
}

std::tuple<at::Tensor, at::Tensor> knn_cpu(const at::Tensor& query_in, const at::Tensor& ref_in,
                                           int64_t k, bool exclude_self) {
  check_knn_inputs(query_in, ref_in, k, exclude_self);
  const int64_t B = query_in.size(0), N = query_in.size(1), C = query_in.size(2);
  const at::Tensor query = query_in.contiguous();
  const at::Tensor ref = ref_in.is_same(query_in) ? query : ref_in.contiguous();
  check_finite(query, "query");
  check_finite(ref, "ref");
  at::Tensor dist = at::empty({B, N, k}, query.options());
  at::Tensor idx = at::empty({B, N, k}, query.options().dtype(at::kLong));
  if (N == 0) return {dist, idx};
  AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "knn_cpu", [&] {
    // 3-D points: the grid, except for reference clouds of one tile, where the tiled search with its
    // one-tile bound is faster (the same neighbours and the same exact distances).
    if (C == 3 && !fits_one_tile(ref.size(1), k)) knn_grid<scalar_t>(query, ref, k, exclude_self, dist, idx);
    else knn_tiled<scalar_t>(query, ref, k, exclude_self, dist, idx);
  });
  return {dist, idx};
}

// d dist2[n, j] / d query[n] = 2 (q_n - r_idx), / d ref[idx] = -2 (q_n - r_idx).
std::tuple<at::Tensor, at::Tensor> knn_backward_cpu(const at::Tensor& grad_in, const at::Tensor& query_in,
                                                    const at::Tensor& ref_in, const at::Tensor& idx_in) {
  check_knn_backward_inputs(grad_in, query_in, ref_in, idx_in);
  const at::Tensor grad = grad_in.contiguous(), query = query_in.contiguous();
  const at::Tensor ref = ref_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2), k = idx.size(2);
  at::Tensor grad_q = at::zeros_like(query);
  at::Tensor grad_r = at::zeros_like(ref);
  AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "knn_backward_cpu", [&] {
    const scalar_t* g = grad.const_data_ptr<scalar_t>();
    const scalar_t* q = query.const_data_ptr<scalar_t>();
    const scalar_t* r = ref.const_data_ptr<scalar_t>();
    const int64_t* ix = idx.const_data_ptr<int64_t>();
    scalar_t* gq = grad_q.mutable_data_ptr<scalar_t>();
    scalar_t* gr = grad_r.mutable_data_ptr<scalar_t>();
    parallel_ranges(B * N, 64, [&](int64_t begin, int64_t end) {
      for (int64_t bn = begin; bn < end; ++bn) {
        const int64_t b = bn / N;
        for (int64_t j = 0; j < k; ++j) {
          const scalar_t w = 2 * g[bn * k + j];
          const scalar_t* rj = r + (b * M + ix[bn * k + j]) * C;
          for (int64_t c = 0; c < C; ++c) gq[bn * C + c] += w * (q[bn * C + c] - rj[c]);
        }
      }
    });
    // Each task owns one (batch, channel) column of grad_r: no races, deterministic order.
    parallel_ranges(B * C, 1, [&](int64_t begin, int64_t end) {
      for (int64_t bc = begin; bc < end; ++bc) {
        const int64_t b = bc / C, c = bc % C;
        for (int64_t n = 0; n < N; ++n) {
          const int64_t bn = b * N + n;
          for (int64_t j = 0; j < k; ++j) {
            const int64_t m = ix[bn * k + j];
            gr[(b * M + m) * C + c] -= 2 * g[bn * k + j] * (q[bn * C + c] - r[(b * M + m) * C + c]);
          }
        }
      }
    });
  });
  return {grad_q, grad_r};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("knn", &knn_cpu);
  m.impl("knn_backward", &knn_backward_cpu);
}

}  // namespace vrnet
