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
//   RECORD      the walk records what its derivative needs in a tape (tape.h); the caller deposits after it ends.
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
//   Deposit     how a gradient deposit is added (adjoint.h): a plain add on the CPU, an atomic add on a GPU.
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
// The walk is a sequence of steps on one PathState, each a function templated as trace_path is, so that a vector
// walk can take the same steps lane by lane:
//   start_at_sensor     the start at the sensor element (face texels: Sensor::generate_on_face, else
//                       Sensor::generate), and the first Fresnel event of a face texel;
//   fly                 one free flight inside the object through the voxels (VoxelDDA, dda.h) to a collision, the
//                       surface or the grid's box, with the flight's weights and ∂/∂σ_t segments;
//   collide             the collision: roulette, the collision's factors (and their ∂), the new direction;
//   cross_from_inside   the boundary reached from inside: internal reflection, or refraction out of the object;
//   enter_from_outside  outside the object: the flight to the next surface point and its Fresnel event, or escape.
//
// Random numbers (stream `channel` of rng.h: the walk's channel, 3 for a shared walk, 4 for a hero walk, whose hero
// offset is drawn from stream 5): event 0 places the start (u0, u1) and decides the first Fresnel event (u2); each free flight
// draws one event (u0 distance, u1 absorption or Fresnel at the end of the flight, u2 u3 the new direction); a
// surface hit from outside after the first draws one more event (u0 Fresnel).
#pragma once

#include "core/adjoint.h"
#include "core/boundary.h"
#include "core/dda.h"
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
  // Diagnostics, off unless set (the glue's tally, one buffer per thread): per voxel a bin (D, H, W), and per bin
  // the scattering events and the flights' voxel moves (a core box crossed in one move counts once, in the bin of
  // the voxel where it starts), counted into tally[2·bin] and tally[2·bin + 1].
  const uint8_t* tally_bin = nullptr;
  int64_t* tally = nullptr;
  int64_t max_depth = 1;  // interactions (scatterings + internal reflections; SDF: also crossings) before a cut
  int64_t rr_depth = 1;   // interactions before Russian roulette starts

  // Number of sensor elements (texels or pixels).
  TA_HD int64_t elements() const {
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
  int64_t voxel_steps = 0;    // voxels visited by the free flights inside the object
  int64_t outside_steps = 0;  // cells visited outside it, looking for the surface (find_entry)
  int64_t core_events = 0;    // scattering events in the homogeneous core (Medium::core)
};

// Entry of a ray from outside the object (grid-local p, unit d): moves p to the first surface point, sets the
// cell idx there and the outward unit normal n. False when the ray leaves without hitting the object. `steps`
// counts the cells visited.
template <typename T, int BOUNDARY>
TA_HD TA_INLINE bool find_entry(const Scene<T>& S, T p[3], const T d[3], int64_t idx[3], T n[3], int64_t& steps) {
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
    // through the cells with the DDA, looking for f <= 0 in cells that may hold surface
    VoxelDDA<T> dda(M, p, d, idx);
    // copies for the out-of-line root search and normal: no address of the DDA or of the caller's path state may
    // escape into them, or GCC keeps that whole state in memory (measured 5-15 % slower on SDF scenes)
    const T pc[3] = {p[0], p[1], p[2]}, dc[3] = {d[0], d[1], d[2]};
    for (;;) {
      ++steps;
      if (const int k = S.sdf.skip_distance(dda.idx); k > 0) {
        // every cell within k − 1 bricks of this one is outside: leave that box in one move
        if (!dda.leave(dda.brick_box(M, pc, dc, k), M, pc, dc)) return false;  // left the grid: nothing hit
        continue;
      }
      if (S.sdf.cell[dda.voxel()] != kCellOutside) {
        const int64_t cell[3] = {dda.idx[0], dda.idx[1], dda.idx[2]};
        T th;
        if (S.sdf.crossing(M, cell, pc, dc, dda.t0, dda.t1, T(-1), &th)) {
          T ph[3], nh[3];
          for (int k = 0; k < 3; ++k) ph[k] = pc[k] + dc[k] * th;
          S.sdf.normal(M, cell, ph, dc, nh);
          for (int k = 0; k < 3; ++k) {
            idx[k] = cell[k];
            p[k] = ph[k];
            n[k] = nh[k];
          }
          return true;
        }
      }
      if (!dda.next()) return false;
    }
  }
}

