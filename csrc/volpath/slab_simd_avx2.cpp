// AVX2 slab walk (see slab_simd.h). Compiled for AVX2 by the pragma below and called only after a CPU check; this
// file includes no header with inline or template code other than the intrinsics, so no AVX2 instruction can leak
// into code that runs on other CPUs.
//
// Each lane follows core::trace_path<float, 1, kBoxBoundary, DIELECTRIC, RATIO, false, RECORD> for face texels and a
// constant emitter step by step (integrator.h is the reference; comments there explain the estimator):
//   start   event 0: position in the texel (u0, u1), specular reflection at the entry face (u2 < F(1)) escapes;
//   flight  one event per free flight: u0 the optical depth −log u0 in the reference medium, u1 absorption (at a
//           collision) or Fresnel (at the box), u2 u3 the new direction (HG cosine, azimuth 2π u3);
//   DDA     exact regular tracking through the voxels, one voxel per iteration of the wavefront loop;
//   collide depth cut, continuation p_s = α̂ times roulette q on the reference weight, weights σ/σ̂ and α/(p_s q);
//   box     internal reflection with probability F(|d_a|) (depth counted), else escape with weight w.
#include "volpath/slab_simd.h"

#if defined(__x86_64__) || defined(__i386__)
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC target("avx2")
#elif defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx2"))), apply_to = function)
#endif

#include <immintrin.h>
#include <stdlib.h>
#include <string.h>

