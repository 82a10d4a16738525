// The slab walk of slab_simd.h written once for any SIMD width. Not a normal header: an instruction-set translation
// unit (slab_simd_avx2.cpp, slab_simd_avx512.cpp) includes it inside its anonymous namespace, after defining
//   kLanes                    lanes per vector (8, 16)
//   F, I, M                   float vector, int32 vector, lane mask
//   fset iset fzero           broadcast constants
//   add sub mul div sqrt_ fmin_ fmax_ floor_ round_ neg fabs_ sign1   float arithmetic (round_: to nearest even;
//                             fmin_/fmax_: the instruction's min/max; sign1(x) = copysign(1, x))
//   cvtif cvtfi               int → float, float → int (round to nearest)
//   iadd isub imul iand ior_ ixor srli<K> slli<K> srai<K>   int32 lanes; asf asi   bit casts
//   lt ge gt eq (F) ieq igt (I) → M;  mand mor mandnot(a, b) = !a & b, mnot, mnone, bits(M) → lane bits
//   sel(M, a, b) = M ? a : b for F, seli for I;  iadd1(I, M) adds 1 in the lanes of M
//   loadf storef loadi storei (aligned to the vector), gather(base, idx, M) = base[idx] and
//                             gather_pair(base, k, idx, M) = base[2 idx + k] (0 in lanes outside M)
//   mulhilo(a, m, hi, lo)     the 32 × 32 → 64-bit products of Philox
//   store_pairs(base, slot, a, b, M)   the 8 bytes at base + 8·slot = {a, b} (int32 bit patterns) in the lanes of M
//                             (other lanes may write their slot too: the recording walk points them at their tape's
//                             next free entry)
//
// Each lane follows core::trace_path<float, 1, kBoxBoundary, DIELECTRIC, RATIO, false, RECORD> for face texels and a
// constant emitter step by step (integrator.h is the reference, its steps named here; comments there explain the
// estimator):
//   start   (start_at_sensor) event 0: position in the texel (u0, u1), specular reflection at the entry face
//           (u2 < F(1)) escapes;
//   flight  (fly) one event per free flight: u0 the optical depth −log u0 in the reference medium, u1 absorption (at a
//           collision) or Fresnel (at the box), u2 u3 the new direction (HG cosine, azimuth 2π u3);
//   DDA     (VoxelDDA) exact regular tracking through the voxels, one voxel per iteration of the wavefront loop;
//   collide (collide) depth cut, continuation p_s = α̂ times roulette q on the reference weight, weights σ/σ̂ and
//           α/(p_s q);
//   box     (cross_from_inside) internal reflection with probability F(|d_a|) (depth counted), else escape with
//           weight w.
//
// Every operation is IEEE-exact (no contraction), so each width gives the same bits as the other and as the scalar
// walk where the scalar walk computes the same expression.

// Per-lane state, kept in memory between the phases of the wavefront loop (lanes are refilled one at a time).
struct alignas(64) Lanes {
  float p[3][kLanes], d[3][kLanes], tn[3][kLanes], td[3][kLanes];
  int32_t idx[3][kLanes], step[3][kLanes], vstep[3][kLanes], cv[kLanes];
  float tau[kLanes], acc[kLanes], t[kLanes], u1[kLanes], u2[kLanes], u3[kLanes], excess[kLanes];
  float w[kLanes], wref[kLanes], prod[kLanes];
  int32_t zeros[kLanes], event[kLanes], depth[kLanes], chan[kLanes], elem[kLanes], sample[kLanes], state[kLanes];
  int32_t nseg[kLanes], ncol[kLanes];  // RECORD: entries counted (at most the tape's room: cap + 1 is an overflow)
  int64_t item[kLanes], scatter[kLanes];
};
enum : int32_t { kIdle = 0, kNeedFlight = 1, kFlying = 2 };

