// The uniform grid of the 3-D kNN searches (CPU: knn_cpu.cpp; CUDA: knn_grid_kernel), shared so that
// both lay out the same grid: the cells' box (the points inside the robust box: a far stray must not
// stretch the cells), the edge (the finest grid of up to 1024 cells per axis with at most ~2 cells per
// point), cell coordinates and box distances. Free of torch includes (the CUDA kernels use it).
#pragma once

#include <cmath>
#include <cstdint>

#include "common/host_device.h"

namespace vrnet {

constexpr int64_t kGridMaxDivisions = 1024;  // cells along the longest axis at most

// The ranks of the robust box's quantiles along an axis of m values: the 0.1 % and 99.9 % ones,
// widened by half their distance on both sides, for clouds of 1,000 points or more (else the
// bounding box: ranks 0 and m - 1, no widening).
struct RobustRanks {
  int64_t low, high;
  bool widen;
  explicit RobustRanks(int64_t m)
      : low(m < 1000 ? 0 : m / 1000), high(m < 1000 ? m - 1 : m - 1 - m / 1000), widen(m >= 1000) {}
};

struct GridShape {
  double lo[3] = {0, 0, 0};
  double cell = 1.0;
  int64_t dims[3] = {1, 1, 1};

  // The grid over the box [lo, hi] of `inliers` points (lo = hi = 0 when there are none).
  static GridShape fit(const double lo[3], const double hi[3], int64_t inliers) {
    GridShape g;
    double low[3], high[3];
    for (int a = 0; a < 3; ++a) low[a] = inliers > 0 ? lo[a] : 0.0, high[a] = inliers > 0 ? hi[a] : 0.0;
    double extent_max = 0.0;
    for (int a = 0; a < 3; ++a) extent_max = std::fmax(extent_max, high[a] - low[a]);
    if (!(extent_max > 0.0)) extent_max = 1.0;
    const double budget = 2.0 * static_cast<double>(inliers) + 1.0;
    int64_t best = 1;
    for (int64_t lo_d = 1, hi_d = kGridMaxDivisions; lo_d <= hi_d;) {  // largest divisions within budget
      const int64_t d = (lo_d + hi_d) / 2;
      double total = 1.0;
      for (int a = 0; a < 3; ++a) total *= std::fmax(1.0, std::ceil((high[a] - low[a]) / (extent_max / d)));
      if (total <= budget) {
        best = d;
        lo_d = d + 1;
      } else {
        hi_d = d - 1;
      }
    }
    g.cell = extent_max / best * (1.0 + 1e-9);
    for (int a = 0; a < 3; ++a) {
      g.lo[a] = low[a];
      const int64_t d = static_cast<int64_t>(std::ceil((high[a] - low[a]) / g.cell));
      g.dims[a] = d > 1 ? d : 1;
    }
    return g;
  }

  VRNET_HOST_DEVICE int64_t cells() const { return dims[0] * dims[1] * dims[2]; }

  // The cell holding coordinate v along axis a, clamped to the grid.
  VRNET_HOST_DEVICE int64_t cell_coord(double v, int a) const {
    const int64_t c = static_cast<int64_t>(floor((v - lo[a]) / cell));
    return c < 0 ? 0 : (c > dims[a] - 1 ? dims[a] - 1 : c);
  }
  VRNET_HOST_DEVICE int64_t cell_id(int64_t x, int64_t y, int64_t z) const { return (z * dims[1] + y) * dims[0] + x; }

  // Squared distance from q to the box of cell (x, y, z) (0 inside it).
  template <typename scalar_t>
  VRNET_HOST_DEVICE double cell_distance_sq(const scalar_t* q, int64_t x, int64_t y, int64_t z) const {
    const int64_t cell_xyz[3] = {x, y, z};
    double total = 0;
    for (int a = 0; a < 3; ++a) {
      const double low = lo[a] + cell_xyz[a] * cell, v = static_cast<double>(q[a]);
      const double below = low - v, above = v - (low + cell);
      const double gap = below > 0.0 ? below : (above > 0.0 ? above : 0.0);
      total += gap * gap;
    }
    return total;
  }

  // A lower bound on the squared distance from q (in cell c) to any cell outside the cube of cells
  // within r of c: a cell beyond face (a, side) is at least the face gap away along a and, along
  // every other axis, at least q's distance to the grid's extent (outside[], their sum
  // outside_total: this term keeps far-away queries from scanning ring after ring of cells that are
  // all about equally far). *more: whether any cell lies outside that cube.
  template <typename scalar_t>
  VRNET_HOST_DEVICE double beyond_sq(const scalar_t* q, const int64_t* c, int64_t r, const double* outside,
                                     double outside_total, bool* more) const {
    double bound = INFINITY;
    *more = false;
    for (int a = 0; a < 3; ++a) {
      const double others = outside_total - outside[a], v = static_cast<double>(q[a]);
      if (c[a] - r > 0) {
        *more = true;
        const double gap = v - (lo[a] + (c[a] - r) * cell), kept = gap > 0.0 ? gap : 0.0;
        bound = kept * kept + others < bound ? kept * kept + others : bound;
      }
      if (c[a] + r < dims[a] - 1) {
        *more = true;
        const double gap = lo[a] + (c[a] + r + 1) * cell - v, kept = gap > 0.0 ? gap : 0.0;
        bound = kept * kept + others < bound ? kept * kept + others : bound;
      }
    }
    return bound;
  }

  // Squared distance from q to the grid's extent along axis a (0 within it).
  template <typename scalar_t>
  VRNET_HOST_DEVICE double outside_sq(const scalar_t* q, int a) const {
    const double v = static_cast<double>(q[a]), below = lo[a] - v, above = v - (lo[a] + dims[a] * cell);
    const double gap = below > 0.0 ? below : (above > 0.0 ? above : 0.0);
    return gap * gap;
  }
};

}  // namespace vrnet