namespace ta {
namespace simd {
namespace {

typedef __m256 vf;
typedef __m256i vi;

inline vf fset(float x) { return _mm256_set1_ps(x); }
inline vi iset(int32_t x) { return _mm256_set1_epi32(x); }
inline vf sel(vf m, vf a, vf b) { return _mm256_blendv_ps(b, a, m); }  // m ? a : b
inline vi seli(vf m, vi a, vi b) {
  return _mm256_castps_si256(_mm256_blendv_ps(_mm256_castsi256_ps(b), _mm256_castsi256_ps(a), m));
}
inline vf asf(vi x) { return _mm256_castsi256_ps(x); }
inline vi asi(vf x) { return _mm256_castps_si256(x); }
inline vf vand(vf a, vf b) { return _mm256_and_ps(a, b); }
inline vf vor(vf a, vf b) { return _mm256_or_ps(a, b); }
inline vf vandnot(vf a, vf b) { return _mm256_andnot_ps(a, b); }  // !a & b
inline vf lt(vf a, vf b) { return _mm256_cmp_ps(a, b, _CMP_LT_OQ); }
inline vf ge(vf a, vf b) { return _mm256_cmp_ps(a, b, _CMP_GE_OQ); }
inline vf gt(vf a, vf b) { return _mm256_cmp_ps(a, b, _CMP_GT_OQ); }
inline vf eq(vf a, vf b) { return _mm256_cmp_ps(a, b, _CMP_EQ_OQ); }
inline vf ieq(vi a, vi b) { return asf(_mm256_cmpeq_epi32(a, b)); }
inline vf igt(vi a, vi b) { return asf(_mm256_cmpgt_epi32(a, b)); }
inline int bits(vf m) { return _mm256_movemask_ps(m); }
// scalar tmin/tmax semantics: tmin(a, b) = b < a ? b : a; tmax(a, b) = a < b ? b : a
inline vf tmin(vf a, vf b) { return sel(lt(b, a), b, a); }
inline vf tmax(vf a, vf b) { return sel(lt(a, b), b, a); }

// ---- Philox4x32-10, eight counters at once (core/rng.h)
inline void mulhilo(vi a, uint32_t m, vi* hi, vi* lo) {
  const vi mv = _mm256_set1_epi64x(int64_t(m));
  const vi even = _mm256_mul_epu32(a, mv);                          // lanes 0 2 4 6: 64-bit products
  const vi odd = _mm256_mul_epu32(_mm256_srli_epi64(a, 32), mv);    // lanes 1 3 5 7
  *lo = _mm256_blend_epi32(even, _mm256_slli_epi64(odd, 32), 0xAA);
  *hi = _mm256_blend_epi32(_mm256_srli_epi64(even, 32), odd, 0xAA);
}

inline void philox(vi c[4], uint64_t key) {
  uint32_t k0 = uint32_t(key), k1 = uint32_t(key >> 32);
  for (int r = 0; r < 10; ++r) {
    vi hi0, lo0, hi1, lo1;
    mulhilo(c[0], 0xD2511F53u, &hi0, &lo0);
    mulhilo(c[2], 0xCD9E8D57u, &hi1, &lo1);
    const vi n0 = _mm256_xor_si256(_mm256_xor_si256(hi1, c[1]), iset(int32_t(k0)));
    const vi n2 = _mm256_xor_si256(_mm256_xor_si256(hi0, c[3]), iset(int32_t(k1)));
    c[1] = lo1;
    c[3] = lo0;
    c[0] = n0;
    c[2] = n2;
    k0 += 0x9E3779B9u;
    k1 += 0xBB67AE85u;
  }
}

// uniform in (0, 1): (float(x >> 9) + 0.5) · 2^-23, as to_unit_open<float>
inline vf unit(vi x) {
  return _mm256_mul_ps(_mm256_add_ps(_mm256_cvtepi32_ps(_mm256_srli_epi32(x, 9)), fset(0.5f)), fset(1.0f / 8388608.0f));
}

inline void draw(vi elem, vi sample, vi chan, vi event, uint64_t key, vf u[4]) {
  vi c[4] = {elem, sample, chan, event};
  philox(c, key);
  for (int i = 0; i < 4; ++i) u[i] = unit(c[i]);
}

// scalar twin for a lane's start (event 0): a copy of core/rng.h's Philox, since this file must not include that
// header (its inline functions would be compiled for AVX2 here and might be the copy the linker keeps)
inline void draw1(uint32_t elem, uint32_t sample, uint32_t chan, uint32_t event, uint64_t key, float u[4]) {
  uint32_t c[4] = {elem, sample, chan, event};
  uint32_t k[2] = {uint32_t(key), uint32_t(key >> 32)};
  for (int r = 0; r < 10; ++r) {
    const uint64_t p0 = uint64_t(0xD2511F53u) * c[0];
    const uint64_t p1 = uint64_t(0xCD9E8D57u) * c[2];
    const uint32_t n0 = uint32_t(p1 >> 32) ^ c[1] ^ k[0];
    const uint32_t n2 = uint32_t(p0 >> 32) ^ c[3] ^ k[1];
    c[1] = uint32_t(p1);
    c[3] = uint32_t(p0);
    c[0] = n0;
    c[2] = n2;
    k[0] += 0x9E3779B9u;
    k[1] += 0xBB67AE85u;
  }
  for (int i = 0; i < 4; ++i) u[i] = (float(c[i] >> 9) + 0.5f) * (1.0f / 8388608.0f);
}

// ---- float math (Cephes single-precision polynomials, about 1 ulp)
// log x for normal x > 0
inline vf vlog(vf x) {
  vi xi = asi(x);
  vi e = _mm256_sub_epi32(_mm256_srli_epi32(xi, 23), iset(126));                      // x = m·2^e, m in [0.5, 1)
  vf m = asf(_mm256_or_si256(_mm256_and_si256(xi, iset(0x007FFFFF)), iset(0x3F000000)));
  const vf small = lt(m, fset(0.707106781186547524f));
  e = _mm256_sub_epi32(e, _mm256_and_si256(asi(small), iset(1)));
  vf z = _mm256_sub_ps(_mm256_add_ps(m, _mm256_and_ps(small, m)), fset(1.0f));        // 2m − 1 or m − 1
  const vf ef = _mm256_cvtepi32_ps(e);
  const vf z2 = _mm256_mul_ps(z, z);
  vf y = fset(7.0376836292E-2f);
  y = _mm256_add_ps(_mm256_mul_ps(y, z), fset(-1.1514610310E-1f));
  y = _mm256_add_ps(_mm256_mul_ps(y, z), fset(1.1676998740E-1f));
  y = _mm256_add_ps(_mm256_mul_ps(y, z), fset(-1.2420140846E-1f));
  y = _mm256_add_ps(_mm256_mul_ps(y, z), fset(1.4249322787E-1f));
  y = _mm256_add_ps(_mm256_mul_ps(y, z), fset(-1.6668057665E-1f));
  y = _mm256_add_ps(_mm256_mul_ps(y, z), fset(2.0000714765E-1f));
  y = _mm256_add_ps(_mm256_mul_ps(y, z), fset(-2.4999993993E-1f));
  y = _mm256_add_ps(_mm256_mul_ps(y, z), fset(3.3333331174E-1f));
  y = _mm256_mul_ps(_mm256_mul_ps(y, z), z2);
  y = _mm256_add_ps(y, _mm256_mul_ps(ef, fset(-2.12194440e-4f)));
  y = _mm256_sub_ps(y, _mm256_mul_ps(z2, fset(0.5f)));
  return _mm256_add_ps(_mm256_add_ps(z, y), _mm256_mul_ps(ef, fset(0.693359375f)));
}

// exp x (0 below −87.3, +inf above 88.72)
inline vf vexp(vf x) {
  const vf hi = gt(x, fset(88.7228391f)), lo = lt(x, fset(-87.3365448f));
  vf xc = _mm256_min_ps(_mm256_max_ps(x, fset(-87.3365448f)), fset(88.7228391f));
  const vf fx = _mm256_floor_ps(_mm256_add_ps(_mm256_mul_ps(xc, fset(1.44269504088896341f)), fset(0.5f)));
  xc = _mm256_sub_ps(xc, _mm256_mul_ps(fx, fset(0.693359375f)));
  xc = _mm256_sub_ps(xc, _mm256_mul_ps(fx, fset(-2.12194440e-4f)));
  const vf z = _mm256_mul_ps(xc, xc);
  vf y = fset(1.9875691500E-4f);
  y = _mm256_add_ps(_mm256_mul_ps(y, xc), fset(1.3981999507E-3f));
  y = _mm256_add_ps(_mm256_mul_ps(y, xc), fset(8.3334519073E-3f));
  y = _mm256_add_ps(_mm256_mul_ps(y, xc), fset(4.1665795894E-2f));
  y = _mm256_add_ps(_mm256_mul_ps(y, xc), fset(1.6666665459E-1f));
  y = _mm256_add_ps(_mm256_mul_ps(y, xc), fset(5.0000001201E-1f));
  y = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(y, z), xc), fset(1.0f));
  // 2^fx in two halves (fx in [−126, 128])
  const vi n = _mm256_cvtps_epi32(fx);
  const vi n1 = _mm256_srai_epi32(n, 1), n2 = _mm256_sub_epi32(n, n1);
  const vf s1 = asf(_mm256_slli_epi32(_mm256_add_epi32(n1, iset(127)), 23));
  const vf s2 = asf(_mm256_slli_epi32(_mm256_add_epi32(n2, iset(127)), 23));
  y = _mm256_mul_ps(_mm256_mul_ps(y, s1), s2);
  y = sel(hi, fset(__builtin_inff()), y);
  return _mm256_andnot_ps(lo, y);
}

// sin and cos of 2π·u for u in (0, 1): quadrant from round(4u) (exact), polynomials on [−π/4, π/4]
inline void vsincos_turns(vf u, vf* s, vf* c) {
  const vf jf = _mm256_round_ps(_mm256_mul_ps(u, fset(4.0f)), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  const vf r = _mm256_sub_ps(u, _mm256_mul_ps(jf, fset(0.25f)));                     // exact, |r| <= 1/8
  const vf x = _mm256_mul_ps(r, fset(6.283185307179586f));
  const vf z = _mm256_mul_ps(x, x);
  vf ps = fset(-1.9515295891E-4f);
  ps = _mm256_add_ps(_mm256_mul_ps(ps, z), fset(8.3321608736E-3f));
  ps = _mm256_add_ps(_mm256_mul_ps(ps, z), fset(-1.6666654611E-1f));
  ps = _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(ps, z), x), x);
  vf pc = fset(2.443315711809948E-5f);
  pc = _mm256_add_ps(_mm256_mul_ps(pc, z), fset(-1.388731625493765E-3f));
  pc = _mm256_add_ps(_mm256_mul_ps(pc, z), fset(4.166664568298827E-2f));
  pc = _mm256_add_ps(_mm256_sub_ps(_mm256_mul_ps(_mm256_mul_ps(pc, z), z), _mm256_mul_ps(z, fset(0.5f))), fset(1.0f));
  const vi j = _mm256_and_si256(_mm256_cvtps_epi32(jf), iset(3));
  const vf swap = asf(_mm256_and_si256(_mm256_cmpeq_epi32(_mm256_and_si256(j, iset(1)), iset(1)), iset(-1)));
  vf sv = sel(swap, pc, ps), cv = sel(swap, ps, pc);
  // sin sign: quadrants 2, 3 negative; cos sign: quadrants 1, 2 negative
  const vi sneg = _mm256_slli_epi32(_mm256_srli_epi32(j, 1), 31);
  const vi cneg = _mm256_slli_epi32(_mm256_xor_si256(_mm256_srli_epi32(j, 1), _mm256_and_si256(j, iset(1))), 31);
  *s = asf(_mm256_xor_si256(asi(sv), sneg));
  *c = asf(_mm256_xor_si256(asi(cv), cneg));
}

