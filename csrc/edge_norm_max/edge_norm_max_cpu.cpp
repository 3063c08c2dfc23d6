// edge_norm_max on the CPU (definition in edge_norm_max.h).
//
// Layout: the kernels read projections point-major, (B, N, 2O) in memory (what EdgeConv's matrix
// product x^T W^T writes): a neighbour's channels are one contiguous run, so a gather through idx
// fetches whole cache lines, and the loops over channels run on SIMD vectors. Outputs are
// point-major too and returned as (B, O, N) views.
//
// Work is split into tasks of (batch, chunk of kChunk points), claimed dynamically. No task writes
// where another does: the backward computes the gradient of each neighbour term by gathering over
// its incoming edges (a reverse graph built per call) instead of scattering. Per-channel sums are kept
// per task in double, about a task-local shift, and combined in task order (deterministic).
//
// Regions: training forward 2 (statistics + extremes, then the output), 1 with running statistics;
// backward 3 (reverse graph + gradient sums, then the input gradient).
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cstring>
#include <limits>
#include <memory>
#include <type_traits>

#include "common/cpu_dispatch.h"
#include "edge_norm_max/edge_norm_max.h"

namespace vrnet {
namespace {

constexpr int64_t kBlock = 16;   // channels per SIMD block
constexpr int64_t kChunk = 128;  // points per task

struct Layout {
  int64_t B, O, N, k;
  int64_t chunks() const { return (N + kChunk - 1) / kChunk; }
  int64_t tasks() const { return B * chunks(); }
};

// Task `task`: batch `batch`, points [begin, end).
struct Task {
  int64_t batch, begin, end;
  Task(const Layout& L, int64_t task)
      : batch(task / L.chunks()), begin((task % L.chunks()) * kChunk), end(std::min(L.N, begin + kChunk)) {}
};

// SIMD registers as GCC/Clang vector types (16 bytes by default: SSE2 on x86-64, NEON on arm64), so
// the loops over a channel block vectorise without -march flags; 64 bytes inside functions compiled
// for AVX-512 (neighbour_pass_avx512).
// (-Wpsabi, up to neighbour_pass: GCC notes that a 64-byte vector return has another ABI without
// AVX-512; these helpers are always inlined into the AVX-512 function, so no such call exists.)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wpsabi"
template <typename scalar_t, int Bytes = 16>
struct Simd {
  typedef scalar_t vec __attribute__((vector_size(Bytes)));
  static constexpr int64_t lanes = Bytes / sizeof(scalar_t);
  __attribute__((always_inline)) static vec load(const scalar_t* p) {
    vec v;
    std::memcpy(&v, p, sizeof(vec));
    return v;
  }
  __attribute__((always_inline)) static void store(scalar_t* p, vec v) { std::memcpy(p, &v, sizeof(vec)); }
};

// Per-channel normalisation y = scale * (z - mean) + bias (scale = weight * invstd), and the sign of
// the weight: the max over the neighbours is taken of direction * a.
struct ChannelAffine {
  std::vector<double> mean, invstd, scale, bias;
  template <typename stat_t, typename scalar_t>
  ChannelAffine(const stat_t* mean_in, const stat_t* var_in, const scalar_t* weight, const scalar_t* bias_in,
                int64_t O, double eps)
      : mean(O), invstd(O), scale(O), bias(O) {
    for (int64_t o = 0; o < O; ++o) {
      mean[o] = mean_in[o];
      invstd[o] = 1.0 / std::sqrt(static_cast<double>(var_in[o]) + eps);
      scale[o] = (weight ? static_cast<double>(weight[o]) : 1.0) * invstd[o];
      bias[o] = bias_in ? static_cast<double>(bias_in[o]) : 0.0;
    }
  }
};

// Branch-free: the sign of h is random per element, and a mispredicted branch costs more than the
// whole formula. NaN propagates (std::max / std::min return their first argument then).
inline double leaky_relu(double h, double slope) { return std::max(h, 0.0) + slope * std::min(h, 0.0); }

// d leaky_relu / dh at h, branch-free.
inline double leaky_relu_slope(double h, double slope) { return slope + (1.0 - slope) * static_cast<double>(h > 0); }

// out[o] = leaky_relu(scale * (extreme + centre - mean) + bias), in double: the sum and the centring of
// large values near their mean lose nothing in float32 storage.
template <typename scalar_t>
inline void normalise_point(const scalar_t* extreme, const scalar_t* centre, const ChannelAffine& c, double slope,
                            int64_t O, scalar_t* out) {
  const double *scale = c.scale.data(), *mean = c.mean.data(), *bias = c.bias.data();
  for (int64_t o = 0; o < O; ++o) {
    const double h = scale[o] * (static_cast<double>(extreme[o]) + static_cast<double>(centre[o]) - mean[o]) + bias[o];
    out[o] = static_cast<scalar_t>(leaky_relu(h, slope));
  }
}

// One point: over its k neighbours, per channel, the extreme of direction * a and its first slot (NaN
// wins and propagates like torch.max, at the first NaN's slot), and the sum and sum of squares of
// a - shift_a. Full blocks of kBlock channels run on SIMD vectors, the rest lane by lane.
template <typename scalar_t, int Bytes>
__attribute__((always_inline)) inline void neighbour_pass_body(const scalar_t* points, const int64_t* nb, int64_t O,
                                                               int64_t k, const scalar_t* direction,
                                                               const scalar_t* shift_a, scalar_t* extreme,
                                                               int32_t* slot_out, scalar_t* sum, scalar_t* squares) {
  using S = Simd<scalar_t, Bytes>;
  constexpr int64_t vectors = kBlock / S::lanes;
  const int64_t stride = 2 * O, full = O - O % kBlock;
  for (int64_t o0 = 0; o0 < full; o0 += kBlock) {
    typename S::vec dir[vectors], shift[vectors], top[vectors], at[vectors], total[vectors], square[vectors];
    const scalar_t* first = points + nb[0] * stride + o0;
    for (int64_t i = 0; i < vectors; ++i) {
      dir[i] = S::load(direction + o0 + i * S::lanes), shift[i] = S::load(shift_a + o0 + i * S::lanes);
      const typename S::vec v = S::load(first + i * S::lanes), d = v - shift[i];
      top[i] = dir[i] * v, at[i] = v - v, total[i] = d, square[i] = d * d;
    }
    for (int64_t j = 1; j < k; ++j) {
      const scalar_t* row = points + nb[j] * stride + o0;
      const typename S::vec slot_j = typename S::vec{} + static_cast<scalar_t>(j);
      for (int64_t i = 0; i < vectors; ++i) {
        const typename S::vec v = S::load(row + i * S::lanes), signed_v = dir[i] * v, d = v - shift[i];
        const auto better = signed_v > top[i];
        top[i] = better ? signed_v : top[i];
        at[i] = better ? slot_j : at[i];
        total[i] += d, square[i] += d * d;
      }
    }
    for (int64_t i = 0; i < vectors; ++i) {
      scalar_t slot_lanes[S::lanes];
      S::store(extreme + o0 + i * S::lanes, top[i]), S::store(slot_lanes, at[i]);
      S::store(sum + o0 + i * S::lanes, total[i]), S::store(squares + o0 + i * S::lanes, square[i]);
      for (int64_t l = 0; l < S::lanes; ++l) slot_out[o0 + i * S::lanes + l] = static_cast<int32_t>(slot_lanes[l]);
    }
  }
  for (int64_t o = full; o < O; ++o) {
    sum[o] = 0, squares[o] = 0;
    for (int64_t j = 0; j < k; ++j) {
      const scalar_t v = points[nb[j] * stride + o], signed_v = direction[o] * v, d = v - shift_a[o];
      if (j == 0 || signed_v > extreme[o]) extreme[o] = signed_v, slot_out[o] = static_cast<int32_t>(j);
      sum[o] += d, squares[o] += d * d;
    }
  }
  for (int64_t o = 0; o < O; ++o) {
    extreme[o] *= direction[o];
    if (sum[o] != sum[o]) {  // a NaN among the values (or inf - inf in the sum): find the first NaN
      for (int64_t j = 0; j < k; ++j) {
        const scalar_t v = points[nb[j] * stride + o];
        if (v != v) {
          extreme[o] = v, slot_out[o] = static_cast<int32_t>(j);
          break;
        }
      }
    }
  }
}

#ifdef VRNET_X86_DISPATCH
// The same pass with 64-byte registers: the same operations per lane, so the same results.
template <typename scalar_t>
__attribute__((target("avx512f"))) void neighbour_pass_avx512(const scalar_t* points, const int64_t* nb, int64_t O,
                                                              int64_t k, const scalar_t* direction,
                                                              const scalar_t* shift_a, scalar_t* extreme,
                                                              int32_t* slot_out, scalar_t* sum, scalar_t* squares) {
  neighbour_pass_body<scalar_t, 64>(points, nb, O, k, direction, shift_a, extreme, slot_out, sum, squares);
}
#endif

template <typename scalar_t>
void neighbour_pass(const scalar_t* points, const int64_t* nb, int64_t O, int64_t k, const scalar_t* direction,
                    const scalar_t* shift_a, scalar_t* extreme, int32_t* slot_out, scalar_t* sum,
                    scalar_t* squares) {
#ifdef VRNET_X86_DISPATCH
  if (kHasAvx512) return neighbour_pass_avx512(points, nb, O, k, direction, shift_a, extreme, slot_out, sum, squares);
#endif
  neighbour_pass_body<scalar_t, 16>(points, nb, O, k, direction, shift_a, extreme, slot_out, sum, squares);
}
#pragma GCC diagnostic pop

// Means over the task's points of the neighbour terms (a) and the centre terms (b): shifts that keep
// float differences of large values near their typical value exact.
template <typename scalar_t>
void task_means(const scalar_t* points, int64_t O, const Task& t, scalar_t* mean_a, scalar_t* mean_b) {
  std::vector<double> sum(2 * O, 0.0);
  for (int64_t n = t.begin; n < t.end; ++n)
    for (int64_t o = 0; o < 2 * O; ++o) sum[o] += points[n * 2 * O + o];
  for (int64_t o = 0; o < O; ++o) {
    mean_a[o] = static_cast<scalar_t>(sum[o] / (t.end - t.begin));
    mean_b[o] = static_cast<scalar_t>(sum[O + o] / (t.end - t.begin));
  }
}

template <typename scalar_t>
void forward_kernel(const scalar_t* P, const int64_t* I, const scalar_t* weight, const scalar_t* bias,
                    const scalar_t* running_mean, const scalar_t* running_var, double eps, double slope,
                    const Layout& L, scalar_t* out, int32_t* arg, double* mean_out, double* var_out) {
  const int64_t N = L.N, k = L.k, O = L.O, tasks = L.tasks();
  const bool batch_stats = running_mean == nullptr;
  std::vector<scalar_t> direction(O);
  for (int64_t o = 0; o < O; ++o) direction[o] = weight == nullptr || weight[o] >= 0 ? 1 : -1;
  std::unique_ptr<ChannelAffine> running;
  if (!batch_stats) running = std::make_unique<ChannelAffine>(running_mean, running_var, weight, bias, O, eps);
  // Per (task, channel): the task's edge count n_t, shift s_t = mean_a + mean_b over its points, and
  // sum (z - s_t), sum (z - s_t)^2 over its edges.
  std::vector<double> shift(batch_stats ? tasks * O : 0), sum1(shift.size()), sum2(shift.size());
  parallel_tasks(tasks, [&](int64_t task) {
    const Task t(L, task);
    const scalar_t* points = P + t.batch * N * 2 * O;
    const int64_t* ib = I + t.batch * N * k;
    std::vector<scalar_t> shift_a(O, 0), shift_b(O, 0), extreme(O), sum(O), squares(O);
    std::vector<double> s1(batch_stats ? O : 0, 0.0), s2(s1.size(), 0.0);
    if (batch_stats) task_means(points, O, t, shift_a.data(), shift_b.data());
    for (int64_t n = t.begin; n < t.end; ++n) {
      int32_t* slot = arg + (t.batch * N + n) * O;
      scalar_t* e = out + (t.batch * N + n) * O;
      const scalar_t* centre = points + n * 2 * O + O;
      neighbour_pass(points, ib + n * k, O, k, direction.data(), shift_a.data(), extreme.data(), slot, sum.data(),
                     squares.data());
      if (!batch_stats) {
        normalise_point(extreme.data(), centre, *running, slope, O, e);
        continue;
      }
      std::memcpy(e, extreme.data(), O * sizeof(scalar_t));
      for (int64_t o = 0; o < O; ++o) {  // edges (n, j): z - shift = (a_j - shift_a) + (b_n - shift_b)
        const double c = static_cast<double>(centre[o]) - shift_b[o];
        s1[o] += sum[o] + k * c;
        s2[o] += squares[o] + 2 * c * sum[o] + k * c * c;
      }
    }
    for (int64_t o = 0; o < static_cast<int64_t>(s1.size()); ++o) {
      shift[task * O + o] = static_cast<double>(shift_a[o]) + shift_b[o];
      sum1[task * O + o] = s1[o], sum2[task * O + o] = s2[o];
    }
  });
  if (!batch_stats) {
    for (int64_t o = 0; o < O; ++o) mean_out[o] = running_mean[o], var_out[o] = running_var[o];
    return;
  }
  const double count = static_cast<double>(L.B * N * k);
  for (int64_t o = 0; o < O; ++o) {
    double total = 0;
    for (int64_t task = 0; task < tasks; ++task) {
      const Task t(L, task);
      total += sum1[task * O + o] + static_cast<double>((t.end - t.begin) * k) * shift[task * O + o];
    }
    const double mean = total / count;
    double squares = 0;  // sum (z - mean)^2 = sum over tasks of sum (z - s_t - d)^2 with d = mean - s_t
    for (int64_t task = 0; task < tasks; ++task) {
      const Task t(L, task);
      const double d = mean - shift[task * O + o];
      squares += sum2[task * O + o] - 2 * d * sum1[task * O + o] + static_cast<double>((t.end - t.begin) * k) * d * d;
    }
    mean_out[o] = mean, var_out[o] = std::max(squares / count, 0.0);
  }
  const ChannelAffine affine(mean_out, var_out, weight, bias, O, eps);
  parallel_tasks(tasks, [&](int64_t task) {
    const Task t(L, task);
    for (int64_t n = t.begin; n < t.end; ++n) {
      scalar_t* y = out + (t.batch * N + n) * O;
      normalise_point(y, P + (t.batch * N + n) * 2 * O + O, affine, slope, O, y);
    }
  });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> edge_norm_max_cpu(
    const at::Tensor& projections_in, const at::Tensor& idx_in, const c10::optional<at::Tensor>& weight_in,
    const c10::optional<at::Tensor>& bias_in, const c10::optional<at::Tensor>& running_mean_in,
    const c10::optional<at::Tensor>& running_var_in, double eps, double negative_slope) {
  check_edge_norm_max_inputs(projections_in, idx_in, weight_in, bias_in, running_mean_in, running_var_in, eps);
  check_negative_slope(negative_slope);
  const at::Tensor points = projections_in.transpose(1, 2).contiguous();  // (B, N, 2O); free if point-major
  const at::Tensor idx = idx_in.contiguous();
  const at::Tensor weight = contiguous_or_undefined(weight_in), bias = contiguous_or_undefined(bias_in);
  const at::Tensor running_mean = contiguous_or_undefined(running_mean_in);
  const at::Tensor running_var = contiguous_or_undefined(running_var_in);
  const Layout L{points.size(0), points.size(2) / 2, points.size(1), idx.size(2)};
  at::Tensor out = at::empty({L.B, L.N, L.O}, points.options());
  at::Tensor arg = at::empty({L.B, L.N, L.O}, points.options().dtype(at::kInt));
  at::Tensor mean = at::empty({L.O}, points.options().dtype(at::kDouble));
  at::Tensor var = at::empty({L.O}, points.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "edge_norm_max_cpu", [&] {
    const auto ptr = [](const at::Tensor& t) { return t.defined() ? t.const_data_ptr<scalar_t>() : nullptr; };
    forward_kernel<scalar_t>(points.const_data_ptr<scalar_t>(), idx.const_data_ptr<int64_t>(), ptr(weight),
                             ptr(bias), ptr(running_mean), ptr(running_var), eps, negative_slope, L,
                             out.mutable_data_ptr<scalar_t>(), arg.mutable_data_ptr<int32_t>(),
                             mean.mutable_data_ptr<double>(), var.mutable_data_ptr<double>());
  });
  return {out.transpose(1, 2), mean, var, arg.transpose(1, 2)};
}

// The incoming edges of every point, per batch: edges[offsets[m] .. offsets[m + 1]) hold n * k + j for
// each edge (n, j) with idx[n, j] == m, in increasing order.
struct ReverseGraph {
  std::vector<int64_t> offsets;  // (B, N + 1)
  std::vector<int32_t> edges;    // (B, N * k)
  ReverseGraph(const int64_t* I, const Layout& L) : offsets(L.B * (L.N + 1)), edges(L.B * L.N * L.k) {
    parallel_tasks(L.B, [&](int64_t b) {
      const int64_t* ib = I + b * L.N * L.k;
      int64_t* off = offsets.data() + b * (L.N + 1);
      int32_t* out = edges.data() + b * L.N * L.k;
      std::fill(off, off + L.N + 1, 0);
      for (int64_t e = 0; e < L.N * L.k; ++e) ++off[ib[e] + 1];
      for (int64_t m = 0; m < L.N; ++m) off[m + 1] += off[m];
      std::vector<int64_t> cursor(off, off + L.N);
      for (int64_t e = 0; e < L.N * L.k; ++e) out[cursor[ib[e]]++] = static_cast<int32_t>(e);
    });
  }
};

// grad_a[o] += per_edge + per_deviation * (z - mean) + (slot_n[o] == j ? g_n[o] : 0) for one
// incoming edge (n, j) of a point, z - mean = centre + (b_n - shift_b); float runs on SIMD vectors (the
// slot compare masks the winner term), double lane by lane.
template <typename scalar_t>
inline void accumulate_incoming_edge(scalar_t* grad_a, const scalar_t* centre, const scalar_t* b_row,
                                     const scalar_t* shift_b, const scalar_t* per_edge, const scalar_t* per_deviation,
                                     const scalar_t* g_n, const int32_t* slot_n, int32_t j,
                                     int64_t O) {
  int64_t o = 0;
  if constexpr (std::is_same_v<scalar_t, float>) {
    using S = Simd<float>;
    typedef int32_t ivec __attribute__((vector_size(16)));
    const ivec slot_j = ivec{} + j;
    for (; o + S::lanes <= O; o += S::lanes) {
      ivec slots;
      std::memcpy(&slots, slot_n + o, sizeof(ivec));
      const S::vec deviation = S::load(centre + o) + (S::load(b_row + o) - S::load(shift_b + o));
      const S::vec winner = reinterpret_cast<S::vec>(reinterpret_cast<ivec>(S::load(g_n + o)) & (slots == slot_j));
      S::store(grad_a + o, S::load(grad_a + o) + S::load(per_edge + o) + S::load(per_deviation + o) * deviation + winner);
    }
  }
  for (; o < O; ++o) {
    const scalar_t deviation = centre[o] + (b_row[o] - shift_b[o]);
    const scalar_t winner = slot_n[o] == j ? g_n[o] : scalar_t(0);
    grad_a[o] += per_edge[o] + per_deviation[o] * deviation + winner;
  }
}

template <typename scalar_t>
void backward_kernel(const scalar_t* G, const scalar_t* P, const int64_t* I, const int32_t* arg,
                     const scalar_t* weight, const scalar_t* bias, const double* mean_in, const double* var_in,
                     bool batch_stats, double eps, double slope, const Layout& L, scalar_t* grad_p,
                     scalar_t* grad_weight, scalar_t* grad_bias) {
  const int64_t N = L.N, k = L.k, O = L.O, tasks = L.tasks();
  const ChannelAffine c(mean_in, var_in, weight, bias, O, eps);
  const ReverseGraph reverse(I, L);
  // Region 1: gh = dL/dh * scale, the gradient of each point's winning edge value z_win (B, N, O), and
  // per task the sums of dL/dh and of dL/dh * (z_win - mean), h = scale * (z_win - mean) + bias.
  std::vector<scalar_t> gh(L.B * N * O);
  std::vector<double> sum_g(tasks * O, 0.0), sum_gx(tasks * O, 0.0);
  parallel_tasks(tasks, [&](int64_t task) {
    const Task t(L, task);
    const scalar_t* points = P + t.batch * N * 2 * O;
    const int64_t* ib = I + t.batch * N * k;
    double* s_g = sum_g.data() + task * O;
    double* s_gx = sum_gx.data() + task * O;
    for (int64_t n = t.begin; n < t.end; ++n) {
      const int64_t point = t.batch * N + n;
      for (int64_t o = 0; o < O; ++o) {
        const int64_t winner = ib[n * k + arg[point * O + o]];
        const double centred = static_cast<double>(points[winner * 2 * O + o]) + points[n * 2 * O + O + o] - c.mean[o];
        const double g = G[point * O + o] * leaky_relu_slope(c.scale[o] * centred + c.bias[o], slope);
        gh[point * O + o] = static_cast<scalar_t>(g * c.scale[o]);  // the winner's gradient, ready to add
        s_g[o] += g, s_gx[o] += g * centred;
      }
    }
  });
  // mean = sum z / count and var = sum (z - mean)^2 / count over all edges: d mean / dz_e = 1 / count,
  // d var / dz_e = 2 (z_e - mean) / count (zero with running statistics).
  const double count = static_cast<double>(L.B * N * k);
  std::vector<scalar_t> per_edge(O), per_deviation(O);
  for (int64_t o = 0; o < O; ++o) {
    double g = 0, gx = 0;
    for (int64_t task = 0; task < tasks; ++task) g += sum_g[task * O + o], gx += sum_gx[task * O + o];
    grad_bias[o] = static_cast<scalar_t>(g);
    grad_weight[o] = static_cast<scalar_t>(gx * c.invstd[o]);
    const double grad_mean = -c.scale[o] * g;                                    // through the explicit mean
    const double grad_var = -0.5 * c.scale[o] * c.invstd[o] * c.invstd[o] * gx;  // through invstd
    per_edge[o] = static_cast<scalar_t>(batch_stats ? grad_mean / count : 0.0);
    per_deviation[o] = static_cast<scalar_t>(batch_stats ? 2 * grad_var / count : 0.0);
  }
  // Region 2, per point p of the task: the centre term b[p] gets its winner's gh and, from each
  // of its k edges, per_edge + per_deviation * (z - mean); the neighbour term a[p] gets the same from
  // each incoming edge (n, j), plus gh[n] * scale in the channels whose winner (n, j) is.
  // z - mean = (a - shift_a) + (b - shift_b) - rest, each term exact enough in the input's precision.
  parallel_tasks(tasks, [&](int64_t task) {
    const Task t(L, task);
    const scalar_t* points = P + t.batch * N * 2 * O;
    const int64_t* ib = I + t.batch * N * k;
    const int64_t* off = reverse.offsets.data() + t.batch * (N + 1);
    const int32_t* incoming = reverse.edges.data() + t.batch * N * k;
    scalar_t* gp = grad_p + t.batch * N * 2 * O;
    std::vector<scalar_t> shift_a(O), shift_b(O), rest(O), deviation_sum(O), centre(O), grad_a(O);
    task_means(points, O, t, shift_a.data(), shift_b.data());
    for (int64_t o = 0; o < O; ++o) rest[o] = static_cast<scalar_t>(c.mean[o] - shift_a[o] - shift_b[o]);
    for (int64_t p = t.begin; p < t.end; ++p) {
      const scalar_t* own = points + p * 2 * O;
      for (int64_t o = 0; o < O; ++o) centre[o] = (own[O + o] - shift_b[o]) - rest[o], deviation_sum[o] = 0;
      for (int64_t j = 0; j < k; ++j) {
        const scalar_t* row = points + ib[p * k + j] * 2 * O;
        for (int64_t o = 0; o < O; ++o) deviation_sum[o] += (row[o] - shift_a[o]) + centre[o];
      }
      const scalar_t* g_own = gh.data() + (t.batch * N + p) * O;
      for (int64_t o = 0; o < O; ++o) {  // running statistics: no term through them (not even 0 * a NaN)
        const scalar_t through_stats = k * per_edge[o] + per_deviation[o] * deviation_sum[o];
        gp[p * 2 * O + O + o] = batch_stats ? g_own[o] + through_stats : g_own[o];
      }
      for (int64_t o = 0; o < O; ++o) grad_a[o] = 0, centre[o] = (own[o] - shift_a[o]) - rest[o];
      for (int64_t e = off[p]; e < off[p + 1]; ++e) {
        const int64_t n = incoming[e] / k, j = incoming[e] % k;
        const scalar_t* b_row = points + n * 2 * O + O;
        const scalar_t* g_n = gh.data() + (t.batch * N + n) * O;
        const int32_t* slot_n = arg + (t.batch * N + n) * O;
        if (!batch_stats) {
          for (int64_t o = 0; o < O; ++o) grad_a[o] += slot_n[o] == j ? g_n[o] : scalar_t(0);
          continue;
        }
        accumulate_incoming_edge(grad_a.data(), centre.data(), b_row, shift_b.data(), per_edge.data(),
                                 per_deviation.data(), g_n, slot_n, static_cast<int32_t>(j), O);
      }
      std::memcpy(gp + p * 2 * O, grad_a.data(), O * sizeof(scalar_t));
    }
  });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> edge_norm_max_backward_cpu(
    const at::Tensor& grad_in, const at::Tensor& projections_in, const at::Tensor& idx_in, const at::Tensor& arg_in,
    const c10::optional<at::Tensor>& weight_in, const c10::optional<at::Tensor>& bias_in, const at::Tensor& mean_in,
    const at::Tensor& var_in, bool batch_stats, double eps, double negative_slope) {
  const EdgeNormMaxBackwardArgs a = checked_edge_norm_max_backward_args(
      grad_in, projections_in, idx_in, arg_in, weight_in, bias_in, mean_in, var_in, eps, negative_slope);
  const at::Tensor &grad = a.grad, &points = a.points, &arg = a.arg, &idx = a.idx, &mean = a.mean, &var = a.var;
  const at::Tensor &weight = a.weight, &bias = a.bias;
  const Layout L{points.size(0), points.size(2) / 2, points.size(1), idx.size(2)};
  at::Tensor grad_points = at::empty(points.sizes(), points.options());
  at::Tensor grad_weight = at::empty({L.O}, points.options());
  at::Tensor grad_bias = at::empty({L.O}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "edge_norm_max_backward_cpu", [&] {
    const auto ptr = [](const at::Tensor& t) { return t.defined() ? t.const_data_ptr<scalar_t>() : nullptr; };
    backward_kernel<scalar_t>(grad.const_data_ptr<scalar_t>(), points.const_data_ptr<scalar_t>(),
                              idx.const_data_ptr<int64_t>(), arg.const_data_ptr<int32_t>(), ptr(weight), ptr(bias),
                              mean.const_data_ptr<double>(), var.const_data_ptr<double>(), batch_stats, eps,
                              negative_slope, L, grad_points.mutable_data_ptr<scalar_t>(),
                              grad_weight.mutable_data_ptr<scalar_t>(), grad_bias.mutable_data_ptr<scalar_t>());
  });
  return {grad_points.transpose(1, 2), grad_weight, grad_bias};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CPU, m) {
  m.impl("edge_norm_max", &edge_norm_max_cpu);
  m.impl("edge_norm_max_backward", &edge_norm_max_backward_cpu);
}

}  // namespace vrnet
