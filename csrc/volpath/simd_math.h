// The vector operations that the SIMD walks share (slab_simd_walk.h, object_simd_walk.h): Philox4x32-10, the
// float polynomials (log, exp, sin and cos of turns), Henyey–Greenstein sampling, the rotation of a direction and
// the Fresnel reflectance, written once over the vector operations that the instruction-set translation unit
// defines (see slab_simd_walk.h for the list). Not a normal header: included inside that unit's anonymous
// namespace, before the walks.

// scalar tmin/tmax semantics: tmin(a, b) = b < a ? b : a; tmax(a, b) = a < b ? b : a
inline F tmin(F a, F b) { return sel(lt(b, a), b, a); }
inline F tmax(F a, F b) { return sel(lt(a, b), b, a); }

// ---- Philox4x32-10, kLanes counters at once (core/rng.h)
inline void philox(I c[4], uint64_t key) {
  uint32_t k0 = uint32_t(key), k1 = uint32_t(key >> 32);
  for (int r = 0; r < 10; ++r) {
    I hi0, lo0, hi1, lo1;
    mulhilo(c[0], 0xD2511F53u, &hi0, &lo0);
    mulhilo(c[2], 0xCD9E8D57u, &hi1, &lo1);
    const I n0 = ixor(ixor(hi1, c[1]), iset(int32_t(k0)));
    const I n2 = ixor(ixor(hi0, c[3]), iset(int32_t(k1)));
    c[1] = lo1;
    c[3] = lo0;
    c[0] = n0;
    c[2] = n2;
    k0 += 0x9E3779B9u;
    k1 += 0xBB67AE85u;
  }
}

// uniform in (0, 1): (float(x >> 9) + 0.5) · 2^-23, as to_unit_open<float>
inline F unit(I x) { return mul(add(cvtif(srli<9>(x)), fset(0.5f)), fset(1.0f / 8388608.0f)); }

inline void draw(I elem, I sample, I chan, I event, uint64_t key, F u[4]) {
  I c[4] = {elem, sample, chan, event};
  philox(c, key);
  for (int i = 0; i < 4; ++i) u[i] = unit(c[i]);
}

// scalar twin for a lane's start (event 0): a copy of core/rng.h's Philox, since this file must not include that
// header (its inline functions would be compiled for this instruction set and might be the copy the linker keeps)
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
inline F vlog(F x) {
  const I xi = asi(x);
  I e = isub(srli<23>(xi), iset(126));                                        // x = m·2^e, m in [0.5, 1)
  const F m = asf(ior_(iand(xi, iset(0x007FFFFF)), iset(0x3F000000)));
  const M small = lt(m, fset(0.707106781186547524f));
  e = isub(e, seli(small, iset(1), iset(0)));
  const F z = sub(add(m, sel(small, m, fzero())), fset(1.0f));                // 2m − 1 or m − 1
  const F ef = cvtif(e);
  const F z2 = mul(z, z);
  F y = fset(7.0376836292E-2f);
  y = add(mul(y, z), fset(-1.1514610310E-1f));
  y = add(mul(y, z), fset(1.1676998740E-1f));
  y = add(mul(y, z), fset(-1.2420140846E-1f));
  y = add(mul(y, z), fset(1.4249322787E-1f));
  y = add(mul(y, z), fset(-1.6668057665E-1f));
  y = add(mul(y, z), fset(2.0000714765E-1f));
  y = add(mul(y, z), fset(-2.4999993993E-1f));
  y = add(mul(y, z), fset(3.3333331174E-1f));
  y = mul(mul(y, z), z2);
  y = add(y, mul(ef, fset(-2.12194440e-4f)));
  y = sub(y, mul(z2, fset(0.5f)));
  return add(add(z, y), mul(ef, fset(0.693359375f)));
}

// exp x (0 below −87.3, +inf above 88.72)
inline F vexp(F x) {
  const M hi = gt(x, fset(88.7228391f)), lo = lt(x, fset(-87.3365448f));
  F xc = fmin_(fmax_(x, fset(-87.3365448f)), fset(88.7228391f));
  const F fx = floor_(add(mul(xc, fset(1.44269504088896341f)), fset(0.5f)));
  xc = sub(xc, mul(fx, fset(0.693359375f)));
  xc = sub(xc, mul(fx, fset(-2.12194440e-4f)));
  const F z = mul(xc, xc);
  F y = fset(1.9875691500E-4f);
  y = add(mul(y, xc), fset(1.3981999507E-3f));
  y = add(mul(y, xc), fset(8.3334519073E-3f));
  y = add(mul(y, xc), fset(4.1665795894E-2f));
  y = add(mul(y, xc), fset(1.6666665459E-1f));
  y = add(mul(y, xc), fset(5.0000001201E-1f));
  y = add(add(mul(y, z), xc), fset(1.0f));
  // 2^fx in two halves (fx in [−126, 128])
  const I n = cvtfi(fx);
  const I n1 = srai<1>(n), n2 = isub(n, n1);
  const F s1 = asf(slli<23>(iadd(n1, iset(127))));
  const F s2 = asf(slli<23>(iadd(n2, iset(127))));
  y = mul(mul(y, s1), s2);
  y = sel(hi, fset(__builtin_inff()), y);
  return sel(lo, fzero(), y);
}

