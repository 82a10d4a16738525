// Single-walk path replay: the walk of a path records the few numbers its derivative needs (per flight segment the
// voxel and length, per collision the voxel and its factors) in a bounded, caller-owned tape; once the walk has
// ended its final weight V is known and the tape is replayed into the gradient buffers. This replaces the second
// walk of the classic two-pass replay (pass 1 for V, pass 2 re-walking the path to deposit), which repeated every
// random number, logarithm, direction sample and DDA step.
//
// The deposits are the same expressions on the same operands and in the same order as the two-pass replay
// (integrator.h, ADJOINT), so the gradients are bitwise identical to it. A path longer than the tape's capacity
// sets `overflow`; the caller then replays that path with the two-pass method (memory stays bounded and
// independent of path length).
#pragma once

#include "core/defs.h"
#include "core/adjoint.h"

namespace ta {
namespace core {

template <typename T, int LANES>
struct TapeSegment {
  int64_t v;  // voxel (flat index into one channel plane)
  T len;      // length of the flight inside the voxel, mm
};

template <typename T, int LANES>
struct TapeCollision {
  int64_t v;        // voxel of the collision
  int64_t seg_end;  // segments recorded before this collision (they are deposited first)
  T sref;           // reference density σ̂ of the walk's channel in v
  T inv_psq;        // 1 / (p_s q)
  T fs[LANES];      // collision factors σ_c / σ̂
  T fa[LANES];      // albedo factors α_c / (p_s q)
};

template <typename T, int LANES>
struct Tape {
  TapeSegment<T, LANES>* segs = nullptr;
  TapeCollision<T, LANES>* cols = nullptr;
  int64_t seg_cap = 0, col_cap = 0;
  int64_t nseg = 0, ncol = 0;
  bool overflow = false;

  TA_HD void clear() {
    nseg = ncol = 0;
    overflow = false;
  }
  TA_HD void segment(int64_t v, T len) {
    if (nseg < seg_cap) segs[nseg++] = {v, len};
    else overflow = true;
  }
  // The next collision entry, or null (and overflow) when the tape is full.
  TA_HD TapeCollision<T, LANES>* collision(int64_t v) {
    if (ncol >= col_cap) {
      overflow = true;
      return nullptr;
    }
    TapeCollision<T, LANES>& c = cols[ncol++];
    c.v = v;
    c.seg_end = nseg;
    return &c;
  }
};

template <typename T>
TA_HD inline T weight_without(T factor, T value, T prod_nonzero, int zeros) {
  if (factor != T(0)) return zeros == 0 ? value / factor : T(0);
  return zeros == 1 ? prod_nonzero : T(0);
}

// Deposits ∂V/∂θ of a recorded walk (see integrator.h for the formulas), each through A's deposit policy. `value`,
// `prod_nonzero`, `zeros` are the walk's final PathResult fields, `adj[l]` = grad_out·L_e/spp, `chan` the channel of
// a one-lane walk. `tape` is a Tape<T, LANES> or any record of the same fields (segs[].v, .len; cols[].v, .seg_end,
// .sref, .inv_psq, .fs[l], .fa[l]; nseg, ncol), as the SIMD walks' compact tapes (volpath/slab_simd.h).
template <typename T, int LANES, typename TapeT, typename Deposit>
TA_HD inline void deposit_tape(const TapeT& tape, const T* value, const T* prod_nonzero, const int* zeros, int chan,
                               const T* adj, const Adjoint<T, Deposit>& A) {
  int64_t s = 0;
  auto segments_until = [&](int64_t end) {
    if (!A.grad_sigma_t) return;  // (nothing was recorded then)
    for (; s < end; ++s) {
      const int64_t v = tape.segs[s].v;
      const T len = tape.segs[s].len;
      for (int l = 0; l < LANES; ++l) {
        const int c = LANES == 1 ? chan : l;
        A.sigma_t(c, v, -(adj[l] * value[l] * len));
      }
    }
  };
  for (int64_t k = 0; k < tape.ncol; ++k) {
    const auto& col = tape.cols[k];
    segments_until(col.seg_end);
    for (int l = 0; l < LANES; ++l) {
      const int c = LANES == 1 ? chan : l;
      if (A.grad_sigma_t)
        A.sigma_t(c, col.v, adj[l] * weight_without(col.fs[l], value[l], prod_nonzero[l], zeros[l]) / col.sref);
      if (A.grad_albedo)
        A.albedo(c, col.v, adj[l] * weight_without(col.fa[l], value[l], prod_nonzero[l], zeros[l]) *
                                    col.inv_psq);
    }
  }
  segments_until(tape.nseg);
}

}  // namespace core
}  // namespace ta