// Whether a grid-local start point is inside the object; sets idx to its (clamped) cell.
template <typename T, int BOUNDARY>
TA_HD TA_INLINE bool start_inside(const Scene<T>& S, const T p[3], int64_t idx[3]) {
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
TA_HD TA_INLINE void hero_escape(PathResult<T, 3>& res, const T lw[3], const T lrho[3], const T d[3]) {
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
TA_HD TA_INLINE void escape(PathResult<T, LANES>& res, const T w[LANES], const T d[3]) {
  res.escaped = true;
  for (int l = 0; l < LANES; ++l) res.value[l] = w[l];
  for (int k = 0; k < 3; ++k) res.direction[k] = d[k];
}

// The state of one walk, which the steps take by reference.
template <typename T, int LANES>
struct PathState {
  T p[3], d[3];         // grid-local position (mm) and unit direction
  int64_t idx[3];       // the voxel (cell) of p
  int64_t v = 0;        // flat index of the voxel where the last flight ended (a collision's voxel)
  bool inside = false;  // inside the object
  int ch0 = 0;          // the channel whose reference density drives the walk (the hero of a hero walk)
  int64_t depth = 0;    // interactions so far (scatterings, internal reflections; SDF: also crossings)
  PathRng<T> rng;       // the path's random numbers, and the number of its next event
  uint32_t event = 0;
  T u[4];               // the uniforms of the current event
  T u_fresnel;          // the uniform of the next Fresnel event from outside (the first one comes with the start)
  bool fresh = true;    // no surface hit from outside yet
  T w[LANES], wref[LANES];  // path weight (with zero factors) and reference-only weight (for roulette)
  // HERO: lrho[k] = log(p_k/p_h) of the path so far, lw[c] = log of the product of f_c/p_h's non-zero factors
  T lrho[3], lw[LANES];
  // HERO: the last argument and value of each of the collision's logarithms (slots 0..2: σ̂_k/σ̂_h, 3..5: the
  // lanes' f_c/p_h factors); a walk through voxels of equal values (a homogeneous ink) takes no logarithm again
  T memo_arg[6], memo_log[6];

  // log x for a finite x > 0, remembered in `slot`
  TA_HD TA_INLINE T log_memo(int slot, T x) {
    if (x != memo_arg[slot]) {
      memo_arg[slot] = x;
      memo_log[slot] = tlog(x);
    }
    return memo_log[slot];
  }
  // log(a / b), a >= 0, b > 0 (see log_ratio)
  TA_HD TA_INLINE T log_ratio_memo(int slot, T a, T b) {
    const T r = a / b;
    return r > T(0) && r < tinf<T>() ? log_memo(slot, r) : log_ratio(a, b);
  }
};

// The state at the start of the walk of sensor element `elem`, sample `sample`, channel `chan` (LANES == 1), and
// the result it would leave if it ended now (V = 0).
template <typename T, int LANES, bool HERO>
TA_HD TA_INLINE void begin_path(const Scene<T>& S, int64_t elem, int64_t sample, int chan, PathState<T, LANES>& st,
                             PathResult<T, LANES>& res) {
  for (int l = 0; l < LANES; ++l) {
    res.value[l] = T(0);
    res.prod_nonzero[l] = T(1);
    res.zeros[l] = 0;
  }
  for (int k = 0; k < 3; ++k) res.direction[k] = T(0);
  st.ch0 = HERO ? hero_channel<T>(S.seed, elem, sample) : (LANES == 1 ? chan : 0);
  st.rng = PathRng<T>{S.seed, uint32_t(elem), uint32_t(sample), uint32_t(HERO ? 4 : (LANES == 1 ? chan : 3))};
  st.event = 0;
  for (int l = 0; l < LANES; ++l) st.w[l] = st.wref[l] = T(1);
  for (int k = 0; k < 3; ++k) st.lrho[k] = T(0);
  for (int l = 0; l < LANES; ++l) st.lw[l] = T(0);
  for (int i = 0; i < 6; ++i) st.memo_arg[i] = st.memo_log[i] = T(0);
  st.depth = 0;
  st.fresh = true;
}

// The walk escapes along dir: its weight, combined over the channels for a hero walk.
template <bool HERO, typename T, int LANES>
TA_HD TA_INLINE void finish(const PathState<T, LANES>& st, PathResult<T, LANES>& res, const T dir[3]) {
  if constexpr (HERO) hero_escape(res, st.lw, st.lrho, dir);
  else escape(res, st.w, dir);
}

// Step 1, the start at the sensor: event 0 places the walk (u0, u1) and holds the first Fresnel event (u2). Face
// texels start inside the box on its face, where a dielectric reflects the emitter specularly (normal incidence):
// false when the walk ends there.
template <typename T, int LANES, int BOUNDARY, bool DIELECTRIC, bool HERO>
TA_HD TA_INLINE bool start_at_sensor(const Scene<T>& S, int64_t elem, PathState<T, LANES>& st,
                                  PathResult<T, LANES>& res) {
  const Medium<T>& M = S.medium;
  st.rng.draw(st.event++, st.u);
  st.u_fresnel = st.u[2];
  if (S.sensor.kind == kFaceTexels) {
    S.sensor.generate_on_face(elem, M.D, M.H, M.W, M.voxel, st.u, st.p, st.d, st.idx);
    st.inside = true;
    if (DIELECTRIC) {
      const T r = fresnel_dielectric(T(1), T(1) / S.ior);
      if (st.u[2] < r) {
        const T back[3] = {0, 0, -st.d[2]};
        finish<HERO>(st, res, back);
        return false;
      }
    }
    return true;
  }
  T o[3];
  S.sensor.generate(elem, st.u, o, st.d);
  for (int k = 0; k < 3; ++k) st.p[k] = o[k] - M.origin[k];
  st.inside = start_inside<T, BOUNDARY>(S, st.p, st.idx);
  return true;
}

// How a flight ended: at a collision (in voxel st.v), at the SDF surface, or at the grid box's face normal to `axis`.
enum FlightEnd : int { kCollided = 0, kReachedSurface = 1, kLeftGrid = 2 };
struct Flight {
  int end = kCollided;
  int axis = -1;  // kLeftGrid
};

// Step 2, one free flight inside the object in the reference medium: draws the flight's event (u0 the optical depth
// to the collision; u1..u3 are left for what ends the flight), walks the voxels with the DDA (analytic transmittance
// per voxel), stops at the collision, the surface (SDF) or the grid's box, and moves p there. On the way: the ratio
// weights of the flight (RATIO, HERO), its segments in the tape (RECORD) or their ∂/∂σ_t (ADJOINT).
template <typename T, int LANES, int BOUNDARY, bool RATIO, bool ADJOINT, bool RECORD, bool HERO, typename Deposit>
TA_HD TA_INLINE Flight fly(const Scene<T>& S, PathState<T, LANES>& st, PathResult<T, LANES>& res, int chan,
                        const PathResult<T, LANES>* pass1, const T* adj, const Adjoint<T, Deposit>& A,
                        Tape<T, LANES>* tape) {
  constexpr bool SDF = BOUNDARY == kSDFBoundary;
  const Medium<T>& M = S.medium;
  const int64_t N = M.voxels();
  const int ch0 = st.ch0;
  st.rng.draw(st.event++, st.u);
  const T tau = -tlog(st.u[0]);  // optical depth to the next collision, in the reference medium

  VoxelDDA<T> dda(M, st.p, st.d, st.idx);
  const T p0[3] = {st.p[0], st.p[1], st.p[2]}, d0[3] = {st.d[0], st.d[1], st.d[2]};  // for crossing (find_entry)
  T t = 0, acc = 0;
  T excess[LANES];  // Σ (σ_c − σ̂)·ℓ over the flight, for the transmittance ratio
  for (int l = 0; l < LANES; ++l) excess[l] = T(0);
  T ref_excess[3] = {0, 0, 0};  // HERO: Σ (σ̂_k − σ̂_h)·ℓ over the flight
  Flight f;
  for (;;) {
    ++res.voxel_steps;
    if (S.tally != nullptr) ++S.tally[2 * S.tally_bin[dda.voxel()] + 1];
    if (const int k = SDF ? M.core_distance(dda.idx) : 0; k > 0) {
      // the box of core bricks within k − 1 bricks of this one is homogeneous and inside the object, with no ratio
      // weights and (in a replay) no gradient: the flight crosses it in one move, or collides in it
      const auto box = dda.brick_box(M, p0, d0, k);
      const T sref = M.core_sigma_t[ch0];
      const T od = sref * (box.t - dda.t0);
      const bool collided = acc + od >= tau;
      const T len = collided ? (tau - acc) / sref : box.t - dda.t0;
      if (RATIO) {
        for (int l = 0; l < LANES; ++l) excess[l] += (M.core_sigma_t[LANES == 1 ? chan : l] - sref) * len;
      }
      if (HERO) {
        for (int kk = 0; kk < 3; ++kk) ref_excess[kk] += (M.core_sigma_t[kk] - sref) * len;
      }
      if (collided) {
        t = dda.t0 + len;
        VoxelDDA<T>::voxel_in(box, M, p0, d0, t, dda.idx);
        st.v = dda.voxel();
        f.end = kCollided;
        break;
      }
      acc += od;
      if (!dda.leave(box, M, p0, d0)) {
        t = dda.t0;
        f.end = kLeftGrid;
        f.axis = dda.axis;
        break;
      }
      continue;
    }
    const int64_t v = dda.voxel();
    {  // ask for the next voxel's values while this one is worked on: the walk waits on these loads (cache misses)
      const int64_t nv = dda.next_voxel();
      if (M.ref_sigma_t.data != nullptr) prefetch(M.ref_sigma_t.data + ch0 * N + nv);
      if (LANES == 1 && M.ref_albedo.data != nullptr) prefetch(M.ref_albedo.data + chan * N + nv);
      if (SDF) prefetch(S.sdf.cell + nv);
    }
    T tend = dda.t1;
    bool hit_here = false;
    if (SDF && S.sdf.cell[v] != kCellInside) {
      const int64_t cell[3] = {dda.idx[0], dda.idx[1], dda.idx[2]};  // the DDA's address stays private (find_entry)
      T th;
      if (S.sdf.crossing(M, cell, p0, d0, dda.t0, tend, T(1), &th)) {
        tend = th;
        hit_here = true;
      }
    }
    const T seg = tmax(T(0), tend - dda.t0);
    const T sref = M.ref_sigma_t[ch0 * N + v];  // reference density, mm⁻¹ (t is in mm)
    const T od = sref * seg;
    T len = seg;
    bool collided = false;
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
        A.sigma_t(c, v, -(adj[l] * pass1->value[l] * len));
      }
    }
    if (collided) {
      t = dda.t0 + len;
      st.v = v;
      f.end = kCollided;
      break;
    }
    acc += od;
    if (hit_here) {
      t = tend;
      f.end = kReachedSurface;
      break;
    }
    if (!dda.next()) {
      t = dda.t0;
      f.end = kLeftGrid;
      f.axis = dda.axis;
      break;
    }
  }
  for (int k = 0; k < 3; ++k) st.idx[k] = dda.idx[k];
  for (int k = 0; k < 3; ++k) st.p[k] += st.d[k] * t;
  if constexpr (HERO) {
    for (int k = 0; k < 3; ++k) st.lrho[k] -= ref_excess[k];
    for (int l = 0; l < LANES; ++l) st.lw[l] -= RATIO ? excess[l] : ref_excess[l];  // f_c/p_h of the flight
  } else if (RATIO) {
    for (int l = 0; l < LANES; ++l) {
      const T fl = texp(-excess[l]);
      st.w[l] *= fl;
      res.prod_nonzero[l] *= fl;
    }
  }
  return f;
}

