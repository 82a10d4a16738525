// The object walk of object_simd.h written once for any SIMD width. Not a normal header: an instruction-set
// translation unit (slab_simd_avx2.cpp, slab_simd_avx512.cpp) includes it inside its anonymous namespace after
// simd_math.h, with the vector operations listed in slab_simd_walk.h and
//   cvttfi                    float → int32, truncated
//   gather_u8(base, idx, M)   base[idx] of a byte grid (0 outside M)
//
// Each lane follows core::trace_path<float, CH, kSDFBoundary, DIELECTRIC, RATIO, false, RECORD> step by step
// (integrator.h is the reference; its steps are named here), CH = 1 (the lane's channel) or 3 (one path for the three
// channels: flights sampled with channel 0's reference σ̂, a weight, a reference weight and a flight excess per
// channel, p_s the largest reference albedo of the three):
//   start    (begin_path, start_at_sensor, enter_from_outside) the scalar step `start`;
//   flight   (fly) one event per free flight: u0 the optical depth −log u0 in the reference medium, u1 for what ends
//            the flight, u2 u3 the new direction; per iteration of the wavefront loop each lane in flight either
//            steps through one voxel (VoxelDDA; in a mixed cell the lanes find whether and where the ray crosses
//            the surface there, `crossings`: SDFGrid::crossing in lanes) or, in a brick of the
//            homogeneous core, crosses or collides in the box of core bricks around it in one move
//            (VoxelDDA::brick_box, voxel_in, leave), with the core's values and no ratio weight or tape entry;
//            a palette medium (a quantised print) reads each voxel's entry and the tables;
//   collide  (collide) depth cut, continuation p_s = α̂ times roulette q on the reference weight, the factors
//            σ/σ̂ and α/(p_s q) (the core's values in a core brick, and no tape entry there), the new direction;
//   surface  (cross_from_inside, enter_from_outside) the scalar step `surface`, where a flight ends at the surface
//            or the grid's box.
// The DDA's set-up and steps, the core boxes, the collision and the direction are the scalar walk's expressions in
// its order (no contraction), so with ObjectWalkScene::exact_math (libm per lane) every path is the scalar one.

// libm per lane (exact_math) or the polynomials of simd_math.h
template <bool EXACT>
inline F olog(F x) {
  if constexpr (!EXACT) {
    return vlog(x);
  } else {
    alignas(64) float a[kLanes];
    storef(a, x);
    for (int l = 0; l < kLanes; ++l) a[l] = __builtin_logf(a[l]);
    return loadf(a);
  }
}

template <bool EXACT>
inline F oexp(F x) {
  if constexpr (!EXACT) {
    return vexp(x);
  } else {
    alignas(64) float a[kLanes];
    storef(a, x);
    for (int l = 0; l < kLanes; ++l) a[l] = __builtin_expf(a[l]);
    return loadf(a);
  }
}

// the new direction (rotate_direction): sin and cos of the azimuth 2π·u as the scalar walk computes them
template <bool EXACT>
inline void orotate(F d[3], F cos_t, F u) {
  F sp, cp;
  if constexpr (!EXACT) {
    vsincos_turns(u, &sp, &cp);
  } else {
    alignas(64) float a[kLanes], s[kLanes], c[kLanes];
    storef(a, mul(fset(6.283185307179586f), u));
    for (int l = 0; l < kLanes; ++l) {
      s[l] = __builtin_sinf(a[l]);
      c[l] = __builtin_cosf(a[l]);
    }
    sp = loadf(s);
    cp = loadf(c);
  }
  rotate_sc(d, cos_t, sp, cp);
}

// nextafter(x, y) per lane for finite x and y (the scalar walk's tnextafter): the neighbouring float of x toward y
inline F onextafter(F x, F y) {
  const F zero = fzero();
  const M up = lt(x, y);
  const M grow = mor(mand(up, gt(x, zero)), mandnot(up, lt(x, zero)));  // |x| grows: one more unit in the last place
  const I bx = asi(x);
  I r = seli(grow, iadd(bx, iset(1)), isub(bx, iset(1)));
  r = seli(eq(x, zero), seli(up, iset(1), iset(int32_t(0x80000001u))), r);  // ±0: the smallest subnormal toward y
  return sel(eq(x, y), y, asf(r));
}

