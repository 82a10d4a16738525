// Threading: how the sensor elements are dealt to the threads (static chunks, so sums are deterministic for a given
// thread count), the data-parallel share of this process, and the per-chunk gradient buffers with their reduction in
// chunk order. The element loops stop early on Ctrl-C (volpath/interrupt.h).
#pragma once

#include <ATen/Parallel.h>
#include <c10/util/Exception.h>

#include <sys/mman.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <memory>
#include <vector>

#include "core/integrator.h"
#include "core/replay.h"
#include "volpath/interrupt.h"

namespace ta {
namespace volpath {
namespace detail {

constexpr int64_t kTexelBlock = 8;  // sensor elements handed out together (limits false sharing of output rows)

// Static, strided work split: chunk c owns element blocks c, c + n, c + 2n, ... . The split depends only on the
// number of chunks (= threads), so sums are deterministic for a given thread count, and strided blocks balance
// spatially varying path lengths.
template <typename F>
void for_each_chunk(int64_t nchunks, const F& body) {
  at::parallel_for(0, nchunks, 1, [&](int64_t begin, int64_t end) {
    for (int64_t c = begin; c < end; ++c) body(c);
  });
}

// The sensor elements this process traces: t = rank + world·u for u < count (all of them when world = 1).
struct Share {
  int64_t rank = 0, world = 1, count = 0;
  Share(int64_t n, int64_t r, int64_t w) : rank(r), world(w), count(r < n ? (n - r + w - 1) / w : 0) {}
  int64_t element(int64_t u) const { return rank + world * u; }
};

template <typename F>
void for_elements_of_chunk(int64_t c, int64_t nchunks, const Share& share, const F& body) {
  const int64_t n = share.count;
  for (int64_t b0 = c * kTexelBlock; b0 < n; b0 += nchunks * kTexelBlock)
    for (int64_t u = b0, e = std::min(n, b0 + kTexelBlock); u < e; ++u) {
      if (interrupted()) return;
      body(share.element(u));
    }
}

inline int64_t num_chunks(int64_t n) {
  const int64_t blocks = (n + kTexelBlock - 1) / kTexelBlock;
  return std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), blocks));
}

// Face texels of chunk c (of this process's share) in tiles of kTile × kTile texels, tiles dealt to the chunks in
// turn: the paths of neighbouring texels read the same voxels, so a tile's grid stays in the caches (on a 760²
// slab, 1.4× faster than rows of texels).
constexpr int64_t kTile = 16;

template <typename T, typename F>
void for_tiled_face_elements(const core::Scene<T>& S, int64_t c, int64_t nchunks, const Share& share, const F& body) {
  const int64_t H = S.medium.H, W = S.medium.W;
  const int64_t faces = S.sensor.face == core::kFaceBoth ? 2 : 1;
  const int64_t ny = (H + kTile - 1) / kTile, nx = (W + kTile - 1) / kTile;
  for (int64_t q = c; q < faces * ny * nx; q += nchunks) {
    const int64_t f = q / (ny * nx), ty = (q % (ny * nx)) / nx, tx = q % nx;
    for (int64_t j = ty * kTile; j < std::min(H, (ty + 1) * kTile); ++j)
      for (int64_t i = tx * kTile; i < std::min(W, (tx + 1) * kTile); ++i) {
        const int64_t t = (f * H + j) * W + i;
        if (interrupted()) return;
        if (t % share.world == share.rank) body(t);
      }
  }
}

// The elements of chunk c: face texels in tiles, other sensors' elements in strided blocks.
template <typename T, typename F>
void for_chunk_elements(const core::Scene<T>& S, int64_t c, int64_t nchunks, const Share& share, const F& body) {
  if (S.sensor.kind == core::kFaceTexels) for_tiled_face_elements(S, c, nchunks, share, body);
  else for_elements_of_chunk(c, nchunks, share, body);
}

// A sensor element's radiance in channel c from the sum over its samples' terms (core/replay.h).
using core::element_radiance;

// A gradient buffer of n zeros from calloc: a large block comes fresh from the kernel, so the pages that the deposits
// never touch are never resident (an object's paths touch the voxels near its surface, not its whole bounding box).
template <typename T>
struct ZeroedBuffer {
  std::unique_ptr<T, void (*)(void*)> p{nullptr, std::free};
  explicit ZeroedBuffer(int64_t n) : p(static_cast<T*>(std::calloc(size_t(n), sizeof(T))), std::free) {
    TORCH_CHECK(p != nullptr, "volpath backward: could not allocate a gradient buffer of ", n * int64_t(sizeof(T)),
                " bytes");
  }
  T* data() const { return p.get(); }
};

// Adds the chunks' buffers into out (n values) in chunk order, in parallel over the values: deterministic.
template <typename T>
void reduce_in_chunk_order(T* out, const std::vector<ZeroedBuffer<T>>& bufs, int64_t n) {
  if (!out || bufs.empty()) return;
  at::parallel_for(0, n, 1 << 14, [&](int64_t b, int64_t e) {
    for (const auto& buf : bufs) {
      const T* x = buf.data();
      for (int64_t i = b; i < e; ++i) out[i] += x[i];
    }
  });
}

