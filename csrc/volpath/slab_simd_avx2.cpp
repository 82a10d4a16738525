// AVX2 slab walk (see slab_simd.h): eight lanes. Compiled for AVX2 by the pragma below and called only after a CPU
// check; this file includes no header with inline or template code other than the intrinsics and the walk itself
// (slab_simd_walk.h, inside this file's anonymous namespace), so no AVX2 instruction can leak into code that runs on
// other CPUs.
#include "volpath/object_simd.h"
#include "volpath/slab_simd.h"

#if defined(__x86_64__) || defined(__i386__)
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC target("avx2")
#elif defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx2"))), apply_to = function)
#endif

#include <immintrin.h>
#include <string.h>

namespace ta {
namespace simd {
namespace {

constexpr int kLanes = 8;
typedef __m256 F;
typedef __m256i I;
typedef __m256 M;  // all ones in the lanes that are set

inline F fset(float x) { return _mm256_set1_ps(x); }
inline I iset(int32_t x) { return _mm256_set1_epi32(x); }
inline F fzero() { return _mm256_setzero_ps(); }
inline F asf(I x) { return _mm256_castsi256_ps(x); }
inline I asi(F x) { return _mm256_castps_si256(x); }
inline F add(F a, F b) { return _mm256_add_ps(a, b); }
inline F sub(F a, F b) { return _mm256_sub_ps(a, b); }
inline F mul(F a, F b) { return _mm256_mul_ps(a, b); }
inline F div(F a, F b) { return _mm256_div_ps(a, b); }
inline F sqrt_(F a) { return _mm256_sqrt_ps(a); }
inline F fmin_(F a, F b) { return _mm256_min_ps(a, b); }
inline F fmax_(F a, F b) { return _mm256_max_ps(a, b); }
inline F floor_(F a) { return _mm256_floor_ps(a); }
inline F round_(F a) { return _mm256_round_ps(a, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); }
inline F neg(F a) { return _mm256_xor_ps(a, fset(-0.0f)); }
inline F fabs_(F a) { return _mm256_andnot_ps(fset(-0.0f), a); }
inline F sign1(F a) { return _mm256_or_ps(_mm256_and_ps(a, fset(-0.0f)), fset(1.0f)); }
inline F cvtif(I a) { return _mm256_cvtepi32_ps(a); }
inline I cvtfi(F a) { return _mm256_cvtps_epi32(a); }
inline I iadd(I a, I b) { return _mm256_add_epi32(a, b); }
inline I isub(I a, I b) { return _mm256_sub_epi32(a, b); }
inline I imul(I a, I b) { return _mm256_mullo_epi32(a, b); }
inline I iand(I a, I b) { return _mm256_and_si256(a, b); }
inline I ior_(I a, I b) { return _mm256_or_si256(a, b); }
inline I ixor(I a, I b) { return _mm256_xor_si256(a, b); }
template <int K> inline I srli(I a) { return _mm256_srli_epi32(a, K); }
template <int K> inline I slli(I a) { return _mm256_slli_epi32(a, K); }
template <int K> inline I srai(I a) { return _mm256_srai_epi32(a, K); }
inline M lt(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_LT_OQ); }
inline M ge(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_GE_OQ); }
inline M gt(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_GT_OQ); }
inline M eq(F a, F b) { return _mm256_cmp_ps(a, b, _CMP_EQ_OQ); }
inline M ieq(I a, I b) { return asf(_mm256_cmpeq_epi32(a, b)); }
inline M igt(I a, I b) { return asf(_mm256_cmpgt_epi32(a, b)); }
inline M mand(M a, M b) { return _mm256_and_ps(a, b); }
inline M mor(M a, M b) { return _mm256_or_ps(a, b); }
inline M mandnot(M a, M b) { return _mm256_andnot_ps(a, b); }  // !a & b
inline M mnot(M a) { return _mm256_xor_ps(a, asf(iset(-1))); }
inline M mnone() { return _mm256_setzero_ps(); }
inline int bits(M m) { return _mm256_movemask_ps(m); }
inline F sel(M m, F a, F b) { return _mm256_blendv_ps(b, a, m); }  // m ? a : b
inline I seli(M m, I a, I b) { return asi(_mm256_blendv_ps(asf(b), asf(a), m)); }
inline I iadd1(I a, M m) { return _mm256_sub_epi32(a, asi(m)); }  // a true mask is −1: subtracting it adds 1
inline F loadf(const float* p) { return _mm256_load_ps(p); }
inline void storef(float* p, F a) { _mm256_store_ps(p, a); }
inline I loadi(const int32_t* p) { return _mm256_load_si256(reinterpret_cast<const I*>(p)); }
inline void storei(int32_t* p, I a) { _mm256_store_si256(reinterpret_cast<I*>(p), a); }

