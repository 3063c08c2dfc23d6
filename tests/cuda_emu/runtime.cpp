// The runtime of the CUDA emulator (see cuda_emu.h): fibers, the per-block scheduler with barriers
// and warp collectives, the two passes of a launch and the sanitizer.
//
// The kernels' translation units are compiled with GCC's -fsanitize=thread *instrumentation* but not
// linked against its runtime: every load and store they make calls a __tsan_* hook, and this file
// (compiled without instrumentation) defines those hooks as the sanitizer's checks. Accesses made
// outside an emulated thread (the torch glue around a launch) are ignored.
#include <dlfcn.h>
#include <link.h>
#include <ucontext.h>

#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cinttypes>
#include <cstdio>
#include <cstring>
#include <map>
#include <memory>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "common/schemas.h"
#include "cuda_emu/launch.h"

namespace vrnet {
namespace emu {
namespace {

constexpr int kWarp = 32;
constexpr int kMaxThreadsPerBlock = 1024;
constexpr std::size_t kStackBytes = 64 * 1024;
constexpr std::size_t kSharedBytes = 48 * 1024;  // static + dynamic, without opt-in
constexpr std::size_t kMaxFindings = 12;         // listed per launch (all are counted)
constexpr std::size_t kGlobalShadowLimit = 64u << 20;  // bytes of tensors tracked for inter-block races
constexpr int kSecondPassWorkers = 3;

// ---------------------------------------------------------------------------------------------------
// Options and statistics (set and read from Python through the vrnet_ext_emu ops).

struct Options {
  int64_t seed = 0;
  bool sanitize = true;
  bool second_pass = true;
};
Options g_options;

struct KernelStats {
  int64_t launches = 0, blocks = 0, threads = 0;
};
std::mutex g_stats_mutex;
std::map<std::string, KernelStats> g_stats;
std::atomic<int64_t> g_launch_counter{0};

// ---------------------------------------------------------------------------------------------------
// One launch.

struct Range {
  uintptr_t lo = 0, hi = 0;
  bool contains(uintptr_t a, std::size_t n) const { return a >= lo && a + n <= hi; }
  bool overlaps(uintptr_t a, std::size_t n) const { return a < hi && a + n > lo; }
};

// Which block wrote / read each byte of a tensor argument during pass 1 (inter-block races).
struct GlobalShadow {
  std::vector<int32_t> writer, reader;  // block (linear id), -1: none, -2: several (reader only)
};

struct Launch {
  std::string name, short_name;
  dim3 grid, block;
  std::size_t dynamic_shared = 0;
  Trampoline trampoline = nullptr;
  void* params = nullptr;
  Range params_range;
  std::vector<Extent> extents;
  std::vector<Range> extent_ranges;
  std::vector<GlobalShadow> shadows;  // empty when not tracked
  int pass = 1;
  std::mutex findings_mutex;
  std::vector<std::string> findings;
  int64_t finding_count = 0;
  std::map<std::string, int> finding_kinds;  // dedup: one line per kind and site

  void report(const std::string& kind_key, const std::string& text) {
    const std::lock_guard<std::mutex> lock(findings_mutex);
    ++finding_count;
    if (finding_kinds[kind_key]++ > 0) return;
    if (findings.size() < kMaxFindings) findings.push_back(text);
  }
};

std::vector<Range> g_module_ranges;  // this module's loaded segments (static data)

// ---------------------------------------------------------------------------------------------------
// Blocks and threads.

enum class State { kRunnable, kBarrier, kWarp, kDone };

struct Thread {
  uint3 idx{};
  int linear = 0, warp = 0, lane = 0;
  State state = State::kRunnable;
  ucontext_t context{};
  Range stack;
  const void* site = nullptr;  // barrier / collective call site
  // warp collective in progress
  Collective kind = Collective::kShflIdx;
  unsigned int mask = 0;
  uint64_t value = 0, result = 0;
  int arg = 0, width = kWarp;
  // tensor-core product in progress (kMmaTf32): the lane's fragments
  uint32_t mma_a[4] = {}, mma_b[2] = {};
  float mma_d[4] = {};
};

struct SharedRegion {
  const void* tag;
  std::size_t offset, bytes;
};

struct SharedShadow {
  uint64_t serial = 0;  // block run this entry belongs to (entries of older runs are stale)
  int32_t writer = -1, reader = -1;  // thread (linear), reader -2: several
  uint32_t write_epoch = 0, read_epoch = 0;
  int32_t write_warp_epoch = 0, read_warp_epoch = 0;
};

constexpr int32_t kSeveral = -2;

// An OS thread that runs blocks: its fiber stacks, shared memory and scheduler context.
struct Worker {
  ucontext_t scheduler{};
  std::vector<char*> stacks;
  std::vector<unsigned char> shared;
  std::vector<SharedShadow> shadow;
  std::vector<SharedRegion> regions;
  std::size_t shared_used = 0;
  uint64_t serial = 0;
  Launch* launch = nullptr;
  uint3 block_idx{};
  int64_t block_linear = 0;
  std::vector<Thread> threads;
  std::vector<int32_t> warp_epochs;
  uint32_t epoch = 1;
  Thread* current = nullptr;
  bool in_kernel = false;
  bool sanitize = false;
  bool aborted = false;