// Henyey–Greenstein cosine (optics.h sample_hg_cos), g the same for every lane
inline vf hg_cos(float g, vf u) {
  if (g < 1e-3f && g > -1e-3f) return _mm256_sub_ps(fset(1.0f), _mm256_mul_ps(fset(2.0f), u));
  const vf s = _mm256_div_ps(fset(1.0f - g * g), _mm256_add_ps(fset(1.0f - g), _mm256_mul_ps(fset(2.0f * g), u)));
  const vf c = _mm256_mul_ps(_mm256_sub_ps(fset(1.0f + g * g), _mm256_mul_ps(s, s)), fset(1.0f / (2.0f * g)));
  return tmin(fset(1.0f), tmax(fset(-1.0f), c));
}

// new direction at angle acos(cos_t) from d, azimuth 2π u (optics.h rotate_direction: frame of Duff et al. 2017)
inline void rotate(vf d[3], vf cos_t, vf u) {
  const vf sin_t = _mm256_sqrt_ps(tmax(fset(0.0f), _mm256_sub_ps(fset(1.0f), _mm256_mul_ps(cos_t, cos_t))));
  vf sp, cp;
  vsincos_turns(u, &sp, &cp);
  const vf sign = _mm256_or_ps(_mm256_and_ps(d[2], fset(-0.0f)), fset(1.0f));  // copysign(1, d_z)
  const vf a = _mm256_div_ps(fset(-1.0f), _mm256_add_ps(sign, d[2]));
  const vf b = _mm256_mul_ps(_mm256_mul_ps(d[0], d[1]), a);
  const vf b1[3] = {_mm256_add_ps(fset(1.0f), _mm256_mul_ps(_mm256_mul_ps(_mm256_mul_ps(sign, d[0]), d[0]), a)),
                    _mm256_mul_ps(sign, b), _mm256_xor_ps(_mm256_mul_ps(sign, d[0]), fset(-0.0f))};
  const vf b2[3] = {b, _mm256_add_ps(sign, _mm256_mul_ps(_mm256_mul_ps(d[1], d[1]), a)),
                    _mm256_xor_ps(d[1], fset(-0.0f))};
  vf n[3];
  for (int k = 0; k < 3; ++k)
    n[k] = _mm256_add_ps(
        _mm256_mul_ps(sin_t, _mm256_add_ps(_mm256_mul_ps(cp, b1[k]), _mm256_mul_ps(sp, b2[k]))),
        _mm256_mul_ps(cos_t, d[k]));
  const vf len2 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(n[0], n[0]), _mm256_mul_ps(n[1], n[1])),
                                _mm256_mul_ps(n[2], n[2]));
  const vf inv = _mm256_div_ps(fset(1.0f), _mm256_sqrt_ps(len2));
  for (int k = 0; k < 3; ++k) d[k] = _mm256_mul_ps(n[k], inv);
}