// emulated with scalar loads: faster than vpgather on the machines measured; base[STRIDE·idx] (0 outside mask)
template <int STRIDE>
inline F gather_strided(const float* base, I idx, M mask) {
  alignas(32) int32_t ii[8];
  _mm256_store_si256(reinterpret_cast<I*>(ii), _mm256_and_si256(idx, asi(mask)));
  auto at = [&](int l) { return base[STRIDE * int64_t(ii[l])]; };
  const F x = _mm256_set_ps(at(7), at(6), at(5), at(4), at(3), at(2), at(1), at(0));
  return _mm256_and_ps(x, mask);
}

inline F gather(const float* base, I idx, M mask) { return gather_strided<1>(base, idx, mask); }
inline F gather_pair(const float* base, int k, I idx, M mask) { return gather_strided<2>(base + k, idx, mask); }

inline I cvttfi(F a) { return _mm256_cvttps_epi32(a); }  // float → int, truncated

// base[idx] of a byte grid (0 outside mask), with scalar loads
inline I gather_u8(const uint8_t* base, I idx, M mask) {
  alignas(32) int32_t ii[8], r[8];
  _mm256_store_si256(reinterpret_cast<I*>(ii), _mm256_and_si256(idx, asi(mask)));
  for (int l = 0; l < 8; ++l) r[l] = base[ii[l]];
  return _mm256_and_si256(loadi(r), asi(mask));
}

inline void mulhilo(I a, uint32_t m, I* hi, I* lo) {
  const I mv = _mm256_set1_epi64x(int64_t(m));
  const I even = _mm256_mul_epu32(a, mv);                        // lanes 0 2 4 6: 64-bit products
  const I odd = _mm256_mul_epu32(_mm256_srli_epi64(a, 32), mv);  // lanes 1 3 5 7
  *lo = _mm256_blend_epi32(even, _mm256_slli_epi64(odd, 32), 0xAA);
  *hi = _mm256_blend_epi32(_mm256_srli_epi64(even, 32), odd, 0xAA);
}

// branch-free: every lane writes its slot (lanes outside m write their tape's next free entry, written over later)
inline void store_pairs(void* base, I slot, I a, I b, M) {
  alignas(32) int32_t s[8], x[8], y[8];
  storei(s, slot);
  storei(x, a);
  storei(y, b);
  for (int l = 0; l < 8; ++l) {
    const int32_t pair[2] = {x[l], y[l]};
    memcpy(static_cast<char*>(base) + 8 * int64_t(s[l]), pair, 8);
  }
}

#include "volpath/simd_math.h"
#include "volpath/slab_simd_walk.h"
#include "volpath/object_simd_walk.h"

}  // namespace

void slab_walks_avx2(const SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                     const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx) {
  walks_dispatch(S, elems, live, n, ratio, tapes, ended_lanes, done, ctx);
}

void object_walks_avx2(const ObjectWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                       const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx) {
  object_walks_dispatch(S, elems, live, n, ratio, tapes, ended_lanes, done, ctx);
}

}  // namespace simd
}  // namespace ta

#if defined(__clang__)
#pragma clang attribute pop
#endif

#else  // not x86: no AVX2 walk (cpu_simd_level() in simd_glue.cpp is 0 there, so this is never called)

namespace ta {
namespace simd {
void slab_walks_avx2(const SlabWalkScene&, const int64_t*, const uint8_t*, int64_t, bool, const LaneTapes*, int,
                     WalkDone, void*) {
  __builtin_trap();
}
void object_walks_avx2(const ObjectWalkScene&, const int64_t*, const uint8_t*, int64_t, bool, const LaneTapes*, int,
                       WalkDone, void*) {
  __builtin_trap();
}
}  // namespace simd
}  // namespace ta

#endif
