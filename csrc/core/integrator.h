// The random walk: one estimator written once and specialised by template parameters for what runs per step, so
// a scene pays only for what it uses; sensor and emitter are looked up once per path.
//
//   LANES       1: one walk per colour channel (chromatic sampling density);
//               3: one walk serves all three channels (achromatic sampling density).
//   BOUNDARY    kBoxBoundary (the grid box) or kSDFBoundary (zero set of the trilinear corner SDF, boundary.h).
//   DIELECTRIC  smooth dielectric boundary (Fresnel, Snell, TIR) or index matched (no boundary optics at all).
//   RATIO       the walk is sampled from a reference medium that may differ from the parameters and carries the
//               ratio weights f(θ)/p_ref. Off for the default forward pass (reference = parameters).
//   ADJOINT     path replay of radiative backpropagation: deposit ∂/∂θ of the path contribution.
//   HERO        (LANES == 3, chromatic reference) hero-channel spectral MIS: one walk serves all three channels; it
//               samples free flights with the reference density σ̂_h of a hero channel h (uniform per sample:
//               h = (o + sample) mod 3 with a random offset o per sensor element) and weights each channel with
//               the one-sample balance heuristic over the channels (Wilkie et al. 2014; Miller et al. 2019):
//                 V_c(x) = f_c(x) / ((1/3) Σ_k p_k(x)),
//               p_k the pdf of the whole path x had it been sampled with channel k's reference density. The
//               continuation probability p_s = max_c α̂_c and the roulette q do not depend on the hero, so p_k/p_h
//               is the product of the free-flight ratios exp(−∫(σ̂_k − σ̂_h)) and, per collision, σ̂_k/σ̂_h. The
//               walk keeps log(p_k/p_h) and the log of the product of f_c/p_h's non-zero factors, so stiff media
//               (σ̂ differing by 10⁴ between channels, optical depths of 10⁴) neither overflow nor underflow; the
//               weight is combined by log-sum-exp when the path escapes. The MIS weight depends on the detached
//               reference only, so ∂V_c/∂θ is the non-hero formula below with V_c including the weight and σ̂ the
//               hero's.
//
// Estimator (per channel c, for one path x sampled from the reference medium σ̂, α̂):
//   V_c(x) = L_e,c(ω_escape) · Π_flights exp(−Σ_voxels (σ_c − σ̂)·ℓ) · Π_collisions (σ_c/σ̂) · (α_c / (p_s·q))
// where p_s is the probability of continuing at a collision (α̂_c for one lane, max_c α̂_c for three lanes) and q
// the Russian-roulette survival probability computed from the reference throughput only (so V is smooth in θ for
// a fixed reference and seed). Boundary events (Fresnel reflection or refraction, chosen with probability F and
// 1 − F) carry weight 1. Absorbed, roulette-killed and depth-truncated paths contribute 0. The walk returns
// V_c / L_e,c and the escape direction; the caller evaluates the emitter.
// Its derivative is deposited by path replay:
//   ∂V_c/∂σ_c(v) = V_c·(−ℓ_v) for every flight segment in v   +   V_c^{¬σ-factor}/σ̂(v) for a collision in v
//   ∂V_c/∂α_c(v) = V_c^{¬α-factor}/(p_s·q)                     for a scattering collision in v
// where V^{¬f} (V without factor f) is evaluated zero-safely (σ_c = 0 or α_c = 0 factors give exact derivatives).
// Both need the final V: the walk either records the events in a tape and deposits after it ends (RECORD, one walk,
// tape.h) or is replayed twice, first for V, then depositing (ADJOINT; the fallback for paths longer than a tape).
//
// Random numbers (stream `channel` of rng.h: the walk's channel, 3 for a shared walk, 4 for a hero walk, whose hero
// offset is drawn from stream 5): event 0 places the start (u0, u1) and decides the first Fresnel event (u2); each free flight
// draws one event (u0 distance, u1 absorption or Fresnel at the end of the flight, u2 u3 the new direction); a
// surface hit from outside after the first draws one more event (u0 Fresnel).
#pragma once