// SDFGrid::crossing(..., side = +1) in the lanes of `m` (mixed cells idx, the ray p + t·d over [t0, t1]): its
// expressions in its order (the cubic's coefficients, the roots of its derivative, the first monotone piece that rises
// to h >= 0, and the safeguarded Newton steps down to adjacent numbers, lanes stepping together until the last one is
// done), so each lane's crossing is the scalar step's to the bit. Returns the lanes that cross, with their t_hit
// (t1 in the others).
inline M crossings(const ObjectWalkScene& S, M m, const I idx[3], const F p[3], const F d[3], F t0, F t1, F* t_hit) {
  const int32_t W1 = S.W + 1, HW1 = (S.H + 1) * W1;
  const int32_t off[8] = {0, 1, W1, W1 + 1, HW1, HW1 + 1, HW1 + W1, HW1 + W1 + 1};
  alignas(64) int32_t base[kLanes];
  alignas(64) float cs[8][kLanes];
  storei(base, iadd(iadd(imul(idx[2], iset(HW1)), imul(idx[1], iset(W1))), idx[0]));
  for (int j = 0; j < 8; ++j)
    for (int l = 0; l < kLanes; ++l) cs[j][l] = 0.0f;
  for (int mb = bits(m); mb;) {
    const int l = __builtin_ctz(unsigned(mb));
    mb &= mb - 1;
    const float* b = S.sdf + base[l];
    for (int j = 0; j < 8; ++j) cs[j][l] = b[off[j]];
  }
  F a[3], b[3];
  for (int k = 0; k < 3; ++k) {
    a[k] = sub(div(add(p[k], mul(d[k], t0)), fset(S.voxel[k])), cvtif(idx[k]));
    b[k] = div(d[k], fset(S.voxel[k]));
  }
  const F one = fset(1.0f), zero = fzero();
  F k0 = zero, k1 = zero, k2 = zero, k3 = zero;
  for (int corner = 0; corner < 8; ++corner) {
    const int ix = corner & 1, iy = (corner >> 1) & 1, iz = (corner >> 2) & 1;
    const F p0 = ix ? a[0] : sub(one, a[0]), p1 = ix ? b[0] : neg(b[0]);
    const F q0 = iy ? a[1] : sub(one, a[1]), q1 = iy ? b[1] : neg(b[1]);
    const F r0 = iz ? a[2] : sub(one, a[2]), r1 = iz ? b[2] : neg(b[2]);
    const F w = loadf(cs[corner]);  // side · c with side = +1
    k0 = add(k0, mul(mul(mul(w, p0), q0), r0));
    k1 = add(k1, mul(w, add(add(mul(mul(p1, q0), r0), mul(mul(p0, q1), r0)), mul(mul(p0, q0), r1))));
    k2 = add(k2, mul(w, add(add(mul(mul(p1, q1), r0), mul(mul(p1, q0), r1)), mul(mul(p0, q1), r1))));
    k3 = add(k3, mul(mul(mul(w, p1), q1), r1));
  }
  const F L = sub(t1, t0);
  const M ok = mand(m, gt(L, zero));
  // roots of h' = 3k3 τ² + 2k2 τ + k1 (the numerically stable form), sorted
  const F A = mul(fset(3.0f), k3), B = mul(fset(2.0f), k2), C = k1;
  const M quad = mnot(eq(A, zero));
  const F disc = sub(mul(B, B), mul(mul(fset(4.0f), A), C));
  const M two_roots = mand(quad, gt(disc, zero));
  const F sq = sqrt_(sel(two_roots, disc, zero));
  const F q = mul(fset(-0.5f), add(B, asf(ior_(asi(fabs_(sq)), iand(asi(B), asi(fset(-0.0f)))))));
  F ra = div(q, sel(two_roots, A, one));
  F rb = div(C, sel(eq(q, zero), one, q));
  M va = two_roots, vb = mandnot(eq(q, zero), two_roots);
  const M lin = mandnot(quad, mnot(eq(B, zero)));  // A == 0, B != 0: one root −C/B
  ra = sel(lin, div(neg(C), sel(lin, B, one)), ra);
  va = mor(va, lin);
  const M swap = mand(vb, lt(rb, ra));
  const F lo0 = sel(swap, rb, ra), hi0 = sel(swap, ra, rb);
  const M v0 = mand(va, mand(gt(lo0, zero), lt(lo0, L)));
  const M v1 = mand(vb, mand(gt(hi0, zero), lt(hi0, L)));
  // the pieces [0, P1], [P1, P2], [P2, L] (degenerate [L, L] where there are fewer split points)
  const F P1 = sel(v0, lo0, sel(v1, hi0, L)), P2 = sel(mand(v0, v1), hi0, L);
  auto h = [&](F x) { return add(mul(add(mul(add(mul(k3, x), k2), x), k1), x), k0); };
  const F h0 = h(zero), h1 = h(P1), h2 = h(P2), h3 = h(L);
  auto rises = [&](F ha, F hb) { return mandnot(lt(hb, zero), gt(hb, ha)); };
  const M e1 = rises(h0, h1), e2 = rises(h1, h2), e3 = rises(h2, h3);
  const M hit = mand(ok, mor(mor(e1, e2), e3));
  *t_hit = t1;
  if (!bits(hit)) return hit;
  // the first piece that rises to h >= 0: the crossing at its start, or inside it (Newton, as the scalar step)
  F lo = sel(e1, zero, sel(e2, P1, P2)), hi = sel(e1, P1, sel(e2, P2, L));
  F hl = sel(e1, h0, sel(e2, h1, h2)), hh = sel(e1, h1, sel(e2, h2, h3));
  const M at_start = mand(hit, ge(hl, zero));
  const F start = lo;
  M run = mandnot(at_start, hit);
  I same = iset(0), last = iset(0);
  const F half = fset(0.5f), three_k3 = mul(fset(3.0f), k3), two_k2 = mul(fset(2.0f), k2);
  for (int it = 0; it < 160 && bits(run); ++it) {
    const F mid = mul(half, add(lo, hi));
    const M bis = igt(same, iset(2));
    const M from_lo = lt(neg(hl), hh);
    const F s = sel(from_lo, lo, hi), hs = sel(from_lo, hl, hh);
    F mn = sub(s, div(hs, add(mul(add(mul(three_k3, s), two_k2), s), k1)));
    const F nb = onextafter(s, sel(from_lo, hi, lo));
    const M snap = mor(mand(from_lo, mand(lt(mn, nb), ge(mn, s))), mandnot(from_lo, mand(gt(mn, nb), ge(s, mn))));
    mn = sel(snap, nb, mn);
    mn = sel(mand(gt(mn, lo), lt(mn, hi)), mn, mid);
    const F mm = sel(bis, mid, mn);
    same = seli(bis, iset(0), same);
    run = mand(run, mand(gt(mm, lo), lt(mm, hi)));  // a lane whose lo and hi are adjacent numbers is done
    const F hm = h(mm);
    const M far = ge(hm, zero);
    const M up = mand(run, far), down = mandnot(far, run);
    hi = sel(up, mm, hi);
    hh = sel(up, hm, hh);
    lo = sel(down, mm, lo);
    hl = sel(down, hm, hl);
    const I side = seli(far, iset(1), iset(-1));
    same = seli(run, seli(ieq(side, last), iadd(same, iset(1)), iset(0)), same);
    last = seli(run, side, last);
  }
  *t_hit = add(t0, sel(at_start, start, hi));
  return hit;
}

