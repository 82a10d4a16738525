// AVX-512 slab walk (see slab_simd.h): sixteen lanes, the walk of slab_simd_walk.h with AVX-512F vectors, lane masks
// in mask registers and hardware gathers. Compiled for AVX-512F by the pragma below and called only after a CPU check;
// as in slab_simd_avx2.cpp, nothing but the intrinsics and the walk itself (inside this file's anonymous namespace)
// is included, so no AVX-512 instruction can leak into code that runs on other CPUs.
#include "volpath/object_simd.h"
#include "volpath/slab_simd.h"

#if defined(__x86_64__) || defined(__i386__)
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC target("avx512f")
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"  // GCC 12's own intrinsics (_mm512_undefined_*) warn
#elif defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx512f"))), apply_to = function)
#endif

#include <immintrin.h>
#include <string.h>

namespace ta {
namespace simd {
namespace {

constexpr int kLanes = 16;
typedef __m512 F;
typedef __m512i I;
typedef __mmask16 M;

inline F fset(float x) { return _mm512_set1_ps(x); }
inline I iset(int32_t x) { return _mm512_set1_epi32(x); }
inline F fzero() { return _mm512_setzero_ps(); }
inline F asf(I x) { return _mm512_castsi512_ps(x); }
inline I asi(F x) { return _mm512_castps_si512(x); }
inline F add(F a, F b) { return _mm512_add_ps(a, b); }
inline F sub(F a, F b) { return _mm512_sub_ps(a, b); }
inline F mul(F a, F b) { return _mm512_mul_ps(a, b); }
inline F div(F a, F b) { return _mm512_div_ps(a, b); }
inline F sqrt_(F a) { return _mm512_sqrt_ps(a); }
inline F fmin_(F a, F b) { return _mm512_min_ps(a, b); }
inline F fmax_(F a, F b) { return _mm512_max_ps(a, b); }
inline F floor_(F a) { return _mm512_roundscale_ps(a, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC); }
inline F round_(F a) { return _mm512_roundscale_ps(a, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); }
// sign-bit operations on the integer view (AVX-512F has no float and/xor)
inline F neg(F a) { return asf(_mm512_xor_si512(asi(a), iset(int32_t(0x80000000u)))); }
inline F fabs_(F a) { return asf(_mm512_and_si512(asi(a), iset(0x7FFFFFFF))); }
inline F sign1(F a) {
  return asf(_mm512_or_si512(_mm512_and_si512(asi(a), iset(int32_t(0x80000000u))), asi(_mm512_set1_ps(1.0f))));
}
inline F cvtif(I a) { return _mm512_cvtepi32_ps(a); }
inline I cvtfi(F a) { return _mm512_cvtps_epi32(a); }
inline I iadd(I a, I b) { return _mm512_add_epi32(a, b); }
inline I isub(I a, I b) { return _mm512_sub_epi32(a, b); }
inline I imul(I a, I b) { return _mm512_mullo_epi32(a, b); }
inline I iand(I a, I b) { return _mm512_and_si512(a, b); }
inline I ior_(I a, I b) { return _mm512_or_si512(a, b); }
inline I ixor(I a, I b) { return _mm512_xor_si512(a, b); }
template <int K> inline I srli(I a) { return _mm512_srli_epi32(a, K); }
template <int K> inline I slli(I a) { return _mm512_slli_epi32(a, K); }
template <int K> inline I srai(I a) { return _mm512_srai_epi32(a, K); }
inline M lt(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_LT_OQ); }
inline M ge(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_GE_OQ); }
inline M gt(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_GT_OQ); }
inline M eq(F a, F b) { return _mm512_cmp_ps_mask(a, b, _CMP_EQ_OQ); }
inline M ieq(I a, I b) { return _mm512_cmpeq_epi32_mask(a, b); }
inline M igt(I a, I b) { return _mm512_cmpgt_epi32_mask(a, b); }
inline M mand(M a, M b) { return M(a & b); }
inline M mor(M a, M b) { return M(a | b); }
inline M mandnot(M a, M b) { return M(~a & b); }  // !a & b
inline M mnot(M a) { return M(~a); }
inline M mnone() { return M(0); }
inline int bits(M m) { return int(m); }
inline F sel(M m, F a, F b) { return _mm512_mask_blend_ps(m, b, a); }  // m ? a : b
inline I seli(M m, I a, I b) { return _mm512_mask_blend_epi32(m, b, a); }
inline I iadd1(I a, M m) { return _mm512_mask_add_epi32(a, m, a, iset(1)); }
inline F loadf(const float* p) { return _mm512_load_ps(p); }
inline void storef(float* p, F a) { _mm512_store_ps(p, a); }
inline I loadi(const int32_t* p) { return _mm512_load_si512(p); }
inline void storei(int32_t* p, I a) { _mm512_store_si512(p, a); }
inline F gather(const float* base, I idx, M mask) {
  return _mm512_mask_i32gather_ps(_mm512_setzero_ps(), mask, idx, base, 4);
}

