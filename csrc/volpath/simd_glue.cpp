// SIMD glue (see simd_glue.h).
#include "volpath/simd_glue.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cstdlib>
#include <cstring>
#include <memory>

#include "volpath/slab_simd.h"

namespace ta {
namespace volpath {
namespace detail {

using core::Adjoint;
using core::Scene;

// The widest SIMD walk this CPU runs: 2 AVX-512F, 1 AVX2, 0 none (libgcc also checks that the OS saves the registers).
int cpu_simd_level() {
#if (defined(__x86_64__) || defined(__i386__)) && defined(__GNUC__)
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx512f")) return 2;
  return __builtin_cpu_supports("avx2") ? 1 : 0;
#else
  return 0;
#endif
}

// -1: not decided yet (the CPU and TA_SIMD decide at first use); 0 the scalar walk; 1 AVX2; 2 AVX-512. set_simd (tests,
// benchmarks) overrides.
std::atomic<int> g_simd{-1};

int simd_level() {
  int v = g_simd.load();
  if (v < 0) {
    const char* env = std::getenv("TA_SIMD");
    v = cpu_simd_level();
    if (env && env[0] == '0') v = 0;
    else if (env && std::strcmp(env, "avx2") == 0) v = std::min(v, 1);
    g_simd.store(v);
  }
  return v;
}

// TA_SIMD_ENDED_LANES: flights that end before the SIMD walk's collision phase runs (0: its default); for tuning
int simd_ended_lanes() {
  static const int v = [] {
    const char* env = std::getenv("TA_SIMD_ENDED_LANES");
    return env ? std::atoi(env) : 0;
  }();
  return v;
}

namespace {

// The SIMD walk of the selected width.
void slab_walks(const simd::SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                const simd::LaneTapes* tapes, simd::WalkDone done, void* ctx) {
  if (simd_level() == 2) simd::slab_walks_avx512(S, elems, live, n, ratio, tapes, simd_ended_lanes(), done, ctx);
  else simd::slab_walks_avx2(S, elems, live, n, ratio, tapes, simd_ended_lanes(), done, ctx);
}

simd::SlabWalkScene simd_scene(const Scene<float>& S, const float* ref_pair) {
  simd::SlabWalkScene W;
  const auto& M = S.medium;
  W.ref_pair = ref_pair;
  W.sigma_t = M.sigma_t.data;
  W.albedo = M.albedo.data;
  W.ref_sigma_t = M.ref_sigma_t.data;
  W.ref_albedo = M.ref_albedo.data;
  W.ref_sigma_t_floor = M.ref_sigma_t.plain ? 0.0f : M.ref_sigma_t.floor;
  W.ref_albedo_floor = M.ref_albedo.plain ? 0.0f : M.ref_albedo.floor;
  W.D = int32_t(M.D);
  W.H = int32_t(M.H);
  W.W = int32_t(M.W);
  for (int a = 0; a < 3; ++a) W.voxel[a] = M.voxel[a];
  W.g = S.g;
  W.ior = S.ior;
  W.face = S.sensor.face;
  W.seed = S.seed;
  W.max_depth = S.max_depth;
  W.rr_depth = S.rr_depth;
  W.spp = S.spp;
  return W;
}

}  // namespace

// core::deposit_tape<float, 1> for the SIMD walk's compact tape (slab_simd.h), through the same deposit policy
// (Adjoint::sigma_t, Adjoint::albedo), with the σ_t deposits of one voxel in a row summed before they are added (a
// flight that ends by a collision and the next flight's first segment there).
namespace {

// Compact buffers (AskedVoxels): ask for every voxel's rank first, then for the lines of its deposits (channels
// [c0, c1)), so that their cache misses overlap instead of following one another in the adds (an object's shell:
// 1.5 s of a 40 mm iteration at 8 spp; on a slab's dense buffers, which the caches hold better, the same was 4 %
// slower). Forced inline: as an out-of-line helper GCC once compiled these loops to nothing (c9ee578).
TA_INLINE void prefetch_deposits(const simd::WalkOut& o, int c0, int c1, const Adjoint<float>& A) {
  if (A.rank == nullptr) return;
  for (int64_t s = 0; s < o.nseg; ++s) __builtin_prefetch(A.rank + o.segs[s].v);
  for (int64_t s = 0; s < o.nseg; ++s) {
    const int32_t r = A.rank[o.segs[s].v];
    if (r < 0) continue;
    for (int c = c0; c < c1; ++c) {
      if (A.grad_sigma_t) __builtin_prefetch(A.grad_sigma_t + c * A.plane + r, 1);
      if (A.grad_albedo) __builtin_prefetch(A.grad_albedo + c * A.plane + r, 1);
    }
  }
}

}  // namespace

void deposit_simd_tape(const simd::WalkOut& o, int ch, float adj, const Adjoint<float>& A) {
  prefetch_deposits(o, ch, ch + 1, A);
  const float av = adj * o.value[0];
  int64_t cur = -1;  // the voxel of the pending σ_t deposit
  float run = 0.0f;
  auto add_s = [&](int64_t v, float d) {
    if (v == cur) {
      run += d;
      return;
    }
    if (cur >= 0) A.sigma_t(ch, cur, run);
    cur = v;
    run = d;
  };
  int64_t s = 0;
  for (int64_t k = 0; k < o.ncol; ++k) {
    const simd::TapeCollisionF& col = o.cols[k];
    if (A.grad_sigma_t) {
      for (; s < col.seg_end; ++s) add_s(o.segs[s].v, -(av * o.segs[s].len));
      add_s(col.v, adj * core::weight_without(col.fs, o.value[0], o.prod_nonzero[0], int(o.zeros[0])) / col.sref);
    }
    if (A.grad_albedo)
      A.albedo(ch, col.v,
               adj * core::weight_without(col.fa, o.value[0], o.prod_nonzero[0], int(o.zeros[0])) * col.inv_psq);
  }
  if (A.grad_sigma_t) {
    for (; s < o.nseg; ++s) add_s(o.segs[s].v, -(av * o.segs[s].len));
    if (cur >= 0) A.sigma_t(ch, cur, run);
  }
}

// core::deposit_tape<float, 3> itself, on the compact tape.
void deposit_simd_tape3(const simd::WalkOut& o, const float adj[3], const Adjoint<float>& A) {
  prefetch_deposits(o, 0, 3, A);
  struct {
    const simd::TapeSegmentF* segs;
    const simd::TapeCollision3F* cols;
    int64_t nseg, ncol;
  } tape{o.segs, o.cols3, o.nseg, o.ncol};
  core::deposit_tape<float, 3>(tape, o.value, o.prod_nonzero, o.zeros, 0, adj, A);
}

// The image of a batch of n elements from each path's value by item ((k·spp + sample)·3 + channel), summed in
// sample order as the scalar kernel adds them (so the image does not depend on the order the lanes finish in).
void write_batch_image(const Scene<float>& S, const int64_t* elems, int64_t n, const std::vector<double>& values,
                       float* out) {
  for (int64_t k = 0; k < n; ++k) {
    double acc[3] = {0, 0, 0};
    for (int64_t s = 0; s < S.spp; ++s)
      for (int ch = 0; ch < 3; ++ch) acc[ch] += values[size_t((k * S.spp + s) * 3 + ch)];
    for (int ch = 0; ch < 3; ++ch) out[elems[k] * 3 + ch] = element_radiance(S, acc[ch], ch);
  }
}

std::vector<float> pack_reference(const Scene<float>& S) {
  const auto& M = S.medium;
  const int64_t n = 3 * M.voxels();
  std::vector<float> pair(size_t(2 * n));
  const float* s = M.ref_sigma_t.data;
  const float* a = M.ref_albedo.data;
  float* out = pair.data();
  at::parallel_for(0, n, 1 << 16, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) {
      out[2 * i] = s[i];
      out[2 * i + 1] = a[i];
    }
  });
  return pair;
}

template <bool DIEL, bool RATIO>
ForwardCounts simd_forward_chunk(const Scene<float>& S, const float* ref_pair, float* out, int64_t c, int64_t nchunks,
                                 const Share& share) {
  simd::SlabWalkScene W = simd_scene(S, ref_pair);
  W.dielectric = DIEL;
  return simd_forward_batches(
      S, out, [&](const auto& body) { for_tiled_face_elements(S, c, nchunks, share, body); },
      [&](const int64_t* elems, int64_t n, simd::WalkDone done, void* ctx) {
        slab_walks(W, elems, nullptr, n, RATIO, nullptr, done, ctx);
      });
}

template ForwardCounts simd_forward_chunk<false, false>(const Scene<float>&, const float*, float*, int64_t, int64_t,
                                                        const Share&);
template ForwardCounts simd_forward_chunk<false, true>(const Scene<float>&, const float*, float*, int64_t, int64_t,
                                                       const Share&);
template ForwardCounts simd_forward_chunk<true, false>(const Scene<float>&, const float*, float*, int64_t, int64_t,
                                                       const Share&);
template ForwardCounts simd_forward_chunk<true, true>(const Scene<float>&, const float*, float*, int64_t, int64_t,
                                                      const Share&);

template <bool DIEL>
int64_t simd_backward_chunk(const Scene<float>& S, const float* ref_pair, const float* grad_out,
                            const Adjoint<float>& A, TapeStore<float, 1>& store, int64_t c, int64_t nchunks,
                            const Share& share, float* image, int64_t* cut) {
  simd::SlabWalkScene W = simd_scene(S, ref_pair);
  W.dielectric = DIEL;
  return simd_replay_chunk<core::kBoxBoundary, DIEL>(
      S, grad_out, A, store, image, cut,
      [&](const auto& body) { for_tiled_face_elements(S, c, nchunks, share, body); },
      [&](const int64_t* elems, const uint8_t* live, int64_t n, const simd::LaneTapes* tapes, simd::WalkDone done,
          void* ctx) { slab_walks(W, elems, live, n, true, tapes, done, ctx); });
}

template int64_t simd_backward_chunk<false>(const Scene<float>&, const float*, const float*, const Adjoint<float>&,
                                            TapeStore<float, 1>&, int64_t, int64_t, const Share&, float*, int64_t*);
template int64_t simd_backward_chunk<true>(const Scene<float>&, const float*, const float*, const Adjoint<float>&,
                                           TapeStore<float, 1>&, int64_t, int64_t, const Share&, float*, int64_t*);

}  // namespace detail

int64_t set_simd(int64_t mode) {
  TORCH_CHECK(mode >= -1 && mode <= 2, "mode: expected -1 (automatic), 0 (scalar), 1 (AVX2) or 2 (AVX-512), got ",
              mode);
  TORCH_CHECK(mode <= detail::cpu_simd_level(), "mode: this CPU cannot run ", mode == 2 ? "AVX-512F" : "AVX2");
  const int before = detail::simd_level();
  detail::g_simd.store(int(mode));
  return before;
}

}  // namespace volpath
}  // namespace ta