  Worker() : shared(kSharedBytes), shadow(kSharedBytes) {}
  ~Worker() {
    for (char* s : stacks) std::free(s);
  }
  char* stack(int i) {
    while (static_cast<int>(stacks.size()) <= i) stacks.push_back(static_cast<char*>(std::malloc(kStackBytes)));
    return stacks[i];
  }
};

thread_local Worker* tls_worker = nullptr;

std::string str_dim(uint3 d) {
  return "(" + std::to_string(d.x) + "," + std::to_string(d.y) + "," + std::to_string(d.z) + ")";
}
std::string str_dim(dim3 d) { return str_dim(uint3{d.x, d.y, d.z}); }
std::string hex(uintptr_t a) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "0x%" PRIxPTR, a);
  return buf;
}
// "library.so+0x1a2b" (addr2line -e library.so 0x1a2b names the source line).
std::string site_name(const void* site) {
  Dl_info info;
  if (site != nullptr && dladdr(site, &info) != 0 && info.dli_fname != nullptr) {
    std::string file(info.dli_fname);
    file = file.substr(file.find_last_of('/') + 1);
    return file + "+" + hex(reinterpret_cast<uintptr_t>(site) - reinterpret_cast<uintptr_t>(info.dli_fbase));
  }
  return hex(reinterpret_cast<uintptr_t>(site));
}

// "in kernel K, block (..), thread (..)" for the executing thread.
std::string where(const Worker& w, const Thread& t) {
  return "kernel " + w.launch->short_name + ", block " + str_dim(w.block_idx) + ", thread " + str_dim(t.idx);
}

void report(Worker& w, const std::string& kind_key, const std::string& text) {
  w.launch->report(w.launch->short_name + "|" + kind_key, text);
}

// ---------------------------------------------------------------------------------------------------
// The sanitizer's view of one access by the executing thread.

void shared_access(Worker& w, Thread& t, uintptr_t address, std::size_t size, bool write) {
  const std::size_t offset = address - reinterpret_cast<uintptr_t>(w.shared.data());
  if (offset + size > w.shared_used) {
    report(w, "shared-oob", "out-of-bounds shared-memory " + std::string(write ? "write" : "read") + " of " +
                                std::to_string(size) + " bytes at shared offset " + std::to_string(offset) + " (" +
                                std::to_string(w.shared_used) + " bytes declared) in " + where(w, t));
    return;
  }
  const int32_t warp_epoch = w.warp_epochs[t.warp];
  auto same_interval = [&](uint32_t epoch, int32_t other, int32_t other_warp_epoch) {
    // no barrier between the two accesses, and no __syncwarp if both threads are in one warp
    if (epoch != w.epoch) return false;
    if (other == kSeveral) return true;
    const Thread& o = w.threads[other];
    return o.warp != t.warp || other_warp_epoch == warp_epoch;
  };
  for (std::size_t i = 0; i < size; ++i) {
    SharedShadow& s = w.shadow[offset + i];
    if (s.serial != w.serial) s = SharedShadow{w.serial};
    if (write) {
      if (s.writer >= 0 && s.writer != t.linear && same_interval(s.write_epoch, s.writer, s.write_warp_epoch)) {
        report(w, "shared-race-ww" + std::to_string(offset + i),
               "shared-memory race: write-write on shared offset " + std::to_string(offset + i) + " by threads " +
                   str_dim(w.threads[s.writer].idx) + " and " + str_dim(t.idx) +
                   " between the same two barriers in " + where(w, t));
        return;
      }
      if ((s.reader == kSeveral || (s.reader >= 0 && s.reader != t.linear)) &&
          same_interval(s.read_epoch, s.reader, s.read_warp_epoch)) {
        report(w, "shared-race-rw", "shared-memory race: write after another thread's read of shared offset " +
                                        std::to_string(offset + i) + " between the same two barriers in " + where(w, t));
        return;
      }
      s.writer = t.linear;
      s.write_epoch = w.epoch;
      s.write_warp_epoch = warp_epoch;
    } else {
      if (s.writer < 0) {
        report(w, "shared-uninit", "read of shared memory never written in this launch: shared offset " +
                                       std::to_string(offset + i) + " (address " + hex(address) + ") in " + where(w, t));
        return;
      }
      if (s.writer != t.linear && same_interval(s.write_epoch, s.writer, s.write_warp_epoch)) {
        report(w, "shared-race-wr", "shared-memory race: read of shared offset " + std::to_string(offset + i) +
                                        " written by thread " + str_dim(w.threads[s.writer].idx) +
                                        " without a barrier in between (missing __syncthreads?) in " + where(w, t));
        return;
      }
      if (s.read_epoch != w.epoch || s.reader == -1) {
        s.reader = t.linear;
        s.read_epoch = w.epoch;
        s.read_warp_epoch = warp_epoch;
      } else if (s.reader != t.linear) {
        s.reader = kSeveral;
      }
    }
  }
}

void global_access(Worker& w, Thread& t, std::size_t e, uintptr_t address, std::size_t size, bool write) {
  Launch& L = *w.launch;
  const Extent& extent = L.extents[e];
  const std::size_t offset = address - L.extent_ranges[e].lo;
  if (write && !extent.writable) {
    report(w, "readonly" + std::to_string(extent.argument),
           "write to read-only argument " + std::to_string(extent.argument) + " (a const pointer) at byte " +
               std::to_string(offset) + " in " + where(w, t));
    return;
  }
  if (L.shadows.empty()) return;
  GlobalShadow& shadow = L.shadows[e];
  const int32_t block = static_cast<int32_t>(w.block_linear);
  for (std::size_t i = offset; i < offset + size; ++i) {
    const int32_t writer = shadow.writer[i], reader = shadow.reader[i];
    if (writer >= 0 && writer != block) {
      report(w, std::string("global-race") + (write ? "w" : "r") + std::to_string(extent.argument),
             "inter-block race on argument " + std::to_string(extent.argument) + " byte " + std::to_string(i) +
                 ": " + (write ? "written" : "read") + " by block " + std::to_string(block) +
                 " after block " + std::to_string(writer) + " wrote it in the same launch, in " + where(w, t));
      return;
    }
    if (write && (reader == kSeveral || (reader >= 0 && reader != block))) {
      report(w, "global-race-rw" + std::to_string(extent.argument),
             "inter-block race on argument " + std::to_string(extent.argument) + " byte " + std::to_string(i) +
                 ": written by block " + std::to_string(block) + " after another block read it, in " + where(w, t));
      return;
    }
    if (write) shadow.writer[i] = block;
    else shadow.reader[i] = (reader == -1 || reader == block) ? block : kSeveral;
  }
}

void out_of_bounds(Worker& w, Thread& t, uintptr_t address, std::size_t size, bool write) {
  Launch& L = *w.launch;
  std::string nearest;
  uintptr_t best = UINTPTR_MAX;
  for (std::size_t e = 0; e < L.extents.size(); ++e) {
    const Range& r = L.extent_ranges[e];
    const uintptr_t gap = address >= r.hi ? address - r.hi : (address + size <= r.lo ? r.lo - address : 0);
    if (gap < best) {
      best = gap;
      const std::string side = address >= r.hi ? std::to_string(address - r.hi) + " bytes past the end of"
                               : address + size <= r.lo ? std::to_string(r.lo - address) + " bytes before"
                                                        : "straddling the end of";
      nearest = " (" + side + " argument " + std::to_string(L.extents[e].argument) + ", " +
                std::to_string(r.hi - r.lo) + " bytes)";
    }
  }
  report(w, std::string("oob") + (write ? "w" : "r"),
         "out-of-bounds global " + std::string(write ? "write" : "read") + " of " + std::to_string(size) +
             " bytes at " + hex(address) + nearest + " in " + where(w, t));
}

inline void check_access(const void* pointer, std::size_t size, bool write) {
  Worker* w = tls_worker;
  if (w == nullptr || !w->in_kernel || !w->sanitize) return;
  Thread& t = *w->current;
  const uintptr_t a = reinterpret_cast<uintptr_t>(pointer);
  if (t.stack.contains(a, size)) return;
  const uintptr_t shared_lo = reinterpret_cast<uintptr_t>(w->shared.data());
  if (a >= shared_lo && a < shared_lo + kSharedBytes) {
    shared_access(*w, t, a, size, write);
    return;
  }
  Launch& L = *w->launch;
  for (std::size_t e = 0; e < L.extent_ranges.size(); ++e) {
    if (L.extent_ranges[e].contains(a, size)) {
      global_access(*w, t, e, a, size, write);
      return;
    }
  }
  if (L.params_range.contains(a, size)) return;
  for (const Range& r : g_module_ranges)
    if (r.contains(a, size)) return;
  out_of_bounds(*w, t, a, size, write);
}

// ---------------------------------------------------------------------------------------------------
// Fibers and the block scheduler.

void fiber_entry() {
  Worker& w = *tls_worker;
  w.launch->trampoline(w.launch->params);
  w.current->state = State::kDone;
  // returning resumes the scheduler (uc_link)
}

// Suspends the executing thread until the scheduler resumes it.
void yield_to_scheduler() {
  Worker& w = *tls_worker;
  swapcontext(&w.current->context, &w.scheduler);
}

void resume(Worker& w, Thread& t) {
  w.current = &t;
  w.in_kernel = true;
  swapcontext(&w.scheduler, &t.context);
  w.in_kernel = false;
  w.current = nullptr;
}

std::string lanes_text(const std::vector<int>& lanes) {
  std::string s;
  for (std::size_t i = 0; i < lanes.size() && i < 8; ++i) s += (i ? "," : "") + std::to_string(lanes[i]);
  if (lanes.size() > 8) s += ",...";
  return s;
}

// No thread can run: either every live thread waits at __syncthreads() (release them), or the block
// is stuck (report it and abandon the block).
bool release_or_abandon(Worker& w) {
  const int T = static_cast<int>(w.threads.size());
  std::vector<int> done, barrier, collective;
  for (const Thread& t : w.threads) {
    if (t.state == State::kDone) done.push_back(t.linear);
    else if (t.state == State::kBarrier) barrier.push_back(t.linear);
    else if (t.state == State::kWarp) collective.push_back(t.linear);
  }
  if (static_cast<int>(done.size()) == T) return false;
  if (!collective.empty()) {
    const Thread& t = w.threads[collective.front()];
    std::vector<int> missing;
    for (int lane = 0; lane < kWarp; ++lane) {
      if (!(t.mask >> lane & 1u)) continue;
      const int id = t.warp * kWarp + lane;
      if (id >= T || w.threads[id].state != State::kWarp) missing.push_back(lane);
    }
    report(w, "warp-deadlock",
           "warp collective never completes: lane " + std::to_string(t.lane) + " of warp " + std::to_string(t.warp) +
               " waits with mask " + hex(t.mask) + " for lanes {" + lanes_text(missing) +
               "} that exited, do not exist or wait elsewhere (at " + site_name(t.site) + ") in " + where(w, t));
    w.aborted = true;
    return false;
  }
  const Thread& first = w.threads[barrier.front()];
  if (!done.empty()) {
    report(w, "barrier-partial",
           "__syncthreads() not reached by every thread of the block: " + std::to_string(barrier.size()) + " of " +
               std::to_string(T) + " wait at " + site_name(first.site) + ", threads {" + lanes_text(done) +
               "} (linear ids) have exited, in kernel " + w.launch->short_name + ", block " + str_dim(w.block_idx));
  }
  for (int id : barrier) {
    if (w.threads[id].site != first.site) {
      report(w, "barrier-divergent",
             "divergent __syncthreads(): thread " + str_dim(first.idx) + " waits at " + site_name(first.site) +
                 ", thread " + str_dim(w.threads[id].idx) + " at " + site_name(w.threads[id].site) + " in kernel " +
                 w.launch->short_name + ", block " + str_dim(w.block_idx));
      break;
    }
  }
  for (int id : barrier) w.threads[id].state = State::kRunnable;
  ++w.epoch;
  return true;
}

void run_block(Worker& w, Launch& L, int64_t linear_block) {
  const dim3 g = L.grid, b = L.block;
  w.block_linear = linear_block;
  w.block_idx = uint3{static_cast<unsigned>(linear_block % g.x), static_cast<unsigned>(linear_block / g.x % g.y),
                      static_cast<unsigned>(linear_block / (static_cast<int64_t>(g.x) * g.y))};
  const int T = static_cast<int>(b.x * b.y * b.z);
  w.threads.assign(T, Thread{});
  w.warp_epochs.assign((T + kWarp - 1) / kWarp, 0);
  w.regions.clear();
  w.shared_used = (L.dynamic_shared + 15) / 16 * 16;
  ++w.serial;
  w.epoch = 1;
  w.aborted = false;
  for (int i = 0; i < T; ++i) {
    Thread& t = w.threads[i];
    t.linear = i;
    t.idx = uint3{i % b.x, i / b.x % b.y, i / (b.x * b.y)};
    t.warp = i / kWarp;
    t.lane = i % kWarp;
    char* stack = w.stack(i);
    t.stack = Range{reinterpret_cast<uintptr_t>(stack), reinterpret_cast<uintptr_t>(stack) + kStackBytes};
    getcontext(&t.context);
    t.context.uc_stack.ss_sp = stack;
    t.context.uc_stack.ss_size = kStackBytes;
    t.context.uc_link = &w.scheduler;
    makecontext(&t.context, fiber_entry, 0);
  }
  for (;;) {
    bool ran = false;
    for (Thread& t : w.threads) {
      if (t.state != State::kRunnable) continue;
      resume(w, t);
      ran = true;
    }
    if (ran) continue;
    if (!release_or_abandon(w)) break;
  }
}

// ---------------------------------------------------------------------------------------------------
// Workers and the passes of a launch.

std::mutex g_workers_mutex;
std::vector<std::unique_ptr<Worker>> g_workers;  // [0]: the launching thread; others: pass 2

Worker& worker(std::size_t i) {
  const std::lock_guard<std::mutex> lock(g_workers_mutex);
  while (g_workers.size() <= i) g_workers.push_back(std::make_unique<Worker>());
  return *g_workers[i];
}

uint64_t splitmix(uint64_t& state) {
  uint64_t z = (state += 0x9e3779b97f4a7c15ull);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

void run_blocks_on(Worker& w, Launch& L, const std::vector<int64_t>& order, std::atomic<std::size_t>& next,
                   bool sanitize) {
  Worker* previous = tls_worker;
  tls_worker = &w;
  w.launch = &L;
  w.sanitize = sanitize;
  for (std::size_t i = next++; i < order.size(); i = next++) run_block(w, L, order[i]);
  w.launch = nullptr;
  tls_worker = previous;
}

std::string short_kernel_name(const std::string& full) {
  std::string s = full;
  const std::size_t lt = s.find('<');
  if (lt != std::string::npos) s = s.substr(0, lt);
  const std::size_t colon = s.rfind("::");
  if (colon != std::string::npos) s = s.substr(colon + 2);
  s.erase(std::remove_if(s.begin(), s.end(), [](char c) { return c == '&' || c == '(' || c == ' '; }), s.end());
  return s;
}

std::string instantiation_name(const char* pretty) {
  std::string s(pretty);
  const std::size_t at = s.find("Kernel = ");
  if (at == std::string::npos) return s;
  s = s.substr(at + 9);
  const std::size_t end = s.find_last_of(']');
  return end == std::string::npos ? s : s.substr(0, end);
}

void check_config(const std::string& name, dim3 grid, dim3 block, std::size_t shared_bytes) {
  const int64_t threads = static_cast<int64_t>(block.x) * block.y * block.z;
  TORCH_CHECK(threads >= 1 && threads <= kMaxThreadsPerBlock && block.z <= 64,
              "cuda_emu: invalid launch of ", name, ": block ", str_dim(block), " (1 to 1024 threads, z <= 64)");
  TORCH_CHECK(grid.x >= 1 && grid.y >= 1 && grid.z >= 1 && grid.y <= 65535 && grid.z <= 65535 &&
                  grid.x <= 2147483647u,
              "cuda_emu: invalid launch of ", name, ": grid ", str_dim(grid));
  TORCH_CHECK(shared_bytes <= kSharedBytes, "cuda_emu: launch of ", name, " asks for ", shared_bytes,
              " bytes of dynamic shared memory (at most ", kSharedBytes, ")");
}

void find_module_ranges() {
  static std::once_flag once;
  std::call_once(once, [] {
    Dl_info info;
    if (dladdr(reinterpret_cast<void*>(&find_module_ranges), &info) == 0) return;
    dl_iterate_phdr(
        [](dl_phdr_info* phdr, std::size_t, void* base) -> int {
          if (reinterpret_cast<void*>(phdr->dlpi_addr) != base) return 0;
          for (int i = 0; i < phdr->dlpi_phnum; ++i) {
            const ElfW(Phdr)& h = phdr->dlpi_phdr[i];
            if (h.p_type != PT_LOAD) continue;
            const uintptr_t lo = phdr->dlpi_addr + h.p_vaddr;
            g_module_ranges.push_back(Range{lo, lo + h.p_memsz});
          }
          return 1;
        },
        info.dli_fbase);
  });
}

}  // namespace

void launch_kernel(const char* pretty, Trampoline trampoline, void* params, std::size_t params_bytes, dim3 grid,
                   dim3 block, std::size_t shared_bytes, const std::vector<Extent>& extents) {
  find_module_ranges();
  Launch L;
  L.name = instantiation_name(pretty);
  L.short_name = short_kernel_name(L.name);
  check_config(L.name, grid, block, shared_bytes);
  TORCH_CHECK(tls_worker == nullptr, "cuda_emu: a kernel launched another kernel (", L.short_name, ")");
  L.grid = grid;
  L.block = block;
  L.dynamic_shared = shared_bytes;
  L.trampoline = trampoline;
  L.params = params;
  L.params_range = Range{reinterpret_cast<uintptr_t>(params), reinterpret_cast<uintptr_t>(params) + params_bytes};
  L.extents = extents;
  std::size_t total = 0;
  for (const Extent& e : extents) {
    const uintptr_t lo = reinterpret_cast<uintptr_t>(e.base);
    L.extent_ranges.push_back(Range{lo, lo + e.bytes});
    total += e.bytes;
  }
  const int64_t blocks = static_cast<int64_t>(grid.x) * grid.y * grid.z;
  const int64_t threads = static_cast<int64_t>(block.x) * block.y * block.z;
  {
    const std::lock_guard<std::mutex> lock(g_stats_mutex);
    KernelStats& s = g_stats[L.short_name];
    s.launches += 1;
    s.blocks += blocks;
    s.threads += blocks * threads;
  }
  if (g_options.sanitize && total <= kGlobalShadowLimit) {
    for (const Extent& e : extents) L.shadows.push_back(GlobalShadow{std::vector<int32_t>(e.bytes, -1),
                                                                     std::vector<int32_t>(e.bytes, -1)});
  }
  // Writable tensors before the launch, to run pass 2 on the same inputs.
  std::vector<std::vector<unsigned char>> before;
  const bool second_pass = g_options.second_pass && blocks > 1;
  if (second_pass) {
    for (const Extent& e : extents) {
      const auto* p = static_cast<const unsigned char*>(e.base);
      before.emplace_back(e.writable ? std::vector<unsigned char>(p, p + e.bytes) : std::vector<unsigned char>());
    }
  }
  // Pass 1: blocks one at a time in a seeded random order, with the sanitizer.
  uint64_t state = static_cast<uint64_t>(g_options.seed) * 0x100000001b3ull + static_cast<uint64_t>(g_launch_counter++);
  std::vector<int64_t> order(blocks);
  for (int64_t i = 0; i < blocks; ++i) order[i] = i;
  for (int64_t i = blocks - 1; i > 0; --i) std::swap(order[i], order[splitmix(state) % static_cast<uint64_t>(i + 1)]);
  {
    std::atomic<std::size_t> next{0};
    run_blocks_on(worker(0), L, order, next, g_options.sanitize);
  }
  if (second_pass && L.finding_count == 0) {
    // Pass 2: the same launch on the restored tensors, blocks concurrently in the reverse order.
    std::vector<std::vector<unsigned char>> first;
    for (std::size_t e = 0; e < extents.size(); ++e) {
      if (!extents[e].writable) {
        first.emplace_back();
        continue;
      }
      auto* p = static_cast<unsigned char*>(const_cast<void*>(extents[e].base));
      first.emplace_back(p, p + extents[e].bytes);
      std::memcpy(p, before[e].data(), extents[e].bytes);
    }
    std::reverse(order.begin(), order.end());
    std::atomic<std::size_t> next{0};
    const int workers = static_cast<int>(std::min<int64_t>(kSecondPassWorkers, blocks));
    std::vector<Worker*> pool;
    for (int i = 0; i < workers; ++i) pool.push_back(&worker(1 + i));
    std::vector<std::thread> os_threads;
    for (int i = 0; i < workers; ++i)
      os_threads.emplace_back([&, i] { run_blocks_on(*pool[i], L, order, next, false); });
    for (std::thread& t : os_threads) t.join();
    for (std::size_t e = 0; e < extents.size(); ++e) {
      if (!extents[e].writable) continue;
      auto* p = static_cast<unsigned char*>(const_cast<void*>(extents[e].base));
      const auto mismatch = std::mismatch(first[e].begin(), first[e].end(), p);
      if (mismatch.first != first[e].end()) {
        L.report("order" + std::to_string(e),
                 "results depend on the order of blocks: argument " + std::to_string(extents[e].argument) +
                     " differs at byte " + std::to_string(mismatch.first - first[e].begin()) +
                     " between blocks in a seeded order and blocks run concurrently in kernel " + L.short_name +
                     " (a race between blocks, or an order-dependent reduction)");
      }
      std::memcpy(p, first[e].data(), extents[e].bytes);
    }
  }
  if (L.finding_count > 0) {
    std::ostringstream message;
    message << "cuda_emu: " << L.finding_count << " finding(s) in kernel " << L.name << " (grid " << str_dim(grid)
            << ", block " << str_dim(block) << "):";
    for (const std::string& f : L.findings) message << "\n  " << f;
    TORCH_CHECK(false, message.str());
  }
}

// ---------------------------------------------------------------------------------------------------
// The CUDA built-ins.

namespace {
Worker& in_kernel(const char* what) {
  Worker* w = tls_worker;
  TORCH_CHECK(w != nullptr && w->current != nullptr, "cuda_emu: ", what, " called outside a kernel");
  return *w;
}
}  // namespace

uint3 thread_index() { return in_kernel("threadIdx").current->idx; }
uint3 block_index() { return in_kernel("blockIdx").block_idx; }
dim3 block_dimensions() { return in_kernel("blockDim").launch->block; }
dim3 grid_dimensions() { return in_kernel("gridDim").launch->grid; }

void* dynamic_shared_region() {
  Worker& w = in_kernel("extern __shared__");
  return w.shared.data();
}

void* shared_region(const void* tag, std::size_t bytes, std::size_t align) {
  Worker& w = in_kernel("__shared__");
  for (const SharedRegion& r : w.regions)
    if (r.tag == tag) return w.shared.data() + r.offset;
  const std::size_t offset = (w.shared_used + std::max<std::size_t>(align, 16) - 1) / std::max<std::size_t>(align, 16) *
                             std::max<std::size_t>(align, 16);
  TORCH_CHECK(offset + bytes <= kSharedBytes, "cuda_emu: kernel ", w.launch->short_name,
              " declares more than ", kSharedBytes, " bytes of shared memory");
  w.regions.push_back(SharedRegion{tag, offset, bytes});
  w.shared_used = offset + bytes;
  return w.shared.data() + offset;
}

__attribute__((noinline)) void sync_threads() {
  Worker& w = in_kernel("__syncthreads");
  w.current->site = __builtin_return_address(0);
  w.current->state = State::kBarrier;
  yield_to_scheduler();
}

namespace {

bool valid_width(int width) { return width >= 1 && width <= kWarp && (width & (width - 1)) == 0; }

float tf32_operand(uint32_t bits) {
  bits &= 0xffffe000u;  // the tensor cores read 1 + 8 + 10 bits of each operand
  float x;
  std::memcpy(&x, &bits, sizeof x);
  return x;
}

// Every lane of the warp has passed its fragments of one m16n8k8 TF32 product (the PTX ISA's layout:
// groupID g = lane / 4, t = lane % 4; A (row, k): a0 (g, t), a1 (g + 8, t), a2 (g, t + 4),
// a3 (g + 8, t + 4); B (k, col): b0 (t, g), b1 (t + 4, g); D (row, col): d0 (g, 2t), d1 (g, 2t + 1),
// d2 (g + 8, 2t), d3 (g + 8, 2t + 1)): every lane's d += a b. (Lanes that never arrive are reported as
// for any collective of the full warp.)
void resolve_mma(Worker& w, Thread& last) {
  const int first = last.warp * kWarp;
  for (int id = first; id < first + kWarp; ++id) {
    if (w.threads[id].kind != Collective::kMmaTf32 || w.threads[id].mask != last.mask) {
      report(w, "collective-mismatch", "lanes of warp " + std::to_string(last.warp) +
                                           " meet at a tensor-core product and another collective in " +
                                           where(w, w.threads[id]));
    }
  }
  auto a = [&](int row, int k) {
    const Thread& t = w.threads[first + (row % 8) * 4 + k % 4];
    return tf32_operand(t.mma_a[(row >= 8 ? 1 : 0) + (k >= 4 ? 2 : 0)]);
  };
  auto b = [&](int k, int col) { return tf32_operand(w.threads[first + col * 4 + k % 4].mma_b[k >= 4 ? 1 : 0]); };
  float result[kWarp][4];
  for (int lane = 0; lane < kWarp; ++lane) {
    const int g = lane / 4, t = lane % 4;
    for (int i = 0; i < 4; ++i) {
      const int row = g + 8 * (i / 2), col = 2 * t + i % 2;
      float sum = w.threads[first + lane].mma_d[i];
      for (int k = 0; k < 8; ++k) sum += a(row, k) * b(k, col);
      result[lane][i] = sum;
    }
  }
  for (int lane = 0; lane < kWarp; ++lane) {
    Thread& t = w.threads[first + lane];
    std::memcpy(t.mma_d, result[lane], sizeof t.mma_d);
    t.state = State::kRunnable;
  }
}

// The lanes of mask have all arrived: compute every lane's result and wake them.
void resolve(Worker& w, Thread& last) {
  if (last.kind == Collective::kMmaTf32) {
    resolve_mma(w, last);
    return;
  }
  const int T = static_cast<int>(w.threads.size());
  const unsigned int mask = last.mask;
  unsigned int ballot = 0;
  int votes = 0, lanes = 0;
  for (int lane = 0; lane < kWarp; ++lane) {
    if (!(mask >> lane & 1u)) continue;
    const int id = last.warp * kWarp + lane;
    if (id >= T) continue;
    Thread& t = w.threads[id];
    if (t.kind != last.kind || t.mask != mask) {
      report(w, "collective-mismatch",
             "lanes of warp " + std::to_string(last.warp) + " meet at different warp collectives or masks (lane " +
                 std::to_string(t.lane) + " mask " + hex(t.mask) + ", lane " + std::to_string(last.lane) + " mask " +
                 hex(mask) + ") in " + where(w, t));
    }
    ++lanes;
    if (t.value != 0) {
      ballot |= 1u << lane;
      ++votes;
    }
  }
  for (int lane = 0; lane < kWarp; ++lane) {
    if (!(mask >> lane & 1u)) continue;
    const int id = last.warp * kWarp + lane;
    if (id >= T) continue;
    Thread& t = w.threads[id];
    switch (t.kind) {
      case Collective::kBallot: t.result = ballot; break;
      case Collective::kAny: t.result = votes > 0; break;
      case Collective::kAll: t.result = votes == lanes; break;
      case Collective::kSyncWarp: t.result = 0; break;
      default: {
        const int width = valid_width(t.width) ? t.width : kWarp;
        const int base = lane / width * width;
        int source = lane;
        if (t.kind == Collective::kShflIdx) source = base + ((t.arg % width) + width) % width;
        else if (t.kind == Collective::kShflUp) source = lane - t.arg >= base ? lane - t.arg : lane;
        else if (t.kind == Collective::kShflDown) source = lane + t.arg < base + width ? lane + t.arg : lane;
        else source = (lane ^ t.arg) < base + width ? (lane ^ t.arg) : lane;
        const int source_id = last.warp * kWarp + source;
        if (source < 0 || source >= kWarp || !(mask >> source & 1u) || source_id >= T) {
          report(w, "shfl-source", "warp shuffle reads lane " + std::to_string(source) +
                                       ", which is not in the mask " + hex(mask) + ", in " + where(w, t));
          t.result = t.value;
        } else {
          t.result = w.threads[source_id].value;
        }
      }
    }
    if (&t != &last) t.state = State::kRunnable;
  }
  if (last.kind == Collective::kSyncWarp) ++w.warp_epochs[last.warp];
  last.state = State::kRunnable;
}

// The executing lane arrives at a collective; returns when every lane of the mask has arrived.
void arrive(Worker& w, Collective kind, unsigned int mask, uint64_t value, int arg, int width, const void* site) {
  Thread& t = *w.current;
  t.kind = kind;
  t.mask = mask;
  t.value = value;
  t.arg = arg;
  t.width = width;
  t.site = site;
  if (!(mask >> t.lane & 1u)) {
    report(w, "mask-self", "warp collective with mask " + hex(mask) + " that does not name the calling lane " +
                               std::to_string(t.lane) + " in " + where(w, t));
  }
  if (kind <= Collective::kShflXor && !valid_width(width)) {
    report(w, "shfl-width", "warp shuffle with width " + std::to_string(width) +
                                " (must be a power of two from 1 to 32) in " + where(w, t));
  }
  t.state = State::kWarp;
  const int T = static_cast<int>(w.threads.size());
  for (int lane = 0; lane < kWarp; ++lane) {
    if (!(mask >> lane & 1u)) continue;
    const int id = t.warp * kWarp + lane;
    if (id >= T || w.threads[id].state != State::kWarp) {
      yield_to_scheduler();  // resolved by the last lane to arrive
      return;
    }
  }
  resolve(w, t);
}

}  // namespace

__attribute__((noinline)) void warp_collective(Collective kind, unsigned int mask, const void* value,
                                               std::size_t size, int arg, int width, void* result) {
  Worker& w = in_kernel("a warp shuffle");
  uint64_t bits = 0;
  std::memcpy(&bits, value, size);
  arrive(w, kind, mask, bits, arg, width, __builtin_return_address(0));
  std::memcpy(result, &w.current->result, size);
}

__attribute__((noinline)) unsigned int warp_vote(Collective kind, unsigned int mask, int predicate) {
  Worker& w = in_kernel("a warp vote");
  arrive(w, kind, mask, predicate != 0, 0, kWarp, __builtin_return_address(0));
  return static_cast<unsigned int>(w.current->result);
}

__attribute__((noinline)) void mma_m16n8k8_tf32(float (&d)[4], const uint32_t (&a)[4], const uint32_t (&b)[2]) {
  Worker& w = in_kernel("mma.sync");
  Thread& t = *w.current;
  std::memcpy(t.mma_a, a, sizeof t.mma_a);
  std::memcpy(t.mma_b, b, sizeof t.mma_b);
  std::memcpy(t.mma_d, d, sizeof t.mma_d);
  arrive(w, Collective::kMmaTf32, 0xffffffffu, 0, 0, kWarp, __builtin_return_address(0));
  std::memcpy(d, w.current->mma_d, sizeof t.mma_d);
}

__attribute__((noinline)) void sync_warp(unsigned int mask) {
  Worker& w = in_kernel("__syncwarp");
  arrive(w, Collective::kSyncWarp, mask, 0, 0, kWarp, __builtin_return_address(0));
}

unsigned int active_mask() {
  Worker& w = in_kernel("__activemask");
  const Thread& t = *w.current;
  unsigned int mask = 0;
  for (int lane = 0; lane < kWarp; ++lane) {
    const int id = t.warp * kWarp + lane;
    if (id < static_cast<int>(w.threads.size()) && w.threads[id].state != State::kDone) mask |= 1u << lane;
  }
  return mask;
}

// Atomics: a checked read-modify-write that never counts as a race.
namespace {
template <typename T, typename F>
T atomic_update(T* address, F op) {
  Worker* w = tls_worker;
  if (w != nullptr && w->in_kernel && w->sanitize) {
    const uintptr_t a = reinterpret_cast<uintptr_t>(address);
    Thread& t = *w->current;
    const uintptr_t shared_lo = reinterpret_cast<uintptr_t>(w->shared.data());
    bool known = (a >= shared_lo && a + sizeof(T) <= shared_lo + w->shared_used);
    for (std::size_t e = 0; !known && e < w->launch->extent_ranges.size(); ++e) {
      if (w->launch->extent_ranges[e].contains(a, sizeof(T))) {
        known = true;
        if (!w->launch->extents[e].writable)
          report(*w, "atomic-readonly", "atomic on read-only argument " +
                                            std::to_string(w->launch->extents[e].argument) + " in " + where(*w, t));
      }
    }
    if (!known) {
      out_of_bounds(*w, t, a, sizeof(T), true);
      return T{};
    }
    if (a >= shared_lo && a < shared_lo + kSharedBytes) {  // counts as written (initialised)
      for (std::size_t i = 0; i < sizeof(T); ++i) {
        SharedShadow& s = w->shadow[a - shared_lo + i];
        if (s.serial != w->serial) s = SharedShadow{w->serial};
        if (s.writer < 0) s.writer = t.linear;
      }
    }
  }
  T expected;
  __atomic_load(address, &expected, __ATOMIC_SEQ_CST);
  for (;;) {
    const T desired = op(expected);
    if (__atomic_compare_exchange(address, &expected, &desired, false, __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST))
      return expected;
  }
}
}  // namespace

float atomic_add(float* a, float v) { return atomic_update(a, [v](float x) { return x + v; }); }
double atomic_add(double* a, double v) { return atomic_update(a, [v](double x) { return x + v; }); }
int atomic_add(int* a, int v) {
  return atomic_update(a, [v](int x) { return static_cast<int>(static_cast<unsigned>(x) + static_cast<unsigned>(v)); });
}
unsigned int atomic_add(unsigned int* a, unsigned int v) { return atomic_update(a, [v](unsigned x) { return x + v; }); }
unsigned long long atomic_add(unsigned long long* a, unsigned long long v) {
  return atomic_update(a, [v](unsigned long long x) { return x + v; });
}
int atomic_max(int* a, int v) { return atomic_update(a, [v](int x) { return std::max(x, v); }); }
int atomic_min(int* a, int v) { return atomic_update(a, [v](int x) { return std::min(x, v); }); }
unsigned int atomic_max(unsigned int* a, unsigned int v) { return atomic_update(a, [v](unsigned x) { return std::max(x, v); }); }
unsigned int atomic_min(unsigned int* a, unsigned int v) { return atomic_update(a, [v](unsigned x) { return std::min(x, v); }); }
long long atomic_max(long long* a, long long v) { return atomic_update(a, [v](long long x) { return std::max(x, v); }); }
long long atomic_min(long long* a, long long v) { return atomic_update(a, [v](long long x) { return std::min(x, v); }); }
int atomic_cas(int* a, int c, int v) { return atomic_update(a, [c, v](int x) { return x == c ? v : x; }); }
unsigned int atomic_cas(unsigned int* a, unsigned int c, unsigned int v) {
  return atomic_update(a, [c, v](unsigned x) { return x == c ? v : x; });
}
unsigned long long atomic_cas(unsigned long long* a, unsigned long long c, unsigned long long v) {
  return atomic_update(a, [c, v](unsigned long long x) { return x == c ? v : x; });
}
int atomic_exch(int* a, int v) { return atomic_update(a, [v](int) { return v; }); }
unsigned int atomic_exch(unsigned int* a, unsigned int v) { return atomic_update(a, [v](unsigned) { return v; }); }
float atomic_exch(float* a, float v) { return atomic_update(a, [v](float) { return v; }); }

// ---------------------------------------------------------------------------------------------------
// Control from Python.

namespace {

void configure(int64_t seed, bool sanitize, bool second_pass) {
  g_options.seed = seed;
  g_options.sanitize = sanitize;
  g_options.second_pass = second_pass;
}

// One line per kernel: "name launches blocks threads".
std::string stats() {
  const std::lock_guard<std::mutex> lock(g_stats_mutex);
  std::ostringstream out;
  for (const auto& [name, s] : g_stats) out << name << ' ' << s.launches << ' ' << s.blocks << ' ' << s.threads << '\n';
  return out.str();
}

void reset_stats() {
  const std::lock_guard<std::mutex> lock(g_stats_mutex);
  g_stats.clear();
}

}  // namespace

}  // namespace emu
}  // namespace vrnet