inline F gather_pair(const float* base, int k, I idx, M mask) {
  return _mm512_mask_i32gather_ps(_mm512_setzero_ps(), mask, idx, base + k, 8);
}

inline I cvttfi(F a) { return _mm512_cvttps_epi32(a); }  // float → int, truncated

// base[idx] of a byte grid (0 outside mask), with scalar loads (a 32-bit gather could read past the grid's end)
inline I gather_u8(const uint8_t* base, I idx, M mask) {
  alignas(64) int32_t ii[16], r[16];
  _mm512_store_si512(ii, _mm512_maskz_mov_epi32(mask, idx));
  for (int l = 0; l < 16; ++l) r[l] = base[ii[l]];
  return _mm512_maskz_mov_epi32(mask, loadi(r));
}

inline void mulhilo(I a, uint32_t m, I* hi, I* lo) {
  const I mv = _mm512_set1_epi64(int64_t(m));
  const I even = _mm512_mul_epu32(a, mv);                        // even lanes: 64-bit products
  const I odd = _mm512_mul_epu32(_mm512_srli_epi64(a, 32), mv);  // odd lanes
  *lo = _mm512_mask_blend_epi32(0xAAAA, even, _mm512_slli_epi64(odd, 32));
  *hi = _mm512_mask_blend_epi32(0xAAAA, _mm512_srli_epi64(even, 32), odd);
}

// two 8-lane scatters of 64-bit pairs, only the lanes of m
inline void store_pairs(void* base, I slot, I a, I b, M m) {
  const __m512i p0 = _mm512_or_si512(_mm512_cvtepu32_epi64(_mm512_castsi512_si256(a)),
                                     _mm512_slli_epi64(_mm512_cvtepu32_epi64(_mm512_castsi512_si256(b)), 32));
  const __m512i p1 = _mm512_or_si512(_mm512_cvtepu32_epi64(_mm512_extracti64x4_epi64(a, 1)),
                                     _mm512_slli_epi64(_mm512_cvtepu32_epi64(_mm512_extracti64x4_epi64(b, 1)), 32));
  _mm512_mask_i32scatter_epi64(base, __mmask8(m), _mm512_castsi512_si256(slot), p0, 8);
  _mm512_mask_i32scatter_epi64(base, __mmask8(m >> 8), _mm512_extracti64x4_epi64(slot, 1), p1, 8);
}

#include "volpath/simd_math.h"
#include "volpath/slab_simd_walk.h"
#include "volpath/object_simd_walk.h"

}  // namespace

void slab_walks_avx512(const SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                       const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx) {
  walks_dispatch(S, elems, live, n, ratio, tapes, ended_lanes, done, ctx);
}

void object_walks_avx512(const ObjectWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                         const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx) {
  object_walks_dispatch(S, elems, live, n, ratio, tapes, ended_lanes, done, ctx);
}

}  // namespace simd
}  // namespace ta

#if defined(__clang__)
#pragma clang attribute pop
#endif

#else  // not x86: no AVX-512 walk (never called there)

namespace ta {
namespace simd {
void slab_walks_avx512(const SlabWalkScene&, const int64_t*, const uint8_t*, int64_t, bool, const LaneTapes*, int,
                       WalkDone, void*) {
  __builtin_trap();
}
void object_walks_avx512(const ObjectWalkScene&, const int64_t*, const uint8_t*, int64_t, bool, const LaneTapes*,
                         int, WalkDone, void*) {
  __builtin_trap();
}
}  // namespace simd
}  // namespace ta

#endif