// Per-lane state between the phases of the wavefront loop.
struct alignas(64) ObjLanes {
  float p[3][kLanes], d[3][kLanes], tn[3][kLanes], td[3][kLanes], dir[3][kLanes];
  int32_t idx[3][kLanes], step[3][kLanes];
  float tau[kLanes], acc[kLanes], t[kLanes], u1[kLanes], u2[kLanes], u3[kLanes];
  float excess[3][kLanes], w[3][kLanes], wref[3][kLanes], prod[3][kLanes], u_fresnel[kLanes];  // [0] for one channel
  int32_t zeros[3][kLanes], event[kLanes], depth[kLanes], chan[kLanes], elem[kLanes], sample[kLanes], state[kLanes];
  int32_t fresh[kLanes], nseg[kLanes], ncol[kLanes], vsteps[kLanes], exit_axis[kLanes];
  int64_t item[kLanes], scatter[kLanes], osteps[kLanes], cevents[kLanes];
};
enum : int32_t { kObjIdle = 0, kObjNeedFlight = 1, kObjFlying = 2 };
enum : int32_t { kObjCellInside = 1, kObjReachedSurface = 1, kObjLeftGrid = 2 };  // core::kCellInside, FlightEnd

template <bool RATIO, bool RECORD, bool EXACT, int CH>
void object_walks(const ObjectWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n,
                  const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx) {
  static_assert(!RECORD || RATIO, "the recording walk carries ratio weights");
  static_assert(CH == 1 || CH == 3, "one channel per lane, or three");
  const int32_t N = S.D * S.H * S.W;
  const float vs[3] = {S.voxel[0], S.voxel[1], S.voxel[2]};
  const int32_t dims[3] = {S.W, S.H, S.D};
  const bool plain_s = !(S.ref_sigma_t_floor > 0), plain_a = !(S.ref_albedo_floor > 0);
  const bool same_sig = S.sigma_t == S.ref_sigma_t, same_alb = S.albedo == S.ref_albedo;
  const bool pal = CH == 1 && S.index != nullptr;  // a palette medium (forward only: the reference is the medium)
  const I entries = iset(S.entries);

  ObjLanes L;
  memset(&L, 0, sizeof(L));
  const TapeSlots ts(RECORD ? tapes : nullptr);
  TapeSegmentF* const segs = ts.segs;
  TapeCollisionF* const cols = ts.cols;
  TapeCollision3F* const cols3 = ts.cols3;
  BatchOrder order(n, S.spp, live, CH == 3);  // the next path of the batch (the slab walk's order): order.next()
  // a path's end: escaped (its weights are its values) or not (0)
  auto finish = [&](int l, bool escaped, bool truncated) {
    WalkOut o;
    o.item = L.item[l];
    o.channels = CH;
    for (int c = 0; c < CH; ++c) {
      o.value[c] = escaped ? L.w[c][l] : 0.0f;
      o.prod_nonzero[c] = L.prod[c][l];
      o.zeros[c] = L.zeros[c][l];
    }
    o.escaped = escaped;
    o.truncated = truncated;
    o.scatter_events = L.scatter[l];
    ts.report(l, L.nseg[l], L.ncol[l], o);
    for (int a = 0; a < 3; ++a) o.direction[a] = L.dir[a][l];
    o.voxel_steps = L.vsteps[l];
    o.outside_steps = L.osteps[l];
    o.core_events = L.cevents[l];
    done(ctx, o);
    L.state[l] = kObjIdle;
  };
  // a lane's state to and from the scalar steps
  auto to_lane = [&](int l, ObjectLane& o) {
    for (int a = 0; a < 3; ++a) {
      o.p[a] = L.p[a][l];
      o.d[a] = L.d[a][l];
      o.idx[a] = L.idx[a][l];
    }
    o.elem = L.elem[l];
    o.sample = L.sample[l];
    o.chan = L.chan[l];
    o.depth = L.depth[l];
    o.event = uint32_t(L.event[l]);
    o.u1 = L.u1[l];
    o.u_fresnel = L.u_fresnel[l];
    o.fresh = L.fresh[l];
    for (int c = 0; c < CH; ++c) {
      o.w[c] = L.w[c][l];
      o.wref[c] = L.wref[c][l];
      o.prod[c] = L.prod[c][l];
      o.zeros[c] = L.zeros[c][l];
    }
    o.status = kLaneInside;
    o.outside_steps = 0;
  };
  // after a scalar step: on to the next flight, or the path's end
  auto settle = [&](int l, const ObjectLane& o) {
    for (int a = 0; a < 3; ++a) {
      L.p[a][l] = o.p[a];
      L.d[a][l] = o.d[a];
      L.idx[a][l] = o.idx[a];
      L.dir[a][l] = o.dir[a];
    }
    L.depth[l] = o.depth;
    L.event[l] = int32_t(o.event);
    L.u_fresnel[l] = o.u_fresnel;
    L.fresh[l] = o.fresh;
    for (int c = 0; c < CH; ++c) {
      L.w[c][l] = o.w[c];
      L.wref[c][l] = o.wref[c];
      L.prod[c][l] = o.prod[c];
      L.zeros[c][l] = o.zeros[c];
    }
    L.osteps[l] += o.outside_steps;
    if (o.status == kLaneInside) L.state[l] = kObjNeedFlight;
    else finish(l, o.status == kLaneEscaped, o.status == kLaneTruncated);
  };
  // Starts paths in idle lanes until they are all busy or the batch is empty (a path may end at its start).
  bool more = true;
  auto refill = [&](int l) {
    while (L.state[l] == kObjIdle && more) {
      more = order.next();
      if (!more) return;
      L.item[l] = order.item();
      L.elem[l] = int32_t(uint32_t(elems[order.k]));
      L.sample[l] = int32_t(order.s);
      L.chan[l] = CH == 3 ? 3 : order.c;  // (the random stream of a walk of three channels)
      L.scatter[l] = L.osteps[l] = L.cevents[l] = 0;
      L.vsteps[l] = L.nseg[l] = L.ncol[l] = 0;
      ObjectLane o;
      memset(&o, 0, sizeof(o));
      o.elem = L.elem[l];
      o.sample = L.sample[l];
      o.chan = L.chan[l];
      S.start(S.steps, o);
      settle(l, o);
    }
  };
  for (int l = 0; l < kLanes; ++l) refill(l);

  const I Wv = iset(S.W), Hv = iset(S.H), HWv = iset(S.H * S.W), Nv = iset(N);
  const I cb0 = iset(S.core_bricks[0]), cb1 = iset(S.core_bricks[1]);
  const int32_t max_depth = int32_t(S.max_depth < 0x7fffffff ? S.max_depth : 0x7fffffff);
  const int32_t rr_depth = int32_t(S.rr_depth < 0x7fffffff ? S.rr_depth : 0x7fffffff);
  const F inf = fset(__builtin_inff());
  auto by_chan = [&](const float x[3], I chan) {
    return sel(ieq(chan, iset(0)), fset(x[0]), sel(ieq(chan, iset(1)), fset(x[1]), fset(x[2])));
  };
  // channel c's value of the core (c < CH): the lane's channel, or channel c of a walk of three
  auto core_of = [&](const float x[3], I chan, int c) { return CH == 1 ? by_chan(x, chan) : fset(x[c]); };
  // the voxel of p + t·d in the box [lo, hi), clamped to it (VoxelDDA::voxel_in)
  auto voxel_in = [&](const I lo[3], const I hi[3], const F p[3], const F d[3], F t, I cell[3]) {
    for (int a = 0; a < 3; ++a) {
      const F q = div(add(p[a], mul(d[a], t)), fset(vs[a]));
      const I top = isub(hi[a], iset(1));
      cell[a] = seli(ge(q, cvtif(top)), top, seli(gt(q, cvtif(lo[a])), cvttfi(q), lo[a]));
    }
  };
  auto flat = [&](const I i[3]) { return iadd(imul(iadd(imul(i[2], Hv), i[1]), Wv), i[0]); };

  for (;;) {
    const I state = loadi(L.state);
    const M active = igt(state, iset(0));
    if (!bits(active)) break;
    F p[3], d[3], tn[3], td[3];
    I idx[3], step[3];
    for (int a = 0; a < 3; ++a) {
      p[a] = loadf(L.p[a]);
      d[a] = loadf(L.d[a]);
      tn[a] = loadf(L.tn[a]);
      td[a] = loadf(L.td[a]);
      idx[a] = loadi(L.idx[a]);
      step[a] = loadi(L.step[a]);
    }
    F tau = loadf(L.tau), acc = loadf(L.acc), t = loadf(L.t);
    F u1 = loadf(L.u1), u2 = loadf(L.u2), u3 = loadf(L.u3);
    F excess[CH];
    for (int c = 0; c < CH; ++c) excess[c] = loadf(L.excess[c]);
    const I chan = loadi(L.chan);
    const I chN = CH == 1 ? imul(chan, Nv) : iset(0);  // the sampling density's plane
    // channel c's plane (c < CH): the lane's channel, or channel c of a walk of three
    auto plane = [&](int c) { return CH == 1 ? chN : iset(c * N); };

    // ---- lanes starting a free flight: one event, the optical depth and the DDA's set-up (VoxelDDA's expressions)
    const M nf = ieq(state, iset(kObjNeedFlight));
    if (bits(nf)) {
      const I ev = loadi(L.event);
      F u[4];
      draw(loadi(L.elem), loadi(L.sample), chan, ev, S.seed, u);
      storei(L.event, seli(nf, iadd(ev, iset(1)), ev));
      tau = sel(nf, neg(olog<EXACT>(u[0])), tau);
      u1 = sel(nf, u[1], u1);
      u2 = sel(nf, u[2], u2);
      u3 = sel(nf, u[3], u3);
      acc = sel(nf, fzero(), acc);
      t = sel(nf, fzero(), t);
      for (int c = 0; c < CH; ++c) excess[c] = sel(nf, fzero(), excess[c]);
      for (int a = 0; a < 3; ++a) {
        const M pos = gt(d[a], fzero()), negd = lt(d[a], fzero());
        const F v = fset(vs[a]);
        const F i0 = cvtif(idx[a]);
        const F tdp = div(v, d[a]), tdn = div(neg(v), d[a]);
        const F tnp = tmax(fzero(), div(sub(mul(cvtif(iadd(idx[a], iset(1))), v), p[a]), d[a]));
        const F tnn = tmax(fzero(), div(sub(mul(i0, v), p[a]), d[a]));
        td[a] = sel(nf, sel(pos, tdp, sel(negd, tdn, inf)), td[a]);
        tn[a] = sel(nf, sel(pos, tnp, sel(negd, tnn, inf)), tn[a]);
        step[a] = seli(nf, seli(pos, iset(1), seli(negd, iset(-1), iset(0))), step[a]);
      }
    }

    // ---- the flights: one voxel, or one box of core bricks, per iteration for every lane in flight, until enough
    // flights have ended
    M collided = mnone(), surf = mnone(), out = mnone(), flying = active, col_core = mnone();
    F col_sref = fset(1.0f), col_sig[CH];
    for (int c = 0; c < CH; ++c) col_sig[c] = fzero();
    I col_v = iset(0), exit_axis = iset(-1);
    I hit_idx[3] = {idx[0], idx[1], idx[2]};
    I nseg = RECORD ? loadi(L.nseg) : iset(0);
    I vsteps = loadi(L.vsteps);
    do {
      vsteps = iadd1(vsteps, flying);
      I kc = iset(0);  // the core distance of the lane's brick (Medium::core_distance)
      if (S.core != nullptr) {
        const I b = iadd(imul(iadd(imul(srai<2>(idx[2]), cb1), srai<2>(idx[1])), cb0), srai<2>(idx[0]));
        kc = gather_u8(S.core, b, flying);
      }
      const M incore = mand(flying, igt(kc, iset(0)));
      const M vox = mandnot(incore, flying);
      const M m01 = lt(tn[0], tn[1]), m02 = lt(tn[0], tn[2]), m12 = lt(tn[1], tn[2]);
      const M is0 = mand(m01, m02), is1 = mandnot(m01, m12);
      const M is2 = mnot(mor(is0, is1));
      const F t1 = sel(is0, tn[0], sel(is1, tn[1], tn[2]));  // where the ray leaves the voxel
      F tend = t1;
      const I v = flat(idx);
      if (int mp = bits(vox)) {  // ask for the next voxel's values while this one's are loaded (cache misses)
        const I stride = seli(is0, iset(1), seli(is1, Wv, HWv));
        const I vn = iadd(v, imul(seli(is0, step[0], seli(is1, step[1], step[2])), stride));
        alignas(64) int32_t na[kLanes], ca[kLanes];
        storei(na, vn);
        storei(ca, iadd(chN, vn));
        while (mp) {
          const int l = __builtin_ctz(unsigned(mp));
          mp &= mp - 1;
          if (pal) {
            __builtin_prefetch(S.index + na[l]);
          } else {
            __builtin_prefetch(S.ref_sigma_t + ca[l]);
            __builtin_prefetch(S.ref_albedo + ca[l]);  // a collision's albedo (every second voxel step or so)
          }
          __builtin_prefetch(S.cell + na[l]);
          if (RATIO && !same_sig) __builtin_prefetch(S.sigma_t + ca[l]);
          if (RATIO && !same_alb) __builtin_prefetch(S.albedo + ca[l]);
        }
      }
      M hit_here = mnone();
      if (bits(vox)) {
        const I ck = gather_u8(S.cell, v, vox);
        const M mixed = mand(vox, mnot(ieq(ck, iset(kObjCellInside))));
        int mb = bits(mixed);
        if (mb && S.sdf != nullptr) {
          // a lane in a mixed cell asks for the next cell's corner values too (its next cell is often mixed)
          const int32_t W1 = S.W + 1, HW1 = (S.H + 1) * W1;
          const I nidx0 = iadd(idx[0], seli(is0, step[0], iset(0)));
          const I nidx1 = iadd(idx[1], seli(is1, step[1], iset(0)));
          const I nidx2 = iadd(idx[2], seli(is2, step[2], iset(0)));
          alignas(64) int32_t nb[kLanes];
          storei(nb, iadd(iadd(imul(nidx2, iset(HW1)), imul(nidx1, iset(W1))), nidx0));
          for (int m = mb; m;) {
            const int l = __builtin_ctz(unsigned(m));
            m &= m - 1;
            const float* c = S.sdf + nb[l];
            __builtin_prefetch(c);
            __builtin_prefetch(c + W1);
            __builtin_prefetch(c + HW1);
            __builtin_prefetch(c + HW1 + W1);
          }
          F th;
          hit_here = crossings(S, mixed, idx, p, d, t, tend, &th);  // (most flights pass no surface)
          tend = sel(hit_here, th, tend);
        }
      }
      const F seg = tmax(fzero(), sub(tend, t));
      const F raw = pal ? gather(S.sigma_t_table, iadd(imul(chan, entries), gather_u8(S.index, v, vox)), vox)
                        : gather(S.ref_sigma_t, iadd(chN, v), vox);
      const F sref = plain_s ? raw : tmax(raw, fset(S.ref_sigma_t_floor));
      // the box of core bricks within k − 1 bricks (VoxelDDA::brick_box)
      F tb = fzero(), sref_c = fset(1.0f);
      I blo[3] = {iset(0), iset(0), iset(0)}, bhi[3] = {iset(1), iset(1), iset(1)}, baxis = iset(-1);
      if (bits(incore)) {
        F tbox = inf;
        const I km1 = isub(kc, iset(1));
        for (int a = 0; a < 3; ++a) {
          const I brick = srai<2>(idx[a]);
          const I lo = slli<2>(isub(brick, km1)), hi = slli<2>(iadd(brick, kc));
          blo[a] = seli(igt(iset(0), lo), iset(0), lo);
          bhi[a] = seli(igt(hi, iset(dims[a])), iset(dims[a]), hi);
          const I plane = seli(igt(step[a], iset(0)), bhi[a], blo[a]);
          const F ta = div(sub(mul(cvtif(plane), fset(vs[a])), p[a]), d[a]);
          const M better = mandnot(ieq(step[a], iset(0)), lt(ta, tbox));
          tbox = sel(better, ta, tbox);
          baxis = seli(better, iset(a), baxis);
        }
        tb = tmax(tbox, t);
        sref_c = core_of(S.core_sigma_t, chan, 0);
      }
      const F od = sel(incore, mul(sref_c, sub(tb, t)), mul(sref, seg));
      const F sx = sel(incore, sref_c, sref);
      const M hit = mand(flying, ge(add(acc, od), tau));
      const F len = sel(hit, div(sub(tau, acc), sel(hit, sx, fset(1.0f))), sel(incore, sub(tb, t), seg));
      F sig[CH];
      for (int c = 0; c < CH; ++c) sig[c] = fzero();
      if (RATIO) {  // (a core box adds (σ − σ̂)·ℓ = 0 to the channel that samples; to the others in a walk of three)
        for (int c = 0; c < CH; ++c) {
          sig[c] = same_sig && c == 0 ? raw : gather(S.sigma_t, iadd(plane(c), v), vox);
          excess[c] = sel(vox, add(excess[c], mul(sub(sig[c], sref), len)), excess[c]);
          if (CH == 3 && bits(incore))
            excess[c] = sel(incore, add(excess[c], mul(sub(fset(S.core_sigma_t[c]), sref_c), len)), excess[c]);
        }
      }
      if (RECORD) {  // a full tape's lane writes its spare slot and counts up to the room (then overflow)
        const M rec = mand(vox, gt(len, fzero()));
        store_pairs(segs, ts.seg_slot(nseg), v, asi(len), rec);
        nseg = ts.seg_count(nseg, rec);
      }
      // the collisions: in this voxel, or in the core box at t + len
      const M hit_c = mand(hit, incore);
      I ih[3] = {idx[0], idx[1], idx[2]};
      I vh = v;
      if (bits(hit_c)) {
        I cell[3];
        voxel_in(blo, bhi, p, d, add(t, len), cell);
        for (int a = 0; a < 3; ++a) ih[a] = seli(hit_c, cell[a], ih[a]);
        vh = seli(hit_c, flat(cell), vh);
      }
      col_v = seli(hit, vh, col_v);
      for (int a = 0; a < 3; ++a) hit_idx[a] = seli(hit, ih[a], hit_idx[a]);
      col_sref = sel(hit, sx, col_sref);
      for (int c = 0; c < CH; ++c) col_sig[c] = sel(mandnot(incore, hit), sig[c], col_sig[c]);
      col_core = mor(col_core, hit_c);
      // the others move on: to the surface, the next voxel, past the core box, or out of the grid
      const M moving = mandnot(hit, flying);
      acc = sel(moving, add(acc, od), acc);
      const M at_surf = mand(moving, hit_here);
      const M vstep = mandnot(hit_here, mand(moving, vox));
      const M cmove = mand(moving, incore);
      t = sel(hit, add(t, len), sel(at_surf, tend, sel(vstep, t1, sel(cmove, tb, t))));
      M left = mnone();
      for (int a = 0; a < 3; ++a) {  // VoxelDDA::next
        const M axis = mand(vstep, a == 0 ? is0 : (a == 1 ? is1 : is2));
        const I moved = iadd(idx[a], step[a]);
        const M oob = mor(igt(iset(0), moved), igt(moved, iset(dims[a] - 1)));
        const M go = mandnot(oob, axis);
        const M lv = mand(axis, oob);
        left = mor(left, lv);
        exit_axis = seli(lv, iset(a), exit_axis);
        idx[a] = seli(go, moved, idx[a]);
        tn[a] = sel(go, add(tn[a], td[a]), tn[a]);
      }
      if (bits(cmove)) {  // VoxelDDA::leave
        I cell[3];
        voxel_in(blo, bhi, p, d, tb, cell);
        const M noaxis = mand(cmove, ieq(baxis, iset(-1)));  // (only a zero direction)
        M lv = mnone();
        I outv[3];
        for (int a = 0; a < 3; ++a) {
          outv[a] = seli(igt(step[a], iset(0)), bhi[a], isub(blo[a], iset(1)));
          const M oob = mor(igt(iset(0), outv[a]), igt(outv[a], iset(dims[a] - 1)));
          lv = mor(lv, mand(cmove, mand(ieq(baxis, iset(a)), oob)));
        }
        exit_axis = seli(lv, baxis, exit_axis);
        exit_axis = seli(noaxis, seli(is0, iset(0), seli(is1, iset(1), iset(2))), exit_axis);
        const M stay = mandnot(mor(lv, noaxis), cmove);
        for (int a = 0; a < 3; ++a) {
          idx[a] = seli(lv, cell[a], seli(stay, seli(ieq(baxis, iset(a)), outv[a], cell[a]), idx[a]));
          const I plane = seli(igt(step[a], iset(0)), iadd(idx[a], iset(1)), idx[a]);
          const F tna = tmax(tb, div(sub(mul(cvtif(plane), fset(vs[a])), p[a]), d[a]));
          tn[a] = sel(mandnot(ieq(step[a], iset(0)), stay), tna, tn[a]);
        }
        left = mor(left, mor(lv, noaxis));
      }
      collided = mor(collided, hit);
      surf = mor(surf, at_surf);
      out = mor(out, left);
      flying = mandnot(mor(mor(hit, at_surf), left), flying);
    } while (bits(flying) && __builtin_popcount(unsigned(bits(mor(mor(collided, surf), out)))) < ended_lanes);
    if (RECORD) storei(L.nseg, nseg);
    storei(L.vsteps, vsteps);
    for (int a = 0; a < 3; ++a) idx[a] = seli(collided, hit_idx[a], idx[a]);
    // lanes whose flight ended: move along it, apply the flight's transmittance ratio
    const M ended = mor(mor(collided, surf), out);
    F w[CH], prod[CH];
    for (int c = 0; c < CH; ++c) {
      w[c] = loadf(L.w[c]);
      prod[c] = loadf(L.prod[c]);
    }
    if (bits(ended)) {
      for (int a = 0; a < 3; ++a) p[a] = sel(ended, add(p[a], mul(d[a], t)), p[a]);
      if (RATIO) {
        for (int c = 0; c < CH; ++c) {
          const F f = oexp<EXACT>(neg(excess[c]));
          w[c] = sel(ended, mul(w[c], f), w[c]);
          prod[c] = sel(ended, mul(prod[c], f), prod[c]);
        }
      }
    }
    I depth = loadi(L.depth);
    const I newstate = seli(ended, iset(kObjNeedFlight), seli(active, iset(kObjFlying), iset(kObjIdle)));
    int kill_trunc = 0, kill_absorb = 0;

    // ---- collisions (collide)
    if (bits(collided)) {
      for (int a = 0; a < 3; ++a) {
        const F lo = mul(cvtif(idx[a]), fset(vs[a])), hi = mul(cvtif(iadd(idx[a], iset(1))), fset(vs[a]));
        p[a] = sel(collided, tmin(hi, tmax(lo, p[a])), p[a]);
      }
      depth = seli(collided, iadd(depth, iset(1)), depth);
      const M trunc = mand(collided, igt(depth, iset(max_depth)));
      const M col = mandnot(trunc, collided);
      kill_trunc = bits(trunc);
      {
        int m = bits(col);
        const int mc = bits(col_core);
        while (m) {
          const int l = __builtin_ctz(unsigned(m));
          m &= m - 1;
          ++L.scatter[l];
          L.cevents[l] += (mc >> l) & 1;
        }
      }
      // continuation p_s: the reference albedo (the largest of the three in a walk of three), times roulette q on
      // the reference weight
      const M colv = mandnot(col_core, col);
      F araw[CH], aref[CH];
      F ps = fzero();
      for (int c = 0; c < CH; ++c) {
        araw[c] = pal ? gather(S.albedo_table, iadd(imul(chan, entries), gather_u8(S.index, col_v, colv)), colv)
                      : gather(S.ref_albedo, iadd(plane(c), col_v), colv);
        aref[c] = sel(col_core, core_of(S.core_albedo, chan, c),
                      plain_a ? araw[c] : tmax(araw[c], fset(S.ref_albedo_floor)));
        ps = CH == 1 ? aref[c] : tmax(ps, aref[c]);
      }
      F wref[CH];
      for (int c = 0; c < CH; ++c) wref[c] = loadf(L.wref[c]);
      F q = fset(1.0f);
      const M rr = igt(depth, iset(rr_depth));
      if (bits(mand(rr, col))) {
        F m = fzero();
        for (int c = 0; c < CH; ++c) m = tmax(m, div(mul(wref[c], aref[c]), ps));
        q = sel(rr, tmin(fset(1.0f), m), q);
      }
      const F psq = mul(ps, q);
      const M survive = mand(col, lt(u1, psq));
      kill_absorb = bits(mandnot(survive, col));
      const F inv_psq = div(fset(1.0f), psq);
      for (int c = 0; c < CH; ++c) {
        wref[c] = sel(survive, mul(wref[c], mul(aref[c], inv_psq)), wref[c]);
        storef(L.wref[c], wref[c]);
      }
      if (RATIO || CH == 3) {  // the collision's factors σ/σ̂ (1 without ratio weights) and α/(p_s q)
        F fs[CH], fa[CH];
        for (int c = 0; c < CH; ++c) {
          const F alb0 = same_alb ? araw[c] : gather(S.albedo, iadd(plane(c), col_v), mandnot(col_core, survive));
          const F alb = sel(col_core, core_of(S.core_albedo, chan, c), alb0);
          fa[c] = mul(alb, inv_psq);
          fs[c] = RATIO ? div(sel(col_core, core_of(S.core_sigma_t, chan, c), col_sig[c]), col_sref) : fset(1.0f);
          w[c] = sel(survive, mul(w[c], mul(fs[c], fa[c])), w[c]);
          const M zs = eq(fs[c], fzero()), za = eq(fa[c], fzero());
          prod[c] = sel(survive, mul(mul(prod[c], sel(zs, fset(1.0f), fs[c])), sel(za, fset(1.0f), fa[c])), prod[c]);
          I zeros = loadi(L.zeros[c]);
          zeros = iadd1(zeros, mand(survive, zs));
          zeros = iadd1(zeros, mand(survive, za));
          storei(L.zeros[c], zeros);
        }
        if (RECORD) {  // {v, seg_end}, {sref, inv_psq}, {fs, fa} per channel; none in the core
          const M rec = mandnot(col_core, survive);
          const I ncol = loadi(L.ncol);
          if (CH == 1) {
            const I s3 = ts.col_slot<3>(ncol);
            store_pairs(cols, s3, col_v, nseg, rec);
            store_pairs(cols, iadd(s3, iset(1)), asi(col_sref), asi(inv_psq), rec);
            store_pairs(cols, iadd(s3, iset(2)), asi(fs[0]), asi(fa[0]), rec);
          } else {
            const I s5 = ts.col_slot<5>(ncol);  // {v, seg_end}, {sref, inv_psq}, {fs0, fs1}, {fs2, fa0}, {fa1, fa2}
            store_pairs(cols3, s5, col_v, nseg, rec);
            store_pairs(cols3, iadd(s5, iset(1)), asi(col_sref), asi(inv_psq), rec);
            store_pairs(cols3, iadd(s5, iset(2)), asi(fs[0]), asi(fs[1]), rec);
            store_pairs(cols3, iadd(s5, iset(3)), asi(fs[2]), asi(fa[0]), rec);
            store_pairs(cols3, iadd(s5, iset(4)), asi(fa[1]), asi(fa[2]), rec);
          }
          storei(L.ncol, ts.col_count(ncol, rec));
        }
      }
      if (bits(survive)) {
        F dn[3] = {d[0], d[1], d[2]};
        orotate<EXACT>(dn, hg_cos_div(S.g, u2), u3);
        for (int a = 0; a < 3; ++a) d[a] = sel(survive, dn[a], d[a]);
      }
    }

    // ---- back to memory
    for (int a = 0; a < 3; ++a) {
      storef(L.p[a], p[a]);
      storef(L.d[a], d[a]);
      storef(L.tn[a], tn[a]);
      storef(L.td[a], td[a]);
      storei(L.idx[a], idx[a]);
      storei(L.step[a], step[a]);
    }
    storef(L.tau, tau);
    storef(L.acc, acc);
    storef(L.t, t);
    storef(L.u1, u1);
    storef(L.u2, u2);
    storef(L.u3, u3);
    for (int c = 0; c < CH; ++c) {
      storef(L.excess[c], excess[c]);
      storef(L.w[c], w[c]);
      storef(L.prod[c], prod[c]);
    }
    storei(L.depth, depth);
    storei(L.state, newstate);
    storei(L.exit_axis, exit_axis);

    // ---- paths that ended at a collision, then the lanes at the surface or the grid's box (the scalar step)
    const int killed = kill_trunc | kill_absorb;
    for (int m = killed; m;) {
      const int l = __builtin_ctz(unsigned(m));
      m &= m - 1;
      finish(l, false, (kill_trunc >> l) & 1);
    }
    const int boundary = bits(mor(surf, out)), at_surface = bits(surf);
    for (int m = boundary; m;) {
      const int l = __builtin_ctz(unsigned(m));
      m &= m - 1;
      ObjectLane o;
      to_lane(l, o);
      S.surface(S.steps, o, (at_surface >> l) & 1 ? kObjReachedSurface : kObjLeftGrid, L.exit_axis[l]);
      settle(l, o);
    }
    if (killed | boundary)
      for (int l = 0; l < kLanes; ++l) refill(l);
  }
}