// sin and cos of 2π·u for u in (0, 1): quadrant from round(4u) (exact), polynomials on [−π/4, π/4]
inline void vsincos_turns(F u, F* s, F* c) {
  const F jf = round_(mul(u, fset(4.0f)));
  const F r = sub(u, mul(jf, fset(0.25f)));                                   // exact, |r| <= 1/8
  const F x = mul(r, fset(6.283185307179586f));
  const F z = mul(x, x);
  F ps = fset(-1.9515295891E-4f);
  ps = add(mul(ps, z), fset(8.3321608736E-3f));
  ps = add(mul(ps, z), fset(-1.6666654611E-1f));
  ps = add(mul(mul(ps, z), x), x);
  F pc = fset(2.443315711809948E-5f);
  pc = add(mul(pc, z), fset(-1.388731625493765E-3f));
  pc = add(mul(pc, z), fset(4.166664568298827E-2f));
  pc = add(sub(mul(mul(pc, z), z), mul(z, fset(0.5f))), fset(1.0f));
  const I j = iand(cvtfi(jf), iset(3));
  const M swap = ieq(iand(j, iset(1)), iset(1));
  const F sv = sel(swap, pc, ps), cv = sel(swap, ps, pc);
  // sin sign: quadrants 2, 3 negative; cos sign: quadrants 1, 2 negative
  const I sneg = slli<31>(srli<1>(j));
  const I cneg = slli<31>(ixor(srli<1>(j), iand(j, iset(1))));
  *s = asf(ixor(asi(sv), sneg));
  *c = asf(ixor(asi(cv), cneg));
}

// Henyey–Greenstein cosine (optics.h sample_hg_cos), g the same for every lane
inline F hg_cos(float g, F u) {
  if (g < 1e-3f && g > -1e-3f) return sub(fset(1.0f), mul(fset(2.0f), u));
  const F s = div(fset(1.0f - g * g), add(fset(1.0f - g), mul(fset(2.0f * g), u)));
  const F c = mul(sub(fset(1.0f + g * g), mul(s, s)), fset(1.0f / (2.0f * g)));
  return tmin(fset(1.0f), tmax(fset(-1.0f), c));
}

// the same in sample_hg_cos's order of operations (a division by 2g where hg_cos multiplies by its inverse)
inline F hg_cos_div(float g, F u) {
  if (g < 1e-3f && g > -1e-3f) return sub(fset(1.0f), mul(fset(2.0f), u));
  const F s = div(fset(1.0f - g * g), add(fset(1.0f - g), mul(fset(2.0f * g), u)));
  const F c = div(sub(fset(1.0f + g * g), mul(s, s)), fset(2.0f * g));
  return tmin(fset(1.0f), tmax(fset(-1.0f), c));
}

// new direction at angle acos(cos_t) from d, azimuth 2π u (optics.h rotate_direction: frame of Duff et al. 2017)
// from the sine and cosine of the azimuth
inline void rotate_sc(F d[3], F cos_t, F sp, F cp) {
  const F sin_t = sqrt_(tmax(fzero(), sub(fset(1.0f), mul(cos_t, cos_t))));
  const F sign = sign1(d[2]);  // copysign(1, d_z)
  const F a = div(fset(-1.0f), add(sign, d[2]));
  const F b = mul(mul(d[0], d[1]), a);
  const F b1[3] = {add(fset(1.0f), mul(mul(mul(sign, d[0]), d[0]), a)), mul(sign, b), neg(mul(sign, d[0]))};
  const F b2[3] = {b, add(sign, mul(mul(d[1], d[1]), a)), neg(d[1])};
  F n[3];
  for (int k = 0; k < 3; ++k) n[k] = add(mul(sin_t, add(mul(cp, b1[k]), mul(sp, b2[k]))), mul(cos_t, d[k]));
  const F len2 = add(add(mul(n[0], n[0]), mul(n[1], n[1])), mul(n[2], n[2]));
  const F inv = div(fset(1.0f), sqrt_(len2));
  for (int k = 0; k < 3; ++k) d[k] = mul(n[k], inv);
}

inline void rotate(F d[3], F cos_t, F u) {
  F sp, cp;
  vsincos_turns(u, &sp, &cp);
  rotate_sc(d, cos_t, sp, cp);
}