// unpolarised Fresnel reflectance from inside (eta = ior), 1 under total internal reflection
inline vf fresnel(vf cos_i, float eta) {
  const vf e = fset(eta);
  const vf sin2_t = _mm256_mul_ps(_mm256_mul_ps(e, e), _mm256_sub_ps(fset(1.0f), _mm256_mul_ps(cos_i, cos_i)));
  const vf tir = ge(sin2_t, fset(1.0f));
  const vf cos_t = _mm256_sqrt_ps(_mm256_max_ps(fset(0.0f), _mm256_sub_ps(fset(1.0f), sin2_t)));
  const vf ec = _mm256_mul_ps(e, cos_i), et = _mm256_mul_ps(e, cos_t);
  const vf rs = _mm256_div_ps(_mm256_sub_ps(ec, cos_t), _mm256_add_ps(ec, cos_t));
  const vf rp = _mm256_div_ps(_mm256_sub_ps(cos_i, et), _mm256_add_ps(cos_i, et));
  const vf f = _mm256_mul_ps(fset(0.5f), _mm256_add_ps(_mm256_mul_ps(rs, rs), _mm256_mul_ps(rp, rp)));
  return sel(tir, fset(1.0f), f);
}

inline float fresnel1(float cos_i, float eta) {  // scalar twin (the entry face, n_i/n_t = 1/ior)
  const float sin2_t = eta * eta * (1.0f - cos_i * cos_i);
  if (sin2_t >= 1.0f) return 1.0f;
  const float cos_t = __builtin_sqrtf(1.0f - sin2_t);
  const float rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
  const float rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
  return 0.5f * (rs * rs + rp * rp);
}

inline vf gather(const float* base, vi idx, vf mask) {
#ifdef HW_GATHER
  return _mm256_mask_i32gather_ps(_mm256_setzero_ps(), base, idx, mask, 4);
#else
  alignas(32) int32_t ii[8];
  _mm256_store_si256(reinterpret_cast<vi*>(ii), _mm256_and_si256(idx, asi(mask)));
  const vf x = _mm256_set_ps(base[ii[7]], base[ii[6]], base[ii[5]], base[ii[4]], base[ii[3]], base[ii[2]],
                             base[ii[1]], base[ii[0]]);
  return _mm256_and_ps(x, mask);
#endif
}

// Per-lane state, kept in memory between the phases of the wavefront loop (lanes are refilled one at a time).
struct alignas(32) Lanes {
  float p[3][8], d[3][8], tn[3][8], td[3][8];
  int32_t idx[3][8], step[3][8], vstep[3][8], cv[8];
  float tau[8], acc[8], t[8], u1[8], u2[8], u3[8], excess[8];
  float w[8], wref[8], prod[8];
  int32_t zeros[8], event[8], depth[8], chan[8], elem[8], sample[8], state[8];
  int64_t item[8], scatter[8];
};
enum : int32_t { kIdle = 0, kNeedFlight = 1, kFlying = 2 };
#ifndef TA_SIMD_ENDED_LANES
#define TA_SIMD_ENDED_LANES 6
#endif
constexpr int kEndedLanes = TA_SIMD_ENDED_LANES;  // flights that end before the collision phase runs (tuned: 4-8)