// The entry point's body: the template instance for the scene's flags.
template <int CH>
inline void object_walks_for(const ObjectWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                             const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx) {
  if (S.exact_math) {
    if (tapes) object_walks<true, true, true, CH>(S, elems, live, n, tapes, ended_lanes, done, ctx);
    else if (ratio) object_walks<true, false, true, CH>(S, elems, live, n, nullptr, ended_lanes, done, ctx);
    else object_walks<false, false, true, CH>(S, elems, live, n, nullptr, ended_lanes, done, ctx);
  } else {
    if (tapes) object_walks<true, true, false, CH>(S, elems, live, n, tapes, ended_lanes, done, ctx);
    else if (ratio) object_walks<true, false, false, CH>(S, elems, live, n, nullptr, ended_lanes, done, ctx);
    else object_walks<false, false, false, CH>(S, elems, live, n, nullptr, ended_lanes, done, ctx);
  }
}

inline void object_walks_dispatch(const ObjectWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n,
                                  bool ratio, const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx) {
  if (ended_lanes < 1 || ended_lanes > kLanes) ended_lanes = kLanes * 3 / 4;
  if (tapes && !(tapes->seg_cap >= 0 && tapes->seg_cap <= kMaxTapeCap && tapes->col_cap >= 0 &&
                 tapes->col_cap <= kMaxTapeCap && (S.channels == 3 ? tapes->cols3 != nullptr : tapes->cols != nullptr)))
    __builtin_trap();  // (the caller checks first)
  if (S.channels == 3 && S.index != nullptr) __builtin_trap();  // (dense grids only; the glue does not ask)
  if (S.channels == 3) object_walks_for<3>(S, elems, live, n, ratio, tapes, ended_lanes, done, ctx);
  else object_walks_for<1>(S, elems, live, n, ratio, tapes, ended_lanes, done, ctx);
}