// n values of T in fresh anonymous memory asked for in transparent huge pages (where the kernel has them: Linux with
// /sys/kernel/mm/transparent_hugepage/enabled at "always" or "madvise"), each written once by `fill` before use.
// For arrays that are read and written at random all through a walk (the compact gradient buffers and the voxels'
// ranks of AskedVoxels): in 4 KiB pages their TLB misses cost more than the arithmetic around them.
template <typename T>
class HugeArray {
 public:
  explicit HugeArray(int64_t n) : n_(n) {
    constexpr size_t kHuge = size_t(2) << 20;
    const size_t bytes = std::max<size_t>(1, size_t(n) * sizeof(T));
    len_ = bytes + kHuge;  // room to start on a huge-page boundary
    base_ = mmap(nullptr, len_, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    TORCH_CHECK(base_ != MAP_FAILED, "volpath: could not allocate ", bytes, " bytes");
    const uintptr_t a = (reinterpret_cast<uintptr_t>(base_) + kHuge - 1) & ~uintptr_t(kHuge - 1);
    data_ = reinterpret_cast<T*>(a);
#ifdef MADV_HUGEPAGE
    madvise(data_, bytes, MADV_HUGEPAGE);  // (a hint: without huge pages the array is in small pages)
#endif
  }
  HugeArray(HugeArray&& o) noexcept : base_(o.base_), len_(o.len_), n_(o.n_), data_(o.data_) {
    o.base_ = nullptr;
    o.data_ = nullptr;
  }
  HugeArray(const HugeArray&) = delete;
  HugeArray& operator=(const HugeArray&) = delete;
  HugeArray& operator=(HugeArray&&) = delete;
  ~HugeArray() {
    if (base_ != nullptr) munmap(base_, len_);
  }
  // Writes x everywhere, in parallel (each page first by a write: no copy of the shared zero page).
  void fill(T x) {
    at::parallel_for(0, n_, int64_t(1) << 18, [&](int64_t b, int64_t e) { std::fill(data_ + b, data_ + e, x); });
  }
  T* data() const { return data_; }
  int64_t size() const { return n_; }
  T& operator[](int64_t i) const { return data_[i]; }

 private:
  void* base_ = nullptr;
  size_t len_ = 0;
  int64_t n_ = 0;
  T* data_ = nullptr;
};

// The chunks' compact buffers summed in chunk order into the first (deterministic); returns it.
template <typename T>
const HugeArray<T>& sum_in_chunk_order(std::vector<HugeArray<T>>& bufs) {
  HugeArray<T>& out = bufs.front();
  at::parallel_for(0, out.size(), 1 << 14, [&](int64_t b, int64_t e) {
    for (size_t k = 1; k < bufs.size(); ++k) {
      const T* x = bufs[k].data();
      for (int64_t i = b; i < e; ++i) out[i] += x[i];
    }
  });
  return out;
}

// The voxels whose gradients are asked for (grad_support), numbered in grid order: rank[v] is voxel v's place among
// them, −1 for the others. The backward's chunks deposit into compact buffers (3 × count values, channel-planar)
// through it, so the gradient work and memory follow a print's shell, not its bounding box.
struct AskedVoxels {
  HugeArray<int32_t> rank;
  int64_t count = 0, N = 0;

  AskedVoxels(const bool* keep, int64_t n) : rank(n), N(n) {
    constexpr int64_t kBlock = int64_t(1) << 16;
    const int64_t blocks = (n + kBlock - 1) / kBlock;
    std::vector<int64_t> start(size_t(blocks) + 1, 0);
    at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
      for (int64_t b = b0; b < b1; ++b) {
        int64_t k = 0;
        for (int64_t v = b * kBlock, e = std::min(n, v + kBlock); v < e; ++v) k += keep[v];
        start[size_t(b) + 1] = k;
      }
    });
    for (int64_t b = 0; b < blocks; ++b) start[size_t(b) + 1] += start[size_t(b)];
    count = start[size_t(blocks)];
    at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
      for (int64_t b = b0; b < b1; ++b) {
        int64_t k = start[size_t(b)];
        for (int64_t v = b * kBlock, e = std::min(n, v + kBlock); v < e; ++v)
          rank[v] = keep[v] ? int32_t(k++) : -1;
      }
    });
  }

  // Writes the compact values (3 × count) into the asked voxels of the channel-planar grid `out` (3 × N), and
  // nothing else (a fresh zero grid keeps its other pages untouched).
  template <typename T>
  void scatter(const HugeArray<T>& compact, T* out) const {
    at::parallel_for(0, N, 1 << 16, [&](int64_t b, int64_t e) {
      for (int64_t v = b; v < e; ++v) {
        const int32_t r = rank[v];
        if (r < 0) continue;
        for (int c = 0; c < 3; ++c) out[c * N + v] = compact[c * count + r];
      }
    });
  }
};

}  // namespace detail
}  // namespace volpath
}  // namespace ta
