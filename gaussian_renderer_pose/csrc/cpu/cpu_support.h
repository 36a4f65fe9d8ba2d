// Host-only helpers of the CPU kernel (rasterize_cpu.cpp, binning.h): fixed-chunk parallel loops,
// per-thread scratch memory reused between calls, and the optional phase timer.
#pragma once

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <sys/mman.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <new>
#include <mutex>
#include <string>
#include <vector>

namespace grp {
namespace cpu {

// Number of chunks for a loop over n items: one per ATen thread, at most one per `min_items`
// items (at least 1). Results never depend on it (every chunked step has a unique answer).
inline int num_chunks(int64_t n, int64_t min_items) {
  const int64_t by_size = std::max<int64_t>(1, n / std::max<int64_t>(1, min_items));
  return (int)std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), by_size));
}

// First item of chunk c of n items split into nchunks near-equal contiguous chunks.
inline int64_t chunk_begin(int64_t n, int c, int nchunks) { return n * c / nchunks; }

// Runs fn(c) for every chunk c in [0, nchunks) on the ATen pool (serially inside a parallel
// region or for a single chunk).
template <typename F>
void for_each_chunk(int nchunks, const F& fn) {
  if (nchunks <= 1 || at::in_parallel_region()) {
    for (int c = 0; c < nchunks; ++c) fn(c);
    return;
  }
  at::parallel_for(0, nchunks, 1, [&](int64_t b, int64_t e) {
    for (int64_t c = b; c < e; ++c) fn((int)c);
  });
}

// The size of the block alloc_huge gives for `bytes`: at least 2 MiB, a multiple of 2 MiB.
inline size_t huge_size(size_t bytes) {
  const size_t huge = size_t(2) << 20;
  return (std::max(bytes, huge) + huge - 1) / huge * huge;
}

// Memory of 2 MiB or more, 2 MiB aligned and advised as transparent huge pages; nullptr on
// failure. *bytes is rounded up to huge_size(*bytes).
inline void* alloc_huge(size_t* bytes) {
  const size_t huge = size_t(2) << 20;
  *bytes = huge_size(*bytes);
  void* p = std::aligned_alloc(huge, *bytes);
#if defined(MADV_HUGEPAGE)
  if (p != nullptr) madvise(p, *bytes, MADV_HUGEPAGE);
#endif
  return p;
}

// An uninitialised array of trivially copyable T that keeps its memory between calls (one per
// thread and use: see thread_local users), so that a render of a large model does not page-fault
// and zero fresh memory for its temporaries every call. Grows, never shrinks; blocks of 2 MiB or
// more are 2 MiB aligned and advised as transparent huge pages.
template <typename T>
class ScratchArray {
 public:
  ScratchArray() = default;
  ScratchArray(const ScratchArray&) = delete;
  ScratchArray& operator=(const ScratchArray&) = delete;
  ~ScratchArray() { std::free(data_); }

  // At least n elements (contents unspecified).
  T* get(size_t n) {
    if (n > capacity_) {
      size_t bytes = std::max(n, capacity_ + capacity_ / 2) * sizeof(T);
      std::free(data_);
      data_ = nullptr;
      capacity_ = 0;
      if (bytes >= (size_t(2) << 20)) {
        data_ = static_cast<T*>(alloc_huge(&bytes));
      } else {
        bytes = (std::max<size_t>(bytes, 64) + 63) / 64 * 64;
        data_ = static_cast<T*>(std::aligned_alloc(64, bytes));
      }
      if (data_ == nullptr) throw std::bad_alloc();
      capacity_ = bytes / sizeof(T);
    }
    return data_;
  }

 private:
  T* data_ = nullptr;
  size_t capacity_ = 0;
};

// A process-wide cache of freed blocks for the large outputs of the CPU kernel (the forward's
// saved state and images, the backward's gradients). A fresh block costs a page fault and a
// zero-fill per 4 KiB page when first written (about 40 ns a Gaussian for the 64-byte geom
// records alone); a block handed back by a dead tensor does not. At most kMaxCachedBytes are
// kept (the environment variable GRP_CPU_CACHE_MB, read once, overrides it; 0 disables the
// cache). Thread-safe; never destroyed (tensors may die after static destructors have run).
class BlockCache {
 public:
  static BlockCache& instance() {
    static BlockCache* cache = new BlockCache();
    return *cache;
  }