template <bool DIEL, bool RATIO, bool RECORD>
void walks(const SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, const LaneTapes* tapes,
           int ended_lanes, WalkDone done, void* ctx) {
  static_assert(!RECORD || RATIO, "the recording walk carries ratio weights");
  const int64_t N = int64_t(S.D) * S.H * S.W;
  const int32_t HW = S.H * S.W;
  const float vs[3] = {S.voxel[0], S.voxel[1], S.voxel[2]};
  const int32_t dims[3] = {S.W, S.H, S.D};
  const bool plain_s = !(S.ref_sigma_t_floor > 0), plain_a = !(S.ref_albedo_floor > 0);
  // the reference is the medium itself (floored or not): the reference's (unfloored) gather serves both
  const bool same_sig = S.sigma_t == S.ref_sigma_t, same_alb = S.albedo == S.ref_albedo;
  const float r_entry = DIEL ? fresnel1(1.0f, 1.0f / S.ior) : 0.0f;

  Lanes L;
  memset(&L, 0, sizeof(L));
  const TapeSlots ts(RECORD ? tapes : nullptr);
  TapeSegmentF* const segs = ts.segs;
  TapeCollisionF* const cols = ts.cols;
  BatchOrder order(n, S.spp, live);  // the next path of the batch: order.next()
  const int64_t& k = order.k;
  const int64_t& s = order.s;
  const int& c = order.c;
  auto finish = [&](int l, float value, bool escaped, bool truncated) {
    WalkOut o;
    o.item = L.item[l];
    o.value[0] = value;
    o.prod_nonzero[0] = L.prod[l];
    o.zeros[0] = L.zeros[l];
    o.escaped = escaped;
    o.truncated = truncated;
    o.scatter_events = L.scatter[l];
    ts.report(l, L.nseg[l], L.ncol[l], o);
    done(ctx, o);
    L.state[l] = kIdle;
  };
  // Starts paths in idle lanes until they are all busy or the batch is empty (a path may end at its start).
  bool more = true;
  auto refill = [&](int l) {
    while (L.state[l] == kIdle && more) {
      more = order.next();
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
      L.nseg[l] = L.ncol[l] = 0;
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
  for (int l = 0; l < kLanes; ++l) refill(l);

  const I Wv = iset(S.W), HWv = iset(HW), Nv = iset(int32_t(N));
  const int32_t max_depth = int32_t(S.max_depth < 0x7fffffff ? S.max_depth : 0x7fffffff);
  const int32_t rr_depth = int32_t(S.rr_depth < 0x7fffffff ? S.rr_depth : 0x7fffffff);
  for (;;) {
    const I state = loadi(L.state);
    const M active = igt(state, iset(0));
    if (!bits(active)) break;
    F p[3], d[3], tn[3], td[3];
    I idx[3], step[3], vstep[3];
    for (int a = 0; a < 3; ++a) {
      p[a] = loadf(L.p[a]);
      d[a] = loadf(L.d[a]);
      tn[a] = loadf(L.tn[a]);
      td[a] = loadf(L.td[a]);
      idx[a] = loadi(L.idx[a]);
      step[a] = loadi(L.step[a]);
      vstep[a] = loadi(L.vstep[a]);
    }
    I cvox = loadi(L.cv);
    F tau = loadf(L.tau), acc = loadf(L.acc), t = loadf(L.t);
    F u1 = loadf(L.u1), u2 = loadf(L.u2), u3 = loadf(L.u3);
    F excess = loadf(L.excess);
    const I chan = loadi(L.chan);
    const I chN = imul(chan, Nv);

    // ---- lanes starting a free flight: one event, the optical depth and the DDA set-up
    const M nf = ieq(state, iset(kNeedFlight));
    if (bits(nf)) {
      const I ev = loadi(L.event);
      F u[4];
      draw(loadi(L.elem), loadi(L.sample), chan, ev, S.seed, u);
      storei(L.event, seli(nf, iadd(ev, iset(1)), ev));
      tau = sel(nf, neg(vlog(u[0])), tau);
      u1 = sel(nf, u[1], u1);
      u2 = sel(nf, u[2], u2);
      u3 = sel(nf, u[3], u3);
      acc = sel(nf, fzero(), acc);
      t = sel(nf, fzero(), t);
      excess = sel(nf, fzero(), excess);
      const F inf = fset(__builtin_inff());
      for (int a = 0; a < 3; ++a) {
        const M pos = gt(d[a], fzero()), negd = lt(d[a], fzero());
        const F v = fset(vs[a]);
        const F i0 = cvtif(idx[a]);
        const F inv = div(fset(1.0f), d[a]);  // one division per axis (the scalar walk divides thrice)
        const F tdp = mul(v, inv);
        const F tnp = tmax(fzero(), mul(sub(mul(add(i0, fset(1.0f)), v), p[a]), inv));
        const F tnn = tmax(fzero(), mul(sub(mul(i0, v), p[a]), inv));
        const F tdn = neg(tdp);
        const F tdx = sel(pos, tdp, sel(negd, tdn, inf));
        const F tnx = sel(pos, tnp, sel(negd, tnn, inf));
        const I stx = seli(pos, iset(1), seli(negd, iset(-1), iset(0)));
        td[a] = sel(nf, tdx, td[a]);
        tn[a] = sel(nf, tnx, tn[a]);
        step[a] = seli(nf, stx, step[a]);
        const int32_t stride = a == 0 ? 1 : (a == 1 ? S.W : HW);
        vstep[a] = seli(nf, seli(pos, iset(stride), seli(negd, iset(-stride), iset(0))), vstep[a]);
      }
      const I v0 = iadd(iadd(imul(idx[2], HWv), imul(idx[1], Wv)), idx[0]);
      cvox = seli(nf, iadd(chN, v0), cvox);
    }

    // ---- regular tracking: one voxel per iteration for every lane in flight, until enough flights have ended
    // (the collision and flight-start phases below cost the same for one lane or all, so they wait for several).
    // Every lane of the loop steps on to its next voxel whether its flight went on or not, so the next gather's
    // address never waits for this one's value and successive gathers overlap; a lane whose flight ended keeps the
    // voxel of its collision (hit_idx) or stays put at the box (leaving stops its steps), and the state it stepped
    // past (tn, cvox) is set afresh by its next flight.
    M collided = mnone(), out = mnone(), flying = active;
    F col_sref = fset(1.0f), col_sig = fzero();
    I col_v = iset(0), exit_axis = iset(-1);
    I idx_here[3], hit_idx[3] = {idx[0], idx[1], idx[2]};  // this iteration's voxel; the collision voxel
    F raw_next = gather_pair(S.ref_pair, 0, cvox, active);
    I nseg = RECORD ? loadi(L.nseg) : iset(0);
    do {
      const M m01 = lt(tn[0], tn[1]), m02 = lt(tn[0], tn[2]), m12 = lt(tn[1], tn[2]);
      const M is0 = mand(m01, m02), is1 = mandnot(m01, m12);
      const M is2 = mnot(mor(is0, is1));
      const F tend = sel(is0, tn[0], sel(is1, tn[1], tn[2]));
      const I cv = cvox;
      const I v = isub(cvox, chN);
      const F raw = raw_next;
      // the step to the next voxel first, and that voxel's gather, which then runs while this voxel is weighed
      M oob_on = mnone();  // lanes whose step would leave the box
      for (int a = 0; a < 3; ++a) {
        const M axis = a == 0 ? is0 : (a == 1 ? is1 : is2);
        const I moved = iadd(idx[a], step[a]);
        const M oob = mor(igt(iset(0), moved), igt(moved, iset(dims[a] - 1)));
        const M go = mandnot(oob, mand(active, axis));
        oob_on = mor(oob_on, mand(oob, axis));
        exit_axis = seli(mand(flying, mand(oob, axis)), iset(a), exit_axis);
        idx_here[a] = idx[a];
        idx[a] = seli(go, moved, idx[a]);
        cvox = seli(go, iadd(cvox, vstep[a]), cvox);
        tn[a] = sel(go, add(tn[a], td[a]), tn[a]);
      }
      raw_next = gather_pair(S.ref_pair, 0, cvox, active);
      const F seg = tmax(fzero(), sub(tend, t));
      const F sref = plain_s ? raw : tmax(raw, fset(S.ref_sigma_t_floor));
      const F od = mul(sref, seg);
      const M hit = mand(flying, ge(add(acc, od), tau));
      const F len = sel(hit, div(sub(tau, acc), sel(hit, sref, fset(1.0f))), seg);
      F sig = fzero();
      if (RATIO) {
        sig = same_sig ? raw : gather(S.sigma_t, cv, active);
        excess = sel(flying, add(excess, mul(sub(sig, sref), len)), excess);
      }
      if (RECORD) {  // a full tape's lane writes its spare slot and counts up to the room (then overflow)
        const M rec = mand(flying, gt(len, fzero()));
        store_pairs(segs, ts.seg_slot(nseg), v, asi(len), rec);
        nseg = ts.seg_count(nseg, rec);
      }
      col_sref = sel(hit, sref, col_sref);
      col_sig = sel(hit, sig, col_sig);
      col_v = seli(hit, v, col_v);
      for (int a = 0; a < 3; ++a) hit_idx[a] = seli(hit, idx_here[a], hit_idx[a]);
      // lanes that did not collide move on to the next voxel (done above) or leave the box
      const M moving = mandnot(hit, flying);
      acc = sel(moving, add(acc, od), acc);
      t = sel(hit, add(t, len), sel(moving, tend, t));
      const M left = mand(moving, oob_on);
      collided = mor(collided, hit);
      out = mor(out, left);
      flying = mandnot(mor(hit, left), flying);
    } while (bits(flying) && __builtin_popcount(unsigned(bits(mor(collided, out)))) < ended_lanes);
    if (RECORD) storei(L.nseg, nseg);
    for (int a = 0; a < 3; ++a) idx[a] = seli(collided, hit_idx[a], idx[a]);
    // lanes whose flight ended: move along it, apply the flight's transmittance ratio
    const M ended = mor(collided, out);
    F w = loadf(L.w), prod = loadf(L.prod);
    if (bits(ended)) {
      for (int a = 0; a < 3; ++a) p[a] = sel(ended, add(p[a], mul(d[a], t)), p[a]);
      if (RATIO) {
        const F f = vexp(neg(excess));
        w = sel(ended, mul(w, f), w);
        prod = sel(ended, mul(prod, f), prod);
      }
    }
    I depth = loadi(L.depth);
    const I newstate = seli(ended, iset(kNeedFlight), seli(active, iset(kFlying), iset(kIdle)));
    const I cv = iadd(chN, col_v);  // the collision voxel of lanes that collided
    int kill_trunc = 0, kill_absorb = 0, escape = 0;

    // ---- collisions
    if (bits(collided)) {
      for (int a = 0; a < 3; ++a) {
        const F i0 = cvtif(idx[a]), v_ = fset(vs[a]);
        const F lo = mul(i0, v_), hi = mul(add(i0, fset(1.0f)), v_);
        p[a] = sel(collided, tmin(hi, tmax(lo, p[a])), p[a]);
      }
      depth = seli(collided, iadd(depth, iset(1)), depth);
      const M trunc = mand(collided, igt(depth, iset(max_depth)));
      const M col = mandnot(trunc, collided);
      kill_trunc = bits(trunc);
      const F araw = gather_pair(S.ref_pair, 1, cv, col);
      const F aref = plain_a ? araw : tmax(araw, fset(S.ref_albedo_floor));
      const F ps = aref;
      F wref = loadf(L.wref);
      F q = fset(1.0f);
      const M rr = igt(depth, iset(rr_depth));
      if (bits(mand(rr, col))) q = sel(rr, tmin(fset(1.0f), div(mul(wref, aref), ps)), q);
      const F psq = mul(ps, q);
      const M survive = mand(col, lt(u1, psq));
      kill_absorb = bits(mandnot(survive, col));
      const F inv_psq = div(fset(1.0f), psq);
      wref = sel(survive, mul(wref, mul(aref, inv_psq)), wref);
      storef(L.wref, wref);
      if (RATIO) {
        const F alb = same_alb ? araw : gather(S.albedo, cv, survive);
        const F fa = mul(alb, inv_psq);
        const F fs = div(col_sig, col_sref);
        w = sel(survive, mul(w, mul(fs, fa)), w);
        const M zs = eq(fs, fzero()), za = eq(fa, fzero());
        prod = sel(survive, mul(mul(prod, sel(zs, fset(1.0f), fs)), sel(za, fset(1.0f), fa)), prod);
        I zeros = loadi(L.zeros);
        zeros = iadd1(zeros, mand(survive, zs));
        zeros = iadd1(zeros, mand(survive, za));
        storei(L.zeros, zeros);
        if (RECORD) {  // {v, seg_end}, {sref, inv_psq}, {fs, fa}
          const I ncol = loadi(L.ncol);
          const I s3 = ts.col_slot<3>(ncol);
          store_pairs(cols, s3, col_v, loadi(L.nseg), survive);
          store_pairs(cols, iadd(s3, iset(1)), asi(col_sref), asi(inv_psq), survive);
          store_pairs(cols, iadd(s3, iset(2)), asi(fs), asi(fa), survive);
          storei(L.ncol, ts.col_count(ncol, survive));
        }
      }
      {
        int m = bits(col);
        while (m) {
          const int l = __builtin_ctz(unsigned(m));
          m &= m - 1;
          ++L.scatter[l];
        }
      }
      if (bits(survive)) {
        F dn[3] = {d[0], d[1], d[2]};
        rotate(dn, hg_cos(S.g, u2), u3);
        for (int a = 0; a < 3; ++a) d[a] = sel(survive, dn[a], d[a]);
      }
    }

    // ---- lanes at the box: internal reflection or escape
    if (bits(out)) {
      F cos_i = fzero();
      for (int a = 0; a < 3; ++a) {
        const M on = mand(out, ieq(exit_axis, iset(a)));
        const F face = sel(gt(d[a], fzero()), fset(float(dims[a]) * vs[a]), fzero());
        p[a] = sel(on, face, p[a]);
        cos_i = sel(on, fabs_(d[a]), cos_i);
      }
      M refl = mnone();
      if (DIEL) refl = mand(out, lt(u1, fresnel(cos_i, S.ior)));
      if (bits(refl)) {
        depth = seli(refl, iadd(depth, iset(1)), depth);
        const M trunc = mand(refl, igt(depth, iset(max_depth)));
        kill_trunc |= bits(trunc);
        const M flip = mandnot(trunc, refl);
        for (int a = 0; a < 3; ++a) {
          const M on = mand(flip, ieq(exit_axis, iset(a)));
          d[a] = sel(on, neg(d[a]), d[a]);
        }
      }
      escape = bits(mandnot(refl, out));
    }

    // ---- back to memory
    for (int a = 0; a < 3; ++a) {
      storef(L.p[a], p[a]);
      storef(L.d[a], d[a]);
      storef(L.tn[a], tn[a]);
      storef(L.td[a], td[a]);
      storei(L.idx[a], idx[a]);
      storei(L.step[a], step[a]);
      storei(L.vstep[a], vstep[a]);
    }
    storei(L.cv, cvox);
    storef(L.tau, tau);
    storef(L.acc, acc);
    storef(L.t, t);
    storef(L.u1, u1);
    storef(L.u2, u2);
    storef(L.u3, u3);
    storef(L.excess, excess);
    storef(L.w, w);
    storef(L.prod, prod);
    storei(L.depth, depth);
    storei(L.state, newstate);

    // ---- paths that ended: report, then start new ones in their lanes
    const int ended_paths = kill_trunc | kill_absorb | escape;
    if (ended_paths) {
      int m = ended_paths;
      while (m) {
        const int l = __builtin_ctz(unsigned(m));
        m &= m - 1;
        if ((kill_trunc >> l) & 1) finish(l, 0.0f, false, true);
        else if ((kill_absorb >> l) & 1) finish(l, 0.0f, false, false);
        else finish(l, RATIO ? L.w[l] : 1.0f, true, false);
      }
      m = ended_paths;
      while (m) {
        const int l = __builtin_ctz(unsigned(m));
        m &= m - 1;
        refill(l);
      }
    }
  }
}

// The entry point's body: the template instance for the scene's flags.
inline void walks_dispatch(const SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                           const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx) {
  if (ended_lanes < 1 || ended_lanes > kLanes) ended_lanes = kLanes * 3 / 4;
  if (tapes && !(tapes->seg_cap >= 0 && tapes->seg_cap <= kMaxTapeCap && tapes->col_cap >= 0 &&
                 tapes->col_cap <= kMaxTapeCap))
    __builtin_trap();  // (the caller checks first: see simd_glue.cpp)
  if (S.dielectric) {
    if (tapes) walks<true, true, true>(S, elems, live, n, tapes, ended_lanes, done, ctx);
    else if (ratio) walks<true, true, false>(S, elems, live, n, nullptr, ended_lanes, done, ctx);
    else walks<true, false, false>(S, elems, live, n, nullptr, ended_lanes, done, ctx);
  } else {
    if (tapes) walks<false, true, true>(S, elems, live, n, tapes, ended_lanes, done, ctx);
    else if (ratio) walks<false, true, false>(S, elems, live, n, nullptr, ended_lanes, done, ctx);
    else walks<false, false, false>(S, elems, live, n, nullptr, ended_lanes, done, ctx);
  }
}