// unpolarised Fresnel reflectance from inside (eta = ior), 1 under total internal reflection
inline F fresnel(F cos_i, float eta) {
  const F e = fset(eta);
  const F sin2_t = mul(mul(e, e), sub(fset(1.0f), mul(cos_i, cos_i)));
  const M tir = ge(sin2_t, fset(1.0f));
  const F cos_t = sqrt_(fmax_(fzero(), sub(fset(1.0f), sin2_t)));
  const F ec = mul(e, cos_i), et = mul(e, cos_t);
  const F rs = div(sub(ec, cos_t), add(ec, cos_t));
  const F rp = div(sub(cos_i, et), add(cos_i, et));
  const F f = mul(fset(0.5f), add(mul(rs, rs), mul(rp, rp)));
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

// ---- what the walks share besides the arithmetic

// Each lane's slots in the recording walk's tapes (LaneTapes): lane l's tape starts at l·(cap + 1); the spare entry
// takes the writes of a full tape (the path is then replayed by the caller: overflow when more than `cap` entries
// were counted). Offsets are int32 (the caps are at most kMaxTapeCap, checked by the entry point); a collision is
// three 8-byte slots (TapeCollisionF), or five for a walk of three channels per lane (TapeCollision3F, `cols3`).
struct TapeSlots {
  TapeSegmentF* segs = nullptr;
  TapeCollisionF* cols = nullptr;
  TapeCollision3F* cols3 = nullptr;
  int64_t seg_cap = 0, col_cap = 0, seg_room = 1, col_room = 1;
  I seg_base, seg_capv, seg_roomv, col_base, col_capv, col_roomv;
  explicit TapeSlots(const LaneTapes* tapes) {
    static_assert(kLanes <= kMaxLanes, "LaneTapes holds kMaxLanes tapes");
    static_assert(sizeof(TapeSegmentF) == 8 && sizeof(TapeCollisionF) == 24 && sizeof(TapeCollision3F) == 40,
                  "tape entries of 8, 3 × 8 and 5 × 8 bytes");
    if (tapes) {
      segs = tapes->segs;
      cols = tapes->cols;
      cols3 = tapes->cols3;
      seg_cap = tapes->seg_cap;
      col_cap = tapes->col_cap;
    }
    seg_room = seg_cap + 1;
    col_room = col_cap + 1;
    alignas(64) int32_t lane_ids[kLanes];
    for (int l = 0; l < kLanes; ++l) lane_ids[l] = l;
    seg_base = imul(loadi(lane_ids), iset(int32_t(seg_room)));
    seg_capv = iset(int32_t(seg_cap));
    seg_roomv = iset(int32_t(seg_room));
    col_base = imul(loadi(lane_ids), iset(int32_t(col_room)));
    col_capv = iset(int32_t(col_cap));
    col_roomv = iset(int32_t(col_room));
  }
  // the slot of each lane's next segment (its spare one when full), and the count after recording in the lanes of m
  I seg_slot(I nseg) const { return iadd(seg_base, seli(igt(nseg, seg_capv), seg_capv, nseg)); }
  I seg_count(I nseg, M m) const { return iadd1(nseg, mand(m, igt(seg_roomv, nseg))); }
  // the first 8-byte slot of each lane's next collision of K slots (3, or 5 for three channels), and the count after
  // recording in the lanes of m
  template <int K>
  I col_slot(I ncol) const {
    static_assert(K == 3 || K == 5, "a collision is 3 or 5 slots");
    const I slot = iadd(col_base, seli(igt(ncol, col_capv), col_capv, ncol));
    return K == 3 ? iadd(iadd(slot, slot), slot) : iadd(slli<2>(slot), slot);
  }
  I col_count(I ncol, M m) const { return iadd1(ncol, mand(m, igt(col_roomv, ncol))); }
  // lane l's finished tape into o
  void report(int l, int32_t nseg, int32_t ncol, WalkOut& o) const {
    o.segs = segs ? segs + l * seg_room : nullptr;
    o.cols = cols ? cols + l * col_room : nullptr;
    o.cols3 = cols3 ? cols3 + l * col_room : nullptr;
    o.nseg = nseg;
    o.ncol = ncol;
    o.overflow = segs != nullptr && (nseg > seg_cap || ncol > col_cap);
  }
};

// The order in which a batch's paths go to the lanes: channel by channel (c), then element (k) and sample (s), so
// the lanes' paths read one channel plane of the grids at a time and the caches hold a third of what three
// interleaved channels need (760² slab at 32 spp: 20.8 + 38.2 → 18.6 + 34.5 s); only the channels set in live[k].
// With `shared` one path serves the three channels: element and sample only (c = 0), where live[k] has any bit.
struct BatchOrder {
  int64_t n, spp;
  const uint8_t* live;
  bool shared;
  int64_t k = 0, s = -1;
  int c = 0;
  BatchOrder(int64_t n_, int64_t spp_, const uint8_t* live_, bool shared_ = false)
      : n(n_), spp(spp_), live(live_), shared(shared_) {}
  bool next() {
    if (n <= 0) return false;
    for (;;) {
      if (++s == spp) {
        s = 0;
        if (++k == n) {
          k = 0;
          ++c;
        }
      }
      if (c >= (shared ? 1 : 3)) return false;
      if (!live || (shared ? live[k] != 0 : ((live[k] >> c) & 1))) return true;
    }
  }
  int64_t item() const { return (k * spp + s) * 3 + c; }  // WalkOut::item
};