  // An uninitialised tensor of `sizes` and `options` (CPU); blocks under kMinBytes come from
  // at::empty.
  at::Tensor empty(at::IntArrayRef sizes, const at::TensorOptions& options) {
    int64_t numel = 1;
    for (int64_t s : sizes) numel *= s;
    size_t bytes = (size_t)numel * at::elementSize(at::typeMetaToScalarType(options.dtype()));
    if (limit_ == 0 || bytes < kMinBytes) return at::empty(sizes, options);
    // Blocks are whole huge pages: match on the size alloc_huge would give, so that a request
    // just over a multiple of 2 MiB finds the block of the same request again.
    bytes = huge_size(bytes);
    void* p = take(&bytes);
    if (p == nullptr) p = alloc_huge(&bytes);
    if (p == nullptr) return at::empty(sizes, options);
    return at::from_blob(p, sizes, [this, bytes](void* q) { give(q, bytes); }, options);
  }

 private:
  static constexpr size_t kMinBytes = size_t(1) << 20;
  static constexpr size_t kMaxCachedBytes = size_t(1) << 30;

  BlockCache() {
    const char* env = std::getenv("GRP_CPU_CACHE_MB");
    limit_ = env != nullptr ? (size_t)std::strtoull(env, nullptr, 10) << 20 : kMaxCachedBytes;
  }

  // A cached block of at least *bytes and at most 5/4 of it (*bytes set to its size), or nullptr.
  void* take(size_t* bytes) {
    std::lock_guard<std::mutex> lock(mutex_);
    size_t best = blocks_.size();
    for (size_t i = 0; i < blocks_.size(); ++i) {
      const size_t b = blocks_[i].bytes;
      if (b >= *bytes && b <= *bytes + *bytes / 4 &&
          (best == blocks_.size() || b < blocks_[best].bytes))
        best = i;
    }
    if (best == blocks_.size()) return nullptr;
    Block blk = blocks_[best];
    blocks_.erase(blocks_.begin() + best);
    cached_ -= blk.bytes;
    *bytes = blk.bytes;
    return blk.ptr;
  }

  // Keeps the block, evicting the oldest ones beyond the limit.
  void give(void* p, size_t bytes) {
    std::vector<void*> evicted;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      blocks_.push_back({p, bytes});
      cached_ += bytes;
      while (cached_ > limit_ && !blocks_.empty()) {
        evicted.push_back(blocks_.front().ptr);
        cached_ -= blocks_.front().bytes;
        blocks_.erase(blocks_.begin());
      }
    }
    for (void* q : evicted) std::free(q);
  }

  struct Block {
    void* ptr;
    size_t bytes;
  };
  std::mutex mutex_;
  std::vector<Block> blocks_;  // oldest first
  size_t cached_ = 0;
  size_t limit_ = 0;
};

// Wall time of the phases of one call, printed to stderr when the environment variable
// GRP_CPU_TIMING is set (read once per process): "grp cpu <what> P=<P> <W>x<H> threads=<n>:
// phase ms ...". Otherwise every member is a no-op.
class PhaseTimer {
 public:
  PhaseTimer(const char* what, int64_t P, int W, int H) {
    static const bool enabled = std::getenv("GRP_CPU_TIMING") != nullptr;
    if (!enabled) return;
    on_ = true;
    line_ = std::string("grp cpu ") + what + " P=" + std::to_string(P) + " " + std::to_string(W) +
            "x" + std::to_string(H) + " threads=" + std::to_string(at::get_num_threads()) + ":";
    last_ = start_ = Clock::now();
  }
  PhaseTimer(const PhaseTimer&) = delete;
  PhaseTimer& operator=(const PhaseTimer&) = delete;

  // Ends the phase `name` (time since the previous mark, or since construction).
  void mark(const char* name) {
    if (!on_) return;
    const auto now = Clock::now();
    append(name, now - last_);
    last_ = now;
  }

  ~PhaseTimer() {
    if (!on_) return;
    append("total", Clock::now() - start_);
    std::fprintf(stderr, "%s\n", line_.c_str());
  }

 private:
  using Clock = std::chrono::steady_clock;
  void append(const char* name, Clock::duration d) {
    char buf[64];
    std::snprintf(buf, sizeof(buf), " %s %.2f", name,
                  std::chrono::duration<double, std::milli>(d).count());
    line_ += buf;
  }
  bool on_ = false;
  std::string line_;
  Clock::time_point start_, last_;
};

}  // namespace cpu
}  // namespace grp