template <bool DIEL, bool RATIO, bool RECORD>
void walks(const SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, int64_t seg_cap,
           int64_t col_cap, WalkDone done, void* ctx) {
  static_assert(!RECORD || RATIO, "the recording walk carries ratio weights");
  const int64_t N = int64_t(S.D) * S.H * S.W;
  const int32_t HW = S.H * S.W;
  const float vs[3] = {S.voxel[0], S.voxel[1], S.voxel[2]};
  const int32_t dims[3] = {S.W, S.H, S.D};
  const bool plain_s = !(S.ref_sigma_t_floor > 0), plain_a = !(S.ref_albedo_floor > 0);
  const bool same_alb = S.albedo == S.ref_albedo && plain_a;
  const float r_entry = DIEL ? fresnel1(1.0f, 1.0f / S.ior) : 0.0f;

  Lanes L;
  memset(&L, 0, sizeof(L));
  TapeSegmentF* segs = nullptr;
  TapeCollisionF* cols = nullptr;
  int64_t nseg[8] = {0}, ncol[8] = {0};
  // per lane: `cap` entries and one spare slot that takes the writes of a full tape (the path is then replayed by
  // the caller: overflow when more than `cap` entries were counted)
  const int64_t seg_room = seg_cap + 1, col_room = col_cap + 1;
  if (RECORD) {
    segs = static_cast<TapeSegmentF*>(malloc(sizeof(TapeSegmentF) * size_t(8 * seg_room)));
    cols = static_cast<TapeCollisionF*>(malloc(sizeof(TapeCollisionF) * size_t(8 * col_room)));
  }

  // the next path of the batch: k (element), s (sample), c (channel)
  int64_t k = 0, s = 0;
  int c = -1;
  auto next_item = [&]() -> bool {
    for (;;) {
      ++c;
      if (c == 3) {
        c = 0;
        if (++s == S.spp) {
          s = 0;
          ++k;
        }
      }
      if (k >= n) return false;
      if (!live || (live[k] >> c) & 1) return true;
    }
  };
  auto finish = [&](int l, float value, bool escaped, bool truncated) {
    WalkOut o;
    o.item = L.item[l];
    o.value = value;
    o.prod_nonzero = L.prod[l];
    o.zeros = L.zeros[l];
    o.escaped = escaped;
    o.truncated = truncated;
    o.scatter_events = L.scatter[l];
    o.segs = RECORD ? segs + l * seg_room : nullptr;
    o.cols = RECORD ? cols + l * col_room : nullptr;
    o.nseg = nseg[l];
    o.ncol = ncol[l];
    o.overflow = RECORD && (nseg[l] > seg_cap || ncol[l] > col_cap);
    done(ctx, o);
    L.state[l] = kIdle;
  };
  // Starts paths in idle lanes until they are all busy or the batch is empty (a path may end at its start).
  bool more = true;
  auto refill = [&](int l) {
    while (L.state[l] == kIdle && more) {
      more = next_item();
      if (!more) return;
      const int64_t elem = elems[k];
      const int face = S.face == 2 ? int(elem / HW) : S.face;
      const int64_t ti = elem % HW;
      const int32_t tj = int32_t(ti / S.W), tx = int32_t(ti % S.W);
      float u[4];
      draw1(uint32_t(elem), uint32_t(s), uint32_t(c), 0u, S.seed, u);
      L.item[l] = (k * S.spp + s) * 3 + c;
      L.elem[l] = int32_t(uint32_t(elem));
      L.sample[l] = int32_t(s);
      L.chan[l] = c;
      L.event[l] = 1;
      L.depth[l] = 0;
      L.scatter[l] = 0;
      L.w[l] = L.wref[l] = L.prod[l] = 1.0f;
      L.zeros[l] = 0;
      nseg[l] = ncol[l] = 0;
      L.p[0][l] = (float(tx) + u[0]) * vs[0];
      L.p[1][l] = (float(tj) + u[1]) * vs[1];
      L.p[2][l] = face == 0 ? float(S.D) * vs[2] : 0.0f;
      L.d[0][l] = L.d[1][l] = 0.0f;
      L.d[2][l] = face == 0 ? -1.0f : 1.0f;
      L.idx[0][l] = tx;
      L.idx[1][l] = tj;
      L.idx[2][l] = face == 0 ? S.D - 1 : 0;
      L.state[l] = kNeedFlight;
      if (DIEL && u[2] < r_entry) finish(l, 1.0f, true, false);  // specular reflection at the entry face
    }
  };
  for (int l = 0; l < 8; ++l) refill(l);

  const vi Wv = iset(S.W), HWv = iset(HW), Nv = iset(int32_t(N));
  for (;;) {
    const vi state = _mm256_load_si256(reinterpret_cast<const vi*>(L.state));
    const vf active = asf(_mm256_cmpgt_epi32(state, iset(0)));
    if (!bits(active)) break;
    vf p[3], d[3], tn[3], td[3];
    vi idx[3], step[3], vstep[3];
    for (int a = 0; a < 3; ++a) {
      p[a] = _mm256_load_ps(L.p[a]);
      d[a] = _mm256_load_ps(L.d[a]);
      tn[a] = _mm256_load_ps(L.tn[a]);
      td[a] = _mm256_load_ps(L.td[a]);
      idx[a] = _mm256_load_si256(reinterpret_cast<const vi*>(L.idx[a]));
      step[a] = _mm256_load_si256(reinterpret_cast<const vi*>(L.step[a]));
      vstep[a] = _mm256_load_si256(reinterpret_cast<const vi*>(L.vstep[a]));
    }
    vi cvox = _mm256_load_si256(reinterpret_cast<const vi*>(L.cv));
    vf tau = _mm256_load_ps(L.tau), acc = _mm256_load_ps(L.acc), t = _mm256_load_ps(L.t);
    vf u1 = _mm256_load_ps(L.u1), u2 = _mm256_load_ps(L.u2), u3 = _mm256_load_ps(L.u3);
    vf excess = _mm256_load_ps(L.excess);
    const vi chan = _mm256_load_si256(reinterpret_cast<const vi*>(L.chan));
    const vi chN = _mm256_mullo_epi32(chan, Nv);

    // ---- lanes starting a free flight: one event, the optical depth and the DDA set-up
    const vf nf = ieq(state, iset(kNeedFlight));
    if (bits(nf)) {
      vi ev = _mm256_load_si256(reinterpret_cast<const vi*>(L.event));
      vf u[4];
      draw(_mm256_load_si256(reinterpret_cast<const vi*>(L.elem)),
           _mm256_load_si256(reinterpret_cast<const vi*>(L.sample)), chan, ev, S.seed, u);
      _mm256_store_si256(reinterpret_cast<vi*>(L.event), seli(nf, _mm256_add_epi32(ev, iset(1)), ev));
      tau = sel(nf, _mm256_xor_ps(vlog(u[0]), fset(-0.0f)), tau);
      u1 = sel(nf, u[1], u1);
      u2 = sel(nf, u[2], u2);
      u3 = sel(nf, u[3], u3);
      acc = sel(nf, _mm256_setzero_ps(), acc);
      t = sel(nf, _mm256_setzero_ps(), t);
      excess = sel(nf, _mm256_setzero_ps(), excess);
      const vf inf = fset(__builtin_inff());
      for (int a = 0; a < 3; ++a) {
        const vf pos = gt(d[a], _mm256_setzero_ps()), neg = lt(d[a], _mm256_setzero_ps());
        const vf v = fset(vs[a]);
        const vf i0 = _mm256_cvtepi32_ps(idx[a]);
        const vf inv = _mm256_div_ps(fset(1.0f), d[a]);  // one division per axis (the scalar walk divides thrice)
        const vf tdp = _mm256_mul_ps(v, inv);
        const vf tnp = tmax(_mm256_setzero_ps(),
                            _mm256_mul_ps(_mm256_sub_ps(_mm256_mul_ps(_mm256_add_ps(i0, fset(1.0f)), v), p[a]), inv));
        const vf tnn = tmax(_mm256_setzero_ps(), _mm256_mul_ps(_mm256_sub_ps(_mm256_mul_ps(i0, v), p[a]), inv));
        const vf tdn = _mm256_xor_ps(tdp, fset(-0.0f));
        const vf tdx = sel(pos, tdp, sel(neg, tdn, inf));
        const vf tnx = sel(pos, tnp, sel(neg, tnn, inf));
        const vi stx = seli(pos, iset(1), seli(neg, iset(-1), iset(0)));
        td[a] = sel(nf, tdx, td[a]);
        tn[a] = sel(nf, tnx, tn[a]);
        step[a] = seli(nf, stx, step[a]);
        const int32_t stride = a == 0 ? 1 : (a == 1 ? S.W : HW);
        vstep[a] = seli(nf, seli(pos, iset(stride), seli(neg, iset(-stride), iset(0))), vstep[a]);
      }
      const vi v0 = _mm256_add_epi32(
          _mm256_add_epi32(_mm256_mullo_epi32(idx[2], HWv), _mm256_mullo_epi32(idx[1], Wv)), idx[0]);
      cvox = seli(nf, _mm256_add_epi32(chN, v0), cvox);
    }

    // ---- regular tracking: one voxel per iteration for every lane in flight, until enough flights have ended
    // (the collision and flight-start phases below cost the same for one lane or eight, so they wait for several)
    vf collided = _mm256_setzero_ps(), out = _mm256_setzero_ps(), flying = active;
    vf col_sref = fset(1.0f), col_sig = _mm256_setzero_ps();
    vi col_v = _mm256_setzero_si256(), exit_axis = iset(-1);
    do {
      const vf m01 = lt(tn[0], tn[1]), m02 = lt(tn[0], tn[2]), m12 = lt(tn[1], tn[2]);
      const vf is0 = vand(m01, m02), is1 = vandnot(m01, m12);
      const vf is2 = vandnot(vor(is0, is1), _mm256_castsi256_ps(iset(-1)));
      const vf tend = sel(is0, tn[0], sel(is1, tn[1], tn[2]));
      const vi cv = cvox;
      const vi v = _mm256_sub_epi32(cvox, chN);
      const vf seg = tmax(_mm256_setzero_ps(), _mm256_sub_ps(tend, t));
      vf sref = gather(S.ref_sigma_t, cv, flying);
      if (!plain_s) sref = tmax(sref, fset(S.ref_sigma_t_floor));
      const vf od = _mm256_mul_ps(sref, seg);
      const vf hit = vand(flying, ge(_mm256_add_ps(acc, od), tau));
      const vf len = sel(hit, _mm256_div_ps(_mm256_sub_ps(tau, acc), sel(hit, sref, fset(1.0f))), seg);
      vf sig = _mm256_setzero_ps();
      if (RATIO) {
        sig = gather(S.sigma_t, cv, flying);
        excess = sel(flying, _mm256_add_ps(excess, _mm256_mul_ps(_mm256_sub_ps(sig, sref), len)), excess);
      }
      if (RECORD) {
        alignas(32) float lens[8];
        alignas(32) int32_t vv[8];
        _mm256_store_ps(lens, len);
        _mm256_store_si256(reinterpret_cast<vi*>(vv), v);
        const int m = bits(vand(flying, gt(len, _mm256_setzero_ps())));
        for (int l = 0; l < 8; ++l) {  // branch-free: every lane writes, only the recording lanes advance
          const int64_t pos = nseg[l];
          segs[l * seg_room + (pos < seg_room ? pos : seg_room - 1)] = {int64_t(vv[l]), lens[l]};
          nseg[l] = pos + ((m >> l) & 1);
        }
      }
      col_sref = sel(hit, sref, col_sref);
      col_sig = sel(hit, sig, col_sig);
      col_v = seli(hit, v, col_v);
      // lanes that did not collide: advance to the next voxel (or leave the box)
      const vf moving = vandnot(hit, flying);
      acc = sel(moving, _mm256_add_ps(acc, od), acc);
      t = sel(hit, _mm256_add_ps(t, len), sel(moving, tend, t));
      vf left = _mm256_setzero_ps();
      for (int a = 0; a < 3; ++a) {
        const vf on = vand(moving, a == 0 ? is0 : (a == 1 ? is1 : is2));
        const vi moved = _mm256_add_epi32(idx[a], step[a]);
        const vf oob = vor(igt(iset(0), moved), igt(moved, iset(dims[a] - 1)));
        const vf leave = vand(on, oob), go = vandnot(oob, on);
        idx[a] = seli(go, moved, idx[a]);
        cvox = seli(go, _mm256_add_epi32(cvox, vstep[a]), cvox);
        tn[a] = sel(go, _mm256_add_ps(tn[a], td[a]), tn[a]);
        left = vor(left, leave);
        exit_axis = seli(leave, iset(a), exit_axis);
      }
      collided = vor(collided, hit);
      out = vor(out, left);
      flying = vandnot(vor(hit, left), flying);
    } while (bits(flying) && __builtin_popcount(bits(vor(collided, out))) < kEndedLanes);
    // lanes whose flight ended: move along it, apply the flight's transmittance ratio
    const vf ended = vor(collided, out);
    vf w = _mm256_load_ps(L.w), prod = _mm256_load_ps(L.prod);
    if (bits(ended)) {
      for (int a = 0; a < 3; ++a) p[a] = sel(ended, _mm256_add_ps(p[a], _mm256_mul_ps(d[a], t)), p[a]);
      if (RATIO) {
        const vf f = vexp(_mm256_xor_ps(excess, fset(-0.0f)));
        w = sel(ended, _mm256_mul_ps(w, f), w);
        prod = sel(ended, _mm256_mul_ps(prod, f), prod);
      }
    }
    vi depth = _mm256_load_si256(reinterpret_cast<const vi*>(L.depth));
    const vi newstate = seli(ended, iset(kNeedFlight), seli(active, iset(kFlying), iset(kIdle)));
    const vi cv = _mm256_add_epi32(chN, col_v);  // the collision voxel of lanes that collided
    int kill_trunc = 0, kill_absorb = 0, escape = 0;

    // ---- collisions
    if (bits(collided)) {
      for (int a = 0; a < 3; ++a) {
        const vf i0 = _mm256_cvtepi32_ps(idx[a]), v_ = fset(vs[a]);
        const vf lo = _mm256_mul_ps(i0, v_), hi = _mm256_mul_ps(_mm256_add_ps(i0, fset(1.0f)), v_);
        p[a] = sel(collided, tmin(hi, tmax(lo, p[a])), p[a]);
      }
      depth = seli(collided, _mm256_add_epi32(depth, iset(1)), depth);
      const vf trunc = vand(collided, igt(depth, iset(int32_t(S.max_depth < 0x7fffffff ? S.max_depth : 0x7fffffff))));
      const vf col = vandnot(trunc, collided);
      kill_trunc = bits(trunc);
      vf aref = gather(S.ref_albedo, cv, col);
      if (!plain_a) aref = tmax(aref, fset(S.ref_albedo_floor));
      const vf ps = aref;
      vf wref = _mm256_load_ps(L.wref);
      vf q = fset(1.0f);
      const vf rr = igt(depth, iset(int32_t(S.rr_depth < 0x7fffffff ? S.rr_depth : 0x7fffffff)));
      if (bits(vand(rr, col))) q = sel(rr, tmin(fset(1.0f), _mm256_div_ps(_mm256_mul_ps(wref, aref), ps)), q);
      const vf psq = _mm256_mul_ps(ps, q);
      const vf survive = vand(col, lt(u1, psq));
      kill_absorb = bits(vandnot(survive, col));
      const vf inv_psq = _mm256_div_ps(fset(1.0f), psq);
      wref = sel(survive, _mm256_mul_ps(wref, _mm256_mul_ps(aref, inv_psq)), wref);
      _mm256_store_ps(L.wref, wref);
      if (RATIO) {
        const vf alb = same_alb ? aref : gather(S.albedo, cv, survive);
        const vf fa = _mm256_mul_ps(alb, inv_psq);
        const vf fs = _mm256_div_ps(col_sig, col_sref);
        w = sel(survive, _mm256_mul_ps(w, _mm256_mul_ps(fs, fa)), w);
        const vf zs = eq(fs, _mm256_setzero_ps()), za = eq(fa, _mm256_setzero_ps());
        prod = sel(survive, _mm256_mul_ps(_mm256_mul_ps(prod, sel(zs, fset(1.0f), fs)), sel(za, fset(1.0f), fa)),
                   prod);
        // a true mask is −1: subtracting it adds 1
        vi zeros = _mm256_load_si256(reinterpret_cast<const vi*>(L.zeros));
        zeros = _mm256_sub_epi32(zeros, asi(vand(survive, zs)));
        zeros = _mm256_sub_epi32(zeros, asi(vand(survive, za)));
        _mm256_store_si256(reinterpret_cast<vi*>(L.zeros), zeros);
        if (RECORD) {
          alignas(32) float a_sref[8], a_ipsq[8], a_fs[8], a_fa[8];
          alignas(32) int32_t vv[8];
          _mm256_store_ps(a_sref, col_sref);
          _mm256_store_ps(a_ipsq, inv_psq);
          _mm256_store_ps(a_fs, fs);
          _mm256_store_ps(a_fa, fa);
          _mm256_store_si256(reinterpret_cast<vi*>(vv), col_v);
          const int m = bits(survive);
          for (int l = 0; l < 8; ++l) {
            const int64_t pos = ncol[l];
            cols[l * col_room + (pos < col_room ? pos : col_room - 1)] = {int64_t(vv[l]), nseg[l], a_sref[l],
                                                                          a_ipsq[l], a_fs[l], a_fa[l]};
            ncol[l] = pos + ((m >> l) & 1);
          }
        }
      }
      {
        int m = bits(col);
        while (m) {
          const int l = __builtin_ctz(m);
          m &= m - 1;
          ++L.scatter[l];
        }
      }
      if (bits(survive)) {
        vf dn[3] = {d[0], d[1], d[2]};
        rotate(dn, hg_cos(S.g, u2), u3);
        for (int a = 0; a < 3; ++a) d[a] = sel(survive, dn[a], d[a]);
      }
    }

    // ---- lanes at the box: internal reflection or escape
    if (bits(out)) {
      vf cos_i = _mm256_setzero_ps();
      for (int a = 0; a < 3; ++a) {
        const vf on = vand(out, ieq(exit_axis, iset(a)));
        const vf face = sel(gt(d[a], _mm256_setzero_ps()), fset(float(dims[a]) * vs[a]), _mm256_setzero_ps());
        p[a] = sel(on, face, p[a]);
        cos_i = sel(on, _mm256_andnot_ps(fset(-0.0f), d[a]), cos_i);
      }
      vf refl = _mm256_setzero_ps();
      if (DIEL) refl = vand(out, lt(u1, fresnel(cos_i, S.ior)));
      if (bits(refl)) {
        depth = seli(refl, _mm256_add_epi32(depth, iset(1)), depth);
        const vf trunc = vand(refl, igt(depth, iset(int32_t(S.max_depth < 0x7fffffff ? S.max_depth : 0x7fffffff))));
        kill_trunc |= bits(trunc);
        const vf flip = vandnot(trunc, refl);
        for (int a = 0; a < 3; ++a) {
          const vf on = vand(flip, ieq(exit_axis, iset(a)));
          d[a] = sel(on, _mm256_xor_ps(d[a], fset(-0.0f)), d[a]);
        }
      }
      escape = bits(vandnot(refl, out));
    }

    // ---- back to memory
    for (int a = 0; a < 3; ++a) {
      _mm256_store_ps(L.p[a], p[a]);
      _mm256_store_ps(L.d[a], d[a]);
      _mm256_store_ps(L.tn[a], tn[a]);
      _mm256_store_ps(L.td[a], td[a]);
      _mm256_store_si256(reinterpret_cast<vi*>(L.idx[a]), idx[a]);
      _mm256_store_si256(reinterpret_cast<vi*>(L.step[a]), step[a]);
      _mm256_store_si256(reinterpret_cast<vi*>(L.vstep[a]), vstep[a]);
    }
    _mm256_store_si256(reinterpret_cast<vi*>(L.cv), cvox);
    _mm256_store_ps(L.tau, tau);
    _mm256_store_ps(L.acc, acc);
    _mm256_store_ps(L.t, t);
    _mm256_store_ps(L.u1, u1);
    _mm256_store_ps(L.u2, u2);
    _mm256_store_ps(L.u3, u3);
    _mm256_store_ps(L.excess, excess);
    _mm256_store_ps(L.w, w);
    _mm256_store_ps(L.prod, prod);
    _mm256_store_si256(reinterpret_cast<vi*>(L.depth), depth);
    _mm256_store_si256(reinterpret_cast<vi*>(L.state), newstate);

    // ---- paths that ended: report, then start new ones in their lanes
    const int ended_paths = kill_trunc | kill_absorb | escape;
    if (ended_paths) {
      int m = ended_paths;
      while (m) {
        const int l = __builtin_ctz(m);
        m &= m - 1;
        if ((kill_trunc >> l) & 1) finish(l, 0.0f, false, true);
        else if ((kill_absorb >> l) & 1) finish(l, 0.0f, false, false);
        else finish(l, RATIO ? L.w[l] : 1.0f, true, false);
      }
      m = ended_paths;
      while (m) {
        const int l = __builtin_ctz(m);
        m &= m - 1;
        refill(l);
      }
    }
  }
  free(segs);
  free(cols);
}

}  // namespace

