// Checks the kNN top-k buffers of csrc/knn/topk.h against std::sort on random candidate streams with
// many ties: TopK (runtime k) and RegisterTopK (compile-time capacity KMAX >= k) must both return the
// k smallest (distance, index) pairs in order, and RegisterTopK::pop_front hand its entries out in that
// order. Prints one line per failure; exit status = failures.
#include <algorithm>
#include <cstdio>
#include <random>
#include <utility>
#include <vector>

#include "knn/topk.h"

using vrnet::RegisterTopK;
using vrnet::TopK;

template <int KMAX>
int check(std::mt19937& rng, int k, int count, int distinct) {
  std::uniform_int_distribution<int> value(0, distinct - 1);
  std::vector<std::pair<float, int>> stream(count);
  for (int j = 0; j < count; ++j) stream[j] = {0.25f * value(rng), j};
  std::shuffle(stream.begin(), stream.end(), rng);
  std::vector<std::pair<float, int>> expected(stream);
  std::sort(expected.begin(), expected.end());
  std::vector<float> dist(k);
  std::vector<int64_t> idx(k);
  TopK<float> runtime{dist.data(), idx.data(), k};
  runtime.reset(count);
  RegisterTopK<float, KMAX> fixed;
  fixed.reset(count);
  for (const auto& [d, j] : stream) {
    runtime.push(d, j);
    if (d <= fixed.worst()) fixed.push(d, j);
  }
  int failures = 0;
  for (int i = 0; i < k; ++i) {
    const bool has = i < count;
    const float want_d = has ? expected[i].first : std::numeric_limits<float>::infinity();
    const int want_i = has ? expected[i].second : count;
    if (runtime.dist[i] != want_d || runtime.idx[i] != want_i || fixed.dist[i] != want_d || fixed.idx[i] != want_i) {
      std::printf("KMAX=%d k=%d count=%d slot %d: want (%g, %d), TopK (%g, %lld), RegisterTopK (%g, %d)\n", KMAX, k,
                  count, i, want_d, want_i, runtime.dist[i], static_cast<long long>(runtime.idx[i]), fixed.dist[i],
                  fixed.idx[i]);
      ++failures;
    }
  }
  // pop_front hands the entries out in order, then empty (+inf, sentinel) ones.
  for (int i = 0; i < KMAX; ++i) {
    const bool has = i < count;
    const float want_d = has ? expected[i].first : std::numeric_limits<float>::infinity();
    const int want_i = has ? expected[i].second : count;
    if (fixed.dist[0] != want_d || fixed.idx[0] != want_i) {
      std::printf("KMAX=%d count=%d pop %d: want (%g, %d), got (%g, %d)\n", KMAX, count, i, want_d, want_i,
                  fixed.dist[0], fixed.idx[0]);
      ++failures;
    }
    fixed.pop_front(count);
  }
  if (fixed.dist[0] != std::numeric_limits<float>::infinity() || fixed.idx[0] != count) ++failures;
  return failures;
}

int main() {
  std::mt19937 rng(7);
  int failures = 0;
  for (int trial = 0; trial < 200; ++trial) {
    for (int distinct : {1, 3, 50, 100000}) {
      const int count = 1 + trial * 7 % 600;
      failures += check<8>(rng, 1 + trial % 8, count, distinct);
      failures += check<32>(rng, 1 + trial % 32, count, distinct);
      failures += check<64>(rng, 20, count, distinct);
    }
  }
  std::printf("%s\n", failures ? "FAILED" : "ok");
  return failures ? 1 : 0;
}