// The test library: vrnet_ext's schemas (the CUDA glue registers CPU kernels for them) and the
// emulator's controls.
TORCH_LIBRARY(vrnet_ext_emu, m) {
#define VRNET_DEFINE(schema) m.def(schema);
  VRNET_OP_SCHEMAS(VRNET_DEFINE)
#undef VRNET_DEFINE
  m.def("emu_configure(int seed, bool sanitize, bool second_pass) -> ()", &vrnet::emu::configure);
  m.def("emu_stats() -> str", &vrnet::emu::stats);
  m.def("emu_reset_stats() -> ()", &vrnet::emu::reset_stats);
}

// ---------------------------------------------------------------------------------------------------
// The hooks that -fsanitize=thread instrumentation calls (the subset GCC emits for this code).

extern "C" {
#define VRNET_EMU_ACCESS(n)                                                                          \
  void __tsan_read##n(void* a) { vrnet::emu::check_access(a, n, false); }                            \
  void __tsan_write##n(void* a) { vrnet::emu::check_access(a, n, true); }                            \
  void __tsan_unaligned_read##n(void* a) { vrnet::emu::check_access(a, n, false); }                  \
  void __tsan_unaligned_write##n(void* a) { vrnet::emu::check_access(a, n, true); }                  \
  void __tsan_volatile_read##n(void* a) { vrnet::emu::check_access(a, n, false); }                   \
  void __tsan_volatile_write##n(void* a) { vrnet::emu::check_access(a, n, true); }                   \
  void __tsan_read##n##_pc(void* a, void*) { vrnet::emu::check_access(a, n, false); }                \
  void __tsan_write##n##_pc(void* a, void*) { vrnet::emu::check_access(a, n, true); }
VRNET_EMU_ACCESS(1)
VRNET_EMU_ACCESS(2)
VRNET_EMU_ACCESS(4)
VRNET_EMU_ACCESS(8)
VRNET_EMU_ACCESS(16)
#undef VRNET_EMU_ACCESS

void __tsan_read_range(void* a, unsigned long n) { vrnet::emu::check_access(a, n, false); }
void __tsan_write_range(void* a, unsigned long n) { vrnet::emu::check_access(a, n, true); }
void __tsan_func_entry(void*) {}
void __tsan_func_exit() {}
void __tsan_init() {}
void __tsan_vptr_update(void**, void*) {}
void __tsan_vptr_read(void**) {}
void __tsan_ignore_thread_begin() {}
void __tsan_ignore_thread_end() {}
void __tsan_acquire(void*) {}
void __tsan_release(void*) {}
void __tsan_mutex_create(void*, unsigned) {}
void __tsan_mutex_destroy(void*, unsigned) {}
void __tsan_mutex_pre_lock(void*, unsigned) {}
void __tsan_mutex_post_lock(void*, unsigned, int) {}
int __tsan_mutex_pre_unlock(void*, unsigned) { return 0; }
void __tsan_mutex_post_unlock(void*, unsigned) {}
void __tsan_mutex_pre_signal(void*, unsigned) {}
void __tsan_mutex_post_signal(void*, unsigned) {}
void __tsan_mutex_pre_divert(void*, unsigned) {}
void __tsan_mutex_post_divert(void*, unsigned) {}
void __tsan_atomic_thread_fence(int) { __atomic_thread_fence(__ATOMIC_SEQ_CST); }
void __tsan_atomic_signal_fence(int) { __atomic_signal_fence(__ATOMIC_SEQ_CST); }

// Atomic operations of instrumented code (e.g. torch's reference counts): performed for real.
#define VRNET_EMU_ATOMICS(bits, type)                                                                   \
  type __tsan_atomic##bits##_load(const volatile type* a, int) { return __atomic_load_n(a, __ATOMIC_SEQ_CST); } \
  void __tsan_atomic##bits##_store(volatile type* a, type v, int) { __atomic_store_n(a, v, __ATOMIC_SEQ_CST); } \
  type __tsan_atomic##bits##_exchange(volatile type* a, type v, int) {                                 \
    return __atomic_exchange_n(a, v, __ATOMIC_SEQ_CST);                                                 \
  }                                                                                                     \
  type __tsan_atomic##bits##_fetch_add(volatile type* a, type v, int) {                                \
    return __atomic_fetch_add(a, v, __ATOMIC_SEQ_CST);                                                  \
  }                                                                                                     \
  type __tsan_atomic##bits##_fetch_sub(volatile type* a, type v, int) {                                \
    return __atomic_fetch_sub(a, v, __ATOMIC_SEQ_CST);                                                  \
  }                                                                                                     \
  type __tsan_atomic##bits##_fetch_and(volatile type* a, type v, int) {                                \
    return __atomic_fetch_and(a, v, __ATOMIC_SEQ_CST);                                                  \
  }                                                                                                     \
  type __tsan_atomic##bits##_fetch_or(volatile type* a, type v, int) {                                 \
    return __atomic_fetch_or(a, v, __ATOMIC_SEQ_CST);                                                   \
  }                                                                                                     \
  type __tsan_atomic##bits##_fetch_xor(volatile type* a, type v, int) {                                \
    return __atomic_fetch_xor(a, v, __ATOMIC_SEQ_CST);                                                  \
  }                                                                                                     \
  type __tsan_atomic##bits##_fetch_nand(volatile type* a, type v, int) {                               \
    return __atomic_fetch_nand(a, v, __ATOMIC_SEQ_CST);                                                 \
  }                                                                                                     \
  int __tsan_atomic##bits##_compare_exchange_strong(volatile type* a, type* c, type v, int, int) {     \
    return __atomic_compare_exchange_n(a, c, v, false, __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST);             \
  }                                                                                                     \
  int __tsan_atomic##bits##_compare_exchange_weak(volatile type* a, type* c, type v, int, int) {       \
    return __atomic_compare_exchange_n(a, c, v, true, __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST);              \
  }                                                                                                     \
  type __tsan_atomic##bits##_compare_exchange_val(volatile type* a, type c, type v, int, int) {        \
    __atomic_compare_exchange_n(a, &c, v, false, __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST);                   \
    return c;                                                                                           \
  }
VRNET_EMU_ATOMICS(8, unsigned char)
VRNET_EMU_ATOMICS(16, unsigned short)
VRNET_EMU_ATOMICS(32, unsigned int)
VRNET_EMU_ATOMICS(64, unsigned long long)
#undef VRNET_EMU_ATOMICS
}