// Step 3, the collision in voxel st.v: keeps p in that voxel, counts the interaction (cut past max_depth),
// continues with probability p_s·q (u1; reference albedo, roulette on the reference weight), carries the collision's
// factors σ_c/σ̂ and α_c/(p_s q) (records them, or deposits their ∂), and samples the new direction (u2, u3).
// False when the walk ends (truncated, absorbed or killed by roulette).
template <typename T, int LANES, bool RATIO, bool ADJOINT, bool RECORD, bool HERO, typename Deposit>
TA_HD TA_INLINE bool collide(const Scene<T>& S, PathState<T, LANES>& st, PathResult<T, LANES>& res, int chan,
                          const PathResult<T, LANES>* pass1, const T* adj, const Adjoint<T, Deposit>& A,
                          Tape<T, LANES>* tape) {
  const Medium<T>& M = S.medium;
  const int64_t N = M.voxels();
  const T* vs = M.voxel;
  const int64_t v = st.v;
  const int ch0 = st.ch0;
  // keep the point inside the voxel the DDA found (no drift into a neighbour through rounding)
  for (int k = 0; k < 3; ++k) st.p[k] = tmin(T(st.idx[k] + 1) * vs[k], tmax(T(st.idx[k]) * vs[k], st.p[k]));
  if (++st.depth > S.max_depth) {  // truncated: contributes 0
    res.truncated = true;
    return false;
  }
  ++res.scatter_events;
  if (S.tally != nullptr) ++S.tally[2 * S.tally_bin[v]];
  // a collision in the homogeneous core reads the core's values (equal in the parameters and the reference) and
  // carries no gradient (Medium::core)
  const bool core = M.core_distance(st.idx) > 0;
  res.core_events += core;
  const auto sigma = [&](const Channels<T>& x, int c) TA_INLINE_LAMBDA { return core ? M.core_sigma_t[c] : x[c * N + v]; };
  const auto alpha = [&](const Channels<T>& x, int c) TA_INLINE_LAMBDA { return core ? M.core_albedo[c] : x[c * N + v]; };
  // continuation probability: reference albedo (max over lanes), times roulette on the reference weight
  T ps, aref[LANES];
  if (LANES == 1) {
    aref[0] = alpha(M.ref_albedo, chan);
    ps = aref[0];
  } else {
    ps = 0;
    for (int l = 0; l < LANES; ++l) {
      aref[l] = alpha(M.ref_albedo, l);
      ps = tmax(ps, aref[l]);
    }
  }
  T q = T(1);
  if (st.depth > S.rr_depth) {
    T m = 0;
    for (int l = 0; l < LANES; ++l) m = tmax(m, st.wref[l] * aref[l] / ps);
    q = tmin(T(1), m);
  }
  if (!(st.u[1] < ps * q)) return false;  // absorbed or killed by roulette: contributes 0
  const T inv_psq = T(1) / (ps * q);
  const T sh = sigma(M.ref_sigma_t, ch0);  // the reference density that sampled the flight
  if constexpr (HERO) {  // the collision density ratios σ̂_k/σ̂_h of the path pdfs
    for (int k = 0; k < 3; ++k)
      if (k != ch0) st.lrho[k] += st.log_ratio_memo(k, sigma(M.ref_sigma_t, k), sh);  // −inf for σ̂_k = 0
  }
  TapeCollision<T, LANES>* rec = nullptr;
  if (RECORD && !core) {
    rec = tape->collision(v);
    if (rec) {
      rec->sref = sh;
      rec->inv_psq = inv_psq;
    }
  }
  for (int l = 0; l < LANES; ++l) {
    const int c = LANES == 1 ? chan : l;
    st.wref[l] *= aref[l] * inv_psq;
    const T fa = alpha(M.albedo, c) * inv_psq;  // albedo factor α_c/(p_s q)
    T fs = T(1);                                // collision factor σ_c/σ̂
    if (RATIO) fs = sigma(M.sigma_t, c) / sh;
    else if (HERO) fs = sigma(M.ref_sigma_t, c) / sh;
    if (RECORD && rec) {
      rec->fs[l] = fs;
      rec->fa[l] = fa;
    }
    if (ADJOINT && !core) {
      if (A.grad_sigma_t)
        A.sigma_t(c, v, adj[l] * weight_without(fs, pass1->value[l], pass1->prod_nonzero[l], pass1->zeros[l]) /
                                 sh);
      if (A.grad_albedo)
        A.albedo(c, v,
                 adj[l] * weight_without(fa, pass1->value[l], pass1->prod_nonzero[l], pass1->zeros[l]) * inv_psq);
    }
    if constexpr (HERO) {
      if (fs == T(0)) ++res.zeros[l];
      if (fa == T(0)) ++res.zeros[l];
      if (fs != T(0) && fa != T(0)) {
        const T f = fs * fa;  // one logarithm unless the product leaves the normal range
        st.lw[l] += (f > T(0) && f < tinf<T>()) ? st.log_memo(3 + l, f) : tlog(fs) + tlog(fa);
      }
    } else if (RATIO || LANES > 1) {
      st.w[l] *= fs * fa;
      if (fs == T(0)) ++res.zeros[l]; else res.prod_nonzero[l] *= fs;
      if (fa == T(0)) ++res.zeros[l]; else res.prod_nonzero[l] *= fa;
    }
  }
  rotate_direction(st.d, sample_hg_cos(S.g, st.u[2]), st.u[3]);
  return true;
}

