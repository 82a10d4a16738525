// The CUDA glue's launch shapes, memory and atomics, shared by its kernels (forward.cu, replay.cu). Compiled by NVRTC
// at run time (torch_appearance/render/cuda_kernels.py), with the tracing core (csrc/core/) as the CPU glue
// (csrc/volpath/) compiles it: the walks are the core's, this room only says which path a thread walks, where its
// terms and deposits go, and how they get there.
//
// One thread per path. The paths of a launch are numbered p = first .. first + paths − 1 over
//   p = (ch · spp + s) · count + u     (one lane per channel: `chans` = 3 walks per element and sample)
//   p = s · count + u                  (three lanes, or a hero walk: one walk per element and sample)
// u the index of the sensor element in this process's share (element t = rank + world · u, volpath/threading.h's
// Share), s the sample, ch the channel: neighbouring threads walk neighbouring elements with the same sample and
// channel, so they read neighbouring voxels of one channel plane. A thread draws the CPU's random numbers (rng.h:
// keyed by seed, element t, sample s, channel), so its path is the CPU's path up to floating-point rounding.
//
// Blocks are kBlock threads (a multiple of the warp: the counters are summed over full warps with shuffles).
// Scene<T> comes by value (a kernel parameter, about 0.5 kB), its pointers in device memory; its tally must be null
// (the CPU's diagnostics, counted without atomics).
#pragma once

#include "core/replay.h"

// A program holds the kernels of one dtype: -DTA_CUDA_DTYPE=32 (float) or 64 (double).
#if !defined(TA_CUDA_DTYPE) || (TA_CUDA_DTYPE != 32 && TA_CUDA_DTYPE != 64)
#error "define TA_CUDA_DTYPE as 32 or 64"
#endif

namespace ta {
namespace cuda {

constexpr int kBlock = 128;

// A gradient deposit shared by every thread: an atomic add (float and double; double needs sm_60 or newer).
struct AtomicAdd {
  template <typename T>
  __device__ static inline void add(T* buffer, int64_t i, T x) { atomicAdd(buffer + i, x); }
};

// The paths of one launch (see above); a large job is split into launches of consecutive paths.
struct Launch {
  int64_t rank;   // the process's share of the sensor elements: t = rank + world · u, u < count
  int64_t world;
  int64_t count;
  int64_t first;  // first path of this launch
  int64_t paths;  // paths of this launch
};

// Which path thread `p` walks (see above).
struct PathIndex {
  int64_t u, t, s;
  int ch;
};
template <int LANES>
__device__ inline PathIndex path_index(const Launch& L, int64_t spp, int64_t p) {
  PathIndex i;
  i.u = p % L.count;
  const int64_t rest = p / L.count;
  i.s = rest % spp;
  i.ch = LANES == 1 ? int(rest / spp) : 0;
  i.t = L.rank + L.world * i.u;
  return i;
}

// Counters of a launch, summed over each warp and added once per warp into counts[0..n).
template <int N>
__device__ inline void add_counts(unsigned long long* counts, long long (&x)[N]) {
  for (int k = 0; k < N; ++k)
    for (int off = 16; off > 0; off >>= 1) x[k] += __shfl_down_sync(0xffffffffu, x[k], off);
  if ((threadIdx.x & 31) == 0)
    for (int k = 0; k < N; ++k)
      if (x[k] != 0) atomicAdd(counts + k, (unsigned long long)x[k]);
}

// A walk's term of channel c into its element's sum (acc: (count, 3) doubles, zeroed by the launcher).
__device__ inline void add_term(double* acc, int64_t u, int c, double term) {
  if (term != 0.0) atomicAdd(acc + u * 3 + c, term);
}

// The image of the share's elements from their sums (core::element_radiance), written at out[t · 3 + c] (the other
// elements of the image are the launcher's zeros, as on the CPU). One thread per element.
template <typename T>
__device__ inline void write_image(const core::Scene<T>& S, const Launch& L, const double* acc, T* out) {
  const int64_t u = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (u >= L.count) return;
  const int64_t t = L.rank + L.world * u;
  for (int c = 0; c < 3; ++c) out[t * 3 + c] = core::element_radiance(S, acc[u * 3 + c], c);
}

}  // namespace cuda
}  // namespace ta