#include "core/boundary.h"
#include "core/defs.h"
#include "core/emitter.h"
#include "core/medium.h"
#include "core/optics.h"
#include "core/rng.h"
#include "core/sensor.h"
#include "core/tape.h"

namespace ta {
namespace core {

template <typename T>
struct Scene {
  Medium<T> medium;
  SDFGrid<T> sdf;       // kSDFBoundary only
  Sensor<T> sensor;
  Emitter<T> emitter;
  T g = 0;              // Henyey–Greenstein parameter, |g| < 1
  T ior = 1;            // DIELECTRIC only
  int64_t spp = 1;
  uint64_t seed = 0;
  int64_t max_depth = 1;  // interactions (scatterings + internal reflections; SDF: also crossings) before a cut
  int64_t rr_depth = 1;   // interactions before Russian roulette starts

  // Number of sensor elements (texels or pixels).
  int64_t elements() const {
    switch (sensor.kind) {
      case kFaceTexels: return (sensor.face == kFaceBoth ? 2 : 1) * medium.H * medium.W;
      case kSurfaceTexels: return sensor.count;
      default: return sensor.rows * sensor.cols;
    }
  }
};

// What a walk leaves behind, per lane: V = 0 unless escaped; prod_nonzero and zeros make V^{¬f} zero-safe.
template <typename T, int LANES>
struct PathResult {
  bool escaped = false;
  bool truncated = false;  // cut by max_depth (a bias the caller reports)
  T value[LANES];          // V_c / L_e,c  (the path weight; 0 if not escaped)
  T prod_nonzero[LANES];   // product of all non-zero factors
  int zeros[LANES];        // number of exactly-zero factors (σ_c = 0 or α_c = 0 at a collision)
  T direction[3];          // escape direction (world), where the emitter is evaluated
  int64_t scatter_events = 0;
};

// Entry of a ray from outside the object (grid-local p, unit d): moves p to the first surface point, sets the
// cell idx there and the outward unit normal n. False when the ray leaves without hitting the object.
template <typename T, int BOUNDARY>
TA_HD inline bool find_entry(const Scene<T>& S, T p[3], const T d[3], int64_t idx[3], T n[3]) {
  const Medium<T>& M = S.medium;
  // clip to the grid box
  T tin = 0, tout = tinf<T>();
  int axis = -1;
  for (int a = 0; a < 3; ++a) {
    const T ext = M.extent(a);
    if (d[a] == T(0)) {
      if (p[a] < T(0) || p[a] > ext) return false;
      continue;
    }
    T t0 = (T(0) - p[a]) / d[a], t1 = (ext - p[a]) / d[a];
    if (t1 < t0) {
      const T tmp = t0;
      t0 = t1;
      t1 = tmp;
    }
    if (t0 > tin) {
      tin = t0;
      axis = a;
    }
    tout = tmin(tout, t1);
  }
  if (!(tin <= tout) || !(tout > T(0))) return false;
  if (axis >= 0) {  // enters the grid box from outside; otherwise p is in the box and idx its cell already
    for (int k = 0; k < 3; ++k) p[k] += d[k] * tin;
    p[axis] = d[axis] > T(0) ? T(0) : M.extent(axis);
    for (int k = 0; k < 3; ++k) p[k] = tmin(M.extent(k), tmax(T(0), p[k]));
    M.locate(p, idx);
  }
  if (BOUNDARY == kBoxBoundary) {
    if (axis < 0) return false;  // in the box but outside the object: only through rounding; leaves
    idx[axis] = d[axis] > T(0) ? 0 : M.dim(axis) - 1;
    for (int k = 0; k < 3; ++k) n[k] = T(0);
    n[axis] = d[axis] > T(0) ? T(-1) : T(1);
    return true;
  } else {
    // DDA through the cells, looking for f <= 0 in cells that may hold surface
    T tnext[3], tdelta[3];
    int64_t step[3];
    for (int a = 0; a < 3; ++a) {
      if (d[a] > T(0)) {
        step[a] = 1;
        tdelta[a] = M.voxel[a] / d[a];
        tnext[a] = tmax(T(0), (T(idx[a] + 1) * M.voxel[a] - p[a]) / d[a]);
      } else if (d[a] < T(0)) {
        step[a] = -1;
        tdelta[a] = -M.voxel[a] / d[a];
        tnext[a] = tmax(T(0), (T(idx[a]) * M.voxel[a] - p[a]) / d[a]);
      } else {
        step[a] = 0;
        tdelta[a] = tnext[a] = tinf<T>();
      }
    }
    T t = 0;
    for (;;) {
      const int a = tnext[0] < tnext[1] ? (tnext[0] < tnext[2] ? 0 : 2) : (tnext[1] < tnext[2] ? 1 : 2);
      if (S.sdf.cell[M.index(idx)] != kCellOutside) {
        T th;
        if (S.sdf.crossing(M, idx, p, d, t, tnext[a], T(-1), &th)) {
          for (int k = 0; k < 3; ++k) p[k] += d[k] * th;
          S.sdf.normal(M, idx, p, d, n);
          return true;
        }
      }
      t = tnext[a];
      idx[a] += step[a];
      if (idx[a] < 0 || idx[a] >= M.dim(a)) return false;
      tnext[a] += tdelta[a];
    }
  }
}

// Whether a grid-local start point is inside the object; sets idx to its (clamped) cell.
template <typename T, int BOUNDARY>
TA_HD inline bool start_inside(const Scene<T>& S, const T p[3], int64_t idx[3]) {
  const Medium<T>& M = S.medium;
  M.locate(p, idx);  // always set (clamped), also for points outside the grid
  for (int a = 0; a < 3; ++a)
    if (!(p[a] > T(0) && p[a] < M.extent(a))) return false;
  if (BOUNDARY == kBoxBoundary) return true;
  T grad[3];
  return S.sdf.value_gradient(M, idx, p, grad) < T(0);
}

// The hero channel of sample `sample` of sensor element `elem`: uniform over the three channels for every sample
// (a random offset per element, then rotating over the samples, so the channels are stratified).
template <typename T>
TA_HD inline int hero_channel(uint64_t seed, int64_t elem, int64_t sample) {
  const PathRng<T> r{seed, uint32_t(elem), 0u, 5u};
  T u[4];
  r.draw(0, u);
  const int offset = tmin(2, int(u[0] * T(3)));
  return int((uint64_t(offset) + uint64_t(sample) % 3u) % 3u);
}

// log(a / b) for a >= 0, b > 0 (−inf for a = 0), also where a / b leaves the floating-point range.
template <typename T>
TA_HD inline T log_ratio(T a, T b) {
  const T r = a / b;
  return (r > T(0) && r < tinf<T>()) || a == T(0) ? tlog(r) : tlog(a) - tlog(b);
}

// Escape of a hero walk: V_c = exp(lw_c − log((1/3) Σ_k exp(lrho_k))) (0 for a path with a zero factor), and the
// same for the product of the non-zero factors. lrho_h = 0, so the log-sum-exp's maximum is >= 0.
template <typename T>
TA_HD inline void hero_escape(PathResult<T, 3>& res, const T lw[3], const T lrho[3], const T d[3]) {
  const T m = tmax(lrho[0], tmax(lrho[1], lrho[2]));
  const T lse = m + tlog((texp(lrho[0] - m) + texp(lrho[1] - m) + texp(lrho[2] - m)) * T(1.0 / 3.0));
  res.escaped = true;
  for (int l = 0; l < 3; ++l) {
    res.prod_nonzero[l] = texp(lw[l] - lse);
    res.value[l] = res.zeros[l] == 0 ? res.prod_nonzero[l] : T(0);
  }
  for (int k = 0; k < 3; ++k) res.direction[k] = d[k];
}

template <typename T, int LANES>
TA_HD inline void escape(PathResult<T, LANES>& res, const T w[LANES], const T d[3]) {
  res.escaped = true;
  for (int l = 0; l < LANES; ++l) res.value[l] = w[l];
  for (int k = 0; k < 3; ++k) res.direction[k] = d[k];
}

// One random walk of the path that starts at sensor element `elem`, sample `sample`.
// `chan` is the channel for LANES == 1 (lanes map to channels 0..2 for LANES == 3).
// With ADJOINT, `pass1` holds this path's result from a non-adjoint replay and `adj[l]` = grad_out·L_e/spp.
// With RECORD, the walk writes what its derivative needs into `tape` (for the gradient buffers named in A; see
// tape.h) and the caller deposits after the walk: one walk instead of two.
template <typename T, int LANES, int BOUNDARY, bool DIELECTRIC, bool RATIO, bool ADJOINT, bool RECORD = false,
          bool HERO = false>
TA_HD inline PathResult<T, LANES> trace_path(const Scene<T>& S, int64_t elem, int64_t sample, int chan,
                                             const PathResult<T, LANES>* pass1, const T* adj, const Adjoint<T>& A,
                                             Tape<T, LANES>* tape = nullptr) {
  static_assert(!ADJOINT || RATIO, "the adjoint replay always carries ratio weights");
  static_assert(!RECORD || (RATIO && !ADJOINT), "the recording walk carries ratio weights and deposits nothing");
  static_assert(!HERO || LANES == 3, "a hero walk serves all three channels");
  constexpr bool SDF = BOUNDARY == kSDFBoundary;
  PathResult<T, LANES> res;
  for (int l = 0; l < LANES; ++l) {
    res.value[l] = T(0);
    res.prod_nonzero[l] = T(1);
    res.zeros[l] = 0;
  }
  for (int k = 0; k < 3; ++k) res.direction[k] = T(0);
  const Medium<T>& M = S.medium;
  const int64_t N = M.voxels();
  const T* vs = M.voxel;
  // the channel whose reference density drives the walk
  const int ch0 = HERO ? hero_channel<T>(S.seed, elem, sample) : (LANES == 1 ? chan : 0);
  const int64_t dims[3] = {M.W, M.H, M.D};

  const PathRng<T> rng{S.seed, uint32_t(elem), uint32_t(sample), uint32_t(HERO ? 4 : (LANES == 1 ? chan : 3))};
  uint32_t event = 0;
  T u[4];
  rng.draw(event++, u);

  T w[LANES], wref[LANES];  // path weight (with zero factors) and reference-only weight (for roulette)
  for (int l = 0; l < LANES; ++l) w[l] = wref[l] = T(1);
  // HERO: lrho[k] = log(p_k/p_h) of the path so far, lw[c] = log of the product of f_c/p_h's non-zero factors
  T lrho[3] = {0, 0, 0}, lw[LANES];
  for (int l = 0; l < LANES; ++l) lw[l] = T(0);
  // HERO: the last argument and value of each of the collision's logarithms (slots 0..2: σ̂_k/σ̂_h, 3..5: the
  // lanes' f_c/p_h factors); a walk through voxels of equal values (a homogeneous ink) takes no logarithm again
  T memo_arg[6], memo_log[6];
  for (int i = 0; i < 6; ++i) memo_arg[i] = memo_log[i] = T(0);
  auto log_memo = [&](int slot, T x) {  // log x for a finite x > 0
    if (x != memo_arg[slot]) {
      memo_arg[slot] = x;
      memo_log[slot] = tlog(x);
    }
    return memo_log[slot];
  };
  auto log_ratio_memo = [&](int slot, T a, T b) {  // log(a / b), a >= 0, b > 0 (see log_ratio)
    const T r = a / b;
    return r > T(0) && r < tinf<T>() ? log_memo(slot, r) : log_ratio(a, b);
  };
  auto finish = [&](const T dir[3]) {
    if constexpr (HERO) hero_escape(res, lw, lrho, dir);
    else escape(res, w, dir);
  };
  T p[3], d[3];  // grid-local position (mm) and unit direction
  int64_t idx[3];
  bool inside;
  T u_fresnel = u[2];  // the uniform of the next Fresnel event from outside (the first one comes with the start)
  bool fresh = true;

  if (S.sensor.kind == kFaceTexels) {
    // Start on the face, inside the texel's footprint, pointing along the inward normal.
    const int64_t HW = M.H * M.W;
    const int face = S.sensor.face == kFaceBoth ? int(elem / HW) : S.sensor.face;
    const int64_t ti = elem % HW;
    const int64_t tj = ti / M.W, tx = ti % M.W;
    p[0] = (T(tx) + u[0]) * vs[0];
    p[1] = (T(tj) + u[1]) * vs[1];
    p[2] = face == kFaceTop ? T(M.D) * vs[2] : T(0);
    d[0] = d[1] = T(0);
    d[2] = face == kFaceTop ? T(-1) : T(1);
    idx[0] = tx;
    idx[1] = tj;
    idx[2] = face == kFaceTop ? M.D - 1 : 0;
    inside = true;
    if (DIELECTRIC) {  // specular reflection of the emitter at the entry face (normal incidence)
      const T r = fresnel_dielectric(T(1), T(1) / S.ior);
      if (u[2] < r) {
        const T back[3] = {0, 0, -d[2]};
        finish(back);
        return res;
      }
    }
  } else {
    T o[3];
    S.sensor.generate(elem, u, o, d);
    for (int k = 0; k < 3; ++k) p[k] = o[k] - M.origin[k];
    inside = start_inside<T, BOUNDARY>(S, p, idx);
  }

  int64_t depth = 0;
  for (;;) {
    if (!inside) {
      // ---- outside the object: fly to the next surface point or escape
      T n[3];
      if (!find_entry<T, BOUNDARY>(S, p, d, idx, n)) {
        finish(d);
        return res;
      }
      if (!fresh) {
        rng.draw(event++, u);
        u_fresnel = u[0];
      }
      fresh = false;
      if (SDF && ++depth > S.max_depth) {
        res.truncated = true;
        return res;
      }
      if (DIELECTRIC) {
        const T cos_i = tmin(T(1), -dot3(d, n));
        const T eta = T(1) / S.ior;
        if (u_fresnel < fresnel_dielectric(cos_i, eta)) {
          reflect(d, n, cos_i);
          if (!SDF) {  // a convex box: the reflected ray leaves
            finish(d);
            return res;
          }
          continue;
        }
        refract(d, n, cos_i, eta);
      }
      inside = true;
      continue;
    }

    // ---- inside: one free flight in the reference medium
    rng.draw(event++, u);
    const T tau = -tlog(u[0]);  // optical depth to the next collision, in the reference medium

    // exact regular tracking through the voxels (DDA), analytic transmittance per voxel
    T tnext[3], tdelta[3];
    int64_t step[3];
    for (int a = 0; a < 3; ++a) {
      if (d[a] > T(0)) {
        step[a] = 1;
        tdelta[a] = vs[a] / d[a];
        tnext[a] = tmax(T(0), (T(idx[a] + 1) * vs[a] - p[a]) / d[a]);
      } else if (d[a] < T(0)) {
        step[a] = -1;
        tdelta[a] = -vs[a] / d[a];
        tnext[a] = tmax(T(0), (T(idx[a]) * vs[a] - p[a]) / d[a]);
      } else {
        step[a] = 0;
        tdelta[a] = tinf<T>();
        tnext[a] = tinf<T>();
      }
    }
    T t = 0, acc = 0;
    T excess[LANES];  // Σ (σ_c − σ̂)·ℓ over the flight, for the transmittance ratio
    for (int l = 0; l < LANES; ++l) excess[l] = T(0);
    T ref_excess[3] = {0, 0, 0};  // HERO: Σ (σ̂_k − σ̂_h)·ℓ over the flight
    bool collided = false, surface = false;
    int exit_axis = -1;
    int64_t v = 0;
    for (;;) {
      v = (idx[2] * M.H + idx[1]) * M.W + idx[0];
      const int a = tnext[0] < tnext[1] ? (tnext[0] < tnext[2] ? 0 : 2) : (tnext[1] < tnext[2] ? 1 : 2);
      T tend = tnext[a];
      bool hit_here = false;
      if (SDF && S.sdf.cell[v] != kCellInside) {
        T th;
        if (S.sdf.crossing(M, idx, p, d, t, tend, T(1), &th)) {
          tend = th;
          hit_here = true;
        }
      }
      const T seg = tmax(T(0), tend - t);
      const T sref = M.ref_sigma_t[ch0 * N + v];  // reference density, mm⁻¹ (t is in mm)
      const T od = sref * seg;
      T len = seg;
      if (acc + od >= tau) {  // collision inside this voxel
        len = (tau - acc) / sref;
        collided = true;
      }
      if (RATIO) {
        for (int l = 0; l < LANES; ++l) {
          const int c = LANES == 1 ? chan : l;
          excess[l] += (M.sigma_t[c * N + v] - M.ref_sigma_t[ch0 * N + v]) * len;
        }
      }
      if (HERO) {
        for (int k = 0; k < 3; ++k) ref_excess[k] += (M.ref_sigma_t[k * N + v] - sref) * len;
      }
      if (RECORD && A.grad_sigma_t && len > T(0)) tape->segment(v, len);
      if (ADJOINT && A.grad_sigma_t && len > T(0)) {
        for (int l = 0; l < LANES; ++l) {
          const int c = LANES == 1 ? chan : l;
          A.grad_sigma_t[c * N + v] -= adj[l] * pass1->value[l] * len;
        }
      }
      if (collided) {
        t += len;
        break;
      }
      acc += od;
      if (hit_here) {
        t = tend;
        surface = true;
        break;
      }
      t = tnext[a];
      idx[a] += step[a];
      if (idx[a] < 0 || idx[a] >= dims[a]) {
        idx[a] -= step[a];
        exit_axis = a;
        break;
      }
      tnext[a] += tdelta[a];
    }
    for (int k = 0; k < 3; ++k) p[k] += d[k] * t;
    if constexpr (HERO) {
      for (int k = 0; k < 3; ++k) lrho[k] -= ref_excess[k];
      for (int l = 0; l < LANES; ++l) lw[l] -= RATIO ? excess[l] : ref_excess[l];  // f_c/p_h of the flight
    } else if (RATIO) {
      for (int l = 0; l < LANES; ++l) {
        const T f = texp(-excess[l]);
        w[l] *= f;
        res.prod_nonzero[l] *= f;
      }
    }

    if (collided) {
      // keep the point inside the voxel the DDA found (no drift into a neighbour through rounding)
      for (int k = 0; k < 3; ++k) p[k] = tmin(T(idx[k] + 1) * vs[k], tmax(T(idx[k]) * vs[k], p[k]));
      if (++depth > S.max_depth) {  // truncated: contributes 0
        res.truncated = true;
        return res;
      }
      ++res.scatter_events;
      // continuation probability: reference albedo (max over lanes), times roulette on the reference weight
      T ps, aref[LANES];
      if (LANES == 1) {
        aref[0] = M.ref_albedo[chan * N + v];
        ps = aref[0];
      } else {
        ps = 0;
        for (int l = 0; l < LANES; ++l) {
          aref[l] = M.ref_albedo[l * N + v];
          ps = tmax(ps, aref[l]);
        }
      }
      T q = T(1);
      if (depth > S.rr_depth) {
        T m = 0;
        for (int l = 0; l < LANES; ++l) m = tmax(m, wref[l] * aref[l] / ps);
        q = tmin(T(1), m);
      }
      if (!(u[1] < ps * q)) return res;  // absorbed or killed by roulette: contributes 0
      const T inv_psq = T(1) / (ps * q);
      if constexpr (HERO) {  // the collision density ratios σ̂_k/σ̂_h of the path pdfs
        const T sh = M.ref_sigma_t[ch0 * N + v];
        for (int k = 0; k < 3; ++k)
          if (k != ch0) lrho[k] += log_ratio_memo(k, M.ref_sigma_t[k * N + v], sh);  // −inf for σ̂_k = 0
      }
      TapeCollision<T, LANES>* rec = nullptr;
      if (RECORD) {
        rec = tape->collision(v);
        if (rec) {
          rec->sref = M.ref_sigma_t[ch0 * N + v];
          rec->inv_psq = inv_psq;
        }
      }
      for (int l = 0; l < LANES; ++l) {
        const int c = LANES == 1 ? chan : l;
        wref[l] *= aref[l] * inv_psq;
        const T fa = M.albedo[c * N + v] * inv_psq;  // albedo factor α_c/(p_s q)
        T fs = T(1);                                 // collision factor σ_c/σ̂
        if (RATIO) fs = M.sigma_t[c * N + v] / M.ref_sigma_t[ch0 * N + v];
        else if (HERO) fs = M.ref_sigma_t[c * N + v] / M.ref_sigma_t[ch0 * N + v];
        if (RECORD && rec) {
          rec->fs[l] = fs;
          rec->fa[l] = fa;
        }
        if (ADJOINT) {
          if (A.grad_sigma_t)
            A.grad_sigma_t[c * N + v] += adj[l] *
                weight_without(fs, pass1->value[l], pass1->prod_nonzero[l], pass1->zeros[l]) /
                M.ref_sigma_t[ch0 * N + v];
          if (A.grad_albedo)
            A.grad_albedo[c * N + v] += adj[l] *
                weight_without(fa, pass1->value[l], pass1->prod_nonzero[l], pass1->zeros[l]) * inv_psq;
        }
        if constexpr (HERO) {
          if (fs == T(0)) ++res.zeros[l];
          if (fa == T(0)) ++res.zeros[l];
          if (fs != T(0) && fa != T(0)) {
            const T f = fs * fa;  // one logarithm unless the product leaves the normal range
            lw[l] += (f > T(0) && f < tinf<T>()) ? log_memo(3 + l, f) : tlog(fs) + tlog(fa);
          }
        } else if (RATIO || LANES > 1) {
          w[l] *= fs * fa;
          if (fs == T(0)) ++res.zeros[l]; else res.prod_nonzero[l] *= fs;
          if (fa == T(0)) ++res.zeros[l]; else res.prod_nonzero[l] *= fa;
        }
      }
      rotate_direction(d, sample_hg_cos(S.g, u[2]), u[3]);
      continue;
    }

    // ---- reached the surface (SDF crossing) or the grid box (axis exit_axis)
    T n[3] = {0, 0, 0};  // outward unit normal
    if (surface) {
      S.sdf.normal(M, idx, p, d, n);
    } else {
      p[exit_axis] = d[exit_axis] > T(0) ? T(dims[exit_axis]) * vs[exit_axis] : T(0);
      n[exit_axis] = d[exit_axis] > T(0) ? T(1) : T(-1);
    }
    if (DIELECTRIC) {
      const T cos_i = surface ? tmin(T(1), tmax(T(0), dot3(d, n))) : tabs(d[exit_axis]);
      if (u[1] < fresnel_dielectric(cos_i, S.ior)) {  // internal reflection (total when F == 1)
        if (++depth > S.max_depth) {
          res.truncated = true;
          return res;
        }
        if (surface) {
          const T n_inc[3] = {-n[0], -n[1], -n[2]};
          reflect(d, n_inc, cos_i);
        } else {
          d[exit_axis] = -d[exit_axis];
        }
        continue;
      }
      if (SDF || S.emitter.kind != kConstant) {  // the escape direction matters: refract
        const T n_inc[3] = {-n[0], -n[1], -n[2]};
        refract(d, n_inc, cos_i, S.ior);
      }
    }
    if (!SDF || !surface) {  // left the box (convex) or, for an SDF, the grid: escaped
      finish(d);
      return res;
    }
    if (++depth > S.max_depth) {
      res.truncated = true;
      return res;
    }
    inside = false;
  }
}

}  // namespace core
}  // namespace ta