// Step 4, the boundary reached from inside (the SDF surface, or the grid box's face normal to f.axis): a dielectric
// reflects internally (u1 < F; an interaction) or refracts; the walk then leaves the object: it escapes the box (or
// an SDF object's grid), or flies on outside an SDF object. False when the walk ends (escaped or truncated).
template <typename T, int LANES, int BOUNDARY, bool DIELECTRIC, bool HERO>
TA_HD TA_INLINE bool cross_from_inside(const Scene<T>& S, PathState<T, LANES>& st, PathResult<T, LANES>& res,
                                    const Flight& f) {
  constexpr bool SDF = BOUNDARY == kSDFBoundary;
  const Medium<T>& M = S.medium;
  const bool surface = f.end == kReachedSurface;
  const int exit_axis = f.axis;
  T n[3] = {0, 0, 0};  // outward unit normal
  if (surface) {
    const int64_t cell[3] = {st.idx[0], st.idx[1], st.idx[2]};  // copies: st stays private (find_entry)
    const T pc[3] = {st.p[0], st.p[1], st.p[2]}, dc[3] = {st.d[0], st.d[1], st.d[2]};
    S.sdf.normal(M, cell, pc, dc, n);
  } else {
    st.p[exit_axis] = st.d[exit_axis] > T(0) ? T(M.dim(exit_axis)) * M.voxel[exit_axis] : T(0);
    n[exit_axis] = st.d[exit_axis] > T(0) ? T(1) : T(-1);
  }
  if (DIELECTRIC) {
    const T cos_i = surface ? tmin(T(1), tmax(T(0), dot3(st.d, n))) : tabs(st.d[exit_axis]);
    if (st.u[1] < fresnel_dielectric(cos_i, S.ior)) {  // internal reflection (total when F == 1)
      if (++st.depth > S.max_depth) {
        res.truncated = true;
        return false;
      }
      if (surface) {
        const T n_inc[3] = {-n[0], -n[1], -n[2]};
        reflect(st.d, n_inc, cos_i);
      } else {
        st.d[exit_axis] = -st.d[exit_axis];
      }
      return true;
    }
    if (SDF || S.emitter.kind != kConstant) {  // the escape direction matters: refract
      const T n_inc[3] = {-n[0], -n[1], -n[2]};
      refract(st.d, n_inc, cos_i, S.ior);
    }
  }
  if (!SDF || !surface) {  // left the box (convex) or, for an SDF, the grid: escaped
    finish<HERO>(st, res, st.d);
    return false;
  }
  if (++st.depth > S.max_depth) {
    res.truncated = true;
    return false;
  }
  st.inside = false;
  return true;
}