void slab_walks_avx2(const SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                     bool record, int64_t seg_cap, int64_t col_cap, WalkDone done, void* ctx) {
  if (S.dielectric) {
    if (record) walks<true, true, true>(S, elems, live, n, seg_cap, col_cap, done, ctx);
    else if (ratio) walks<true, true, false>(S, elems, live, n, 0, 0, done, ctx);
    else walks<true, false, false>(S, elems, live, n, 0, 0, done, ctx);
  } else {
    if (record) walks<false, true, true>(S, elems, live, n, seg_cap, col_cap, done, ctx);
    else if (ratio) walks<false, true, false>(S, elems, live, n, 0, 0, done, ctx);
    else walks<false, false, false>(S, elems, live, n, 0, 0, done, ctx);
  }
}

}  // namespace simd
}  // namespace ta

#if defined(__clang__)
#pragma clang attribute pop
#endif

#else  // not x86: no AVX2 walk (cpu_has_avx2() in volpath_cpu.cpp is false there, so this is never called)

namespace ta {
namespace simd {
void slab_walks_avx2(const SlabWalkScene&, const int64_t*, const uint8_t*, int64_t, bool, bool, int64_t, int64_t,
                     WalkDone, void*) {
  __builtin_trap();
}
}  // namespace simd
}  // namespace ta

#endif