// Step 5, outside the object: the flight to the next surface point (find_entry; none: the walk escapes), the Fresnel
// event of the hit (u0 of a new event, except for the first hit, whose uniform came with the start), the crossing
// counted as an interaction (SDF), then reflection (u < F) or refraction into the object. False when the walk ends
// (escaped, reflected off the convex box, or truncated).
template <typename T, int LANES, int BOUNDARY, bool DIELECTRIC, bool HERO>
TA_HD TA_INLINE bool enter_from_outside(const Scene<T>& S, PathState<T, LANES>& st, PathResult<T, LANES>& res) {
  constexpr bool SDF = BOUNDARY == kSDFBoundary;
  T n[3];
  if (!find_entry<T, BOUNDARY>(S, st.p, st.d, st.idx, n, res.outside_steps)) {
    finish<HERO>(st, res, st.d);
    return false;
  }
  if (!st.fresh) {
    st.rng.draw(st.event++, st.u);
    st.u_fresnel = st.u[0];
  }
  st.fresh = false;
  if (SDF && ++st.depth > S.max_depth) {
    res.truncated = true;
    return false;
  }
  if (DIELECTRIC) {
    const T cos_i = tmin(T(1), -dot3(st.d, n));
    const T eta = T(1) / S.ior;
    if (st.u_fresnel < fresnel_dielectric(cos_i, eta)) {
      reflect(st.d, n, cos_i);
      if (!SDF) {  // a convex box: the reflected ray leaves
        finish<HERO>(st, res, st.d);
        return false;
      }
      return true;  // still outside
    }
    refract(st.d, n, cos_i, eta);
  }
  st.inside = true;
  return true;
}

// One random walk of the path that starts at sensor element `elem`, sample `sample`: the steps above in turn.
// `chan` is the channel for LANES == 1 (lanes map to channels 0..2 for LANES == 3).
// With ADJOINT, `pass1` holds this path's result from a non-adjoint replay and `adj[l]` = grad_out·L_e/spp.
// With RECORD, the walk writes what its derivative needs into `tape` (for the gradient buffers named in A; see
// tape.h) and the caller deposits after the walk: one walk instead of two.
template <typename T, int LANES, int BOUNDARY, bool DIELECTRIC, bool RATIO, bool ADJOINT, bool RECORD = false,
          bool HERO = false, typename Deposit = PlainAdd>
TA_HD inline PathResult<T, LANES> trace_path(const Scene<T>& S, int64_t elem, int64_t sample, int chan,
                                             const PathResult<T, LANES>* pass1, const T* adj,
                                             const Adjoint<T, Deposit>& A, Tape<T, LANES>* tape = nullptr) {
  static_assert(!ADJOINT || RATIO, "the adjoint replay always carries ratio weights");
  static_assert(!RECORD || (RATIO && !ADJOINT), "the recording walk carries ratio weights and deposits nothing");
  static_assert(!HERO || LANES == 3, "a hero walk serves all three channels");
  PathResult<T, LANES> res;
  PathState<T, LANES> st;
  begin_path<T, LANES, HERO>(S, elem, sample, chan, st, res);
  if (!start_at_sensor<T, LANES, BOUNDARY, DIELECTRIC, HERO>(S, elem, st, res)) return res;
  for (;;) {
    if (!st.inside) {
      if (!enter_from_outside<T, LANES, BOUNDARY, DIELECTRIC, HERO>(S, st, res)) return res;
      continue;
    }
    const Flight f = fly<T, LANES, BOUNDARY, RATIO, ADJOINT, RECORD, HERO>(S, st, res, chan, pass1, adj, A, tape);
    if (f.end == kCollided) {
      if (!collide<T, LANES, RATIO, ADJOINT, RECORD, HERO>(S, st, res, chan, pass1, adj, A, tape)) return res;
      continue;
    }
    if (!cross_from_inside<T, LANES, BOUNDARY, DIELECTRIC, HERO>(S, st, res, f)) return res;
  }
}

}  // namespace core
}  // namespace ta
