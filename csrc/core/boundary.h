// Boundaries of the medium. Consulted at every DDA step, so the kind is a template parameter of the walk:
//
//   Box  the grid's own bounding box (the slab of the first wave).
//   SDF  the zero level set of a signed-distance grid sampled at the voxel corners ((D+1)×(H+1)×(W+1), mm,
//        negative inside), trilinear inside each voxel cell; the outward normal is the normalised gradient of that
//        trilinear interpolant. The medium counts only inside.
//
// Either kind is index matched or a smooth dielectric (template flag of the walk; optics in optics.h).
//
// Exact ray–SDF intersection (Marmitt, Kleer, Wald, Friedrich and Slusallek, "Fast and accurate ray-voxel
// intersection techniques for iso-surface ray tracing", VMV 2004): along a ray inside one cell the trilinear
// interpolant is a cubic in the ray parameter. Its coefficients come from the 8 corners; the roots of its
// derivative (a quadratic) split the cell's ray interval into at most three monotone pieces, and the first piece
// whose end lies on the far side of the surface holds exactly one crossing, found by bisection to the last bit
// (robust where Newton or closed-form cubic roots lose digits: tangential hits, nearly flat cells).
#pragma once

#include "core/defs.h"
#include "core/medium.h"

namespace ta {
namespace core {

enum BoundaryKind : int { kBoxBoundary = 0, kSDFBoundary = 1 };

// Classification of an SDF cell by its 8 corners: all < 0, all > 0, or mixed (may hold surface).
enum CellKind : uint8_t { kCellMixed = 0, kCellInside = 1, kCellOutside = 2 };

// Empty-space skipping outside the object: the cells are grouped in bricks of kBrick³ (medium.h), and each brick holds the
// Chebyshev distance (in bricks, capped at 255) to the nearest brick with a cell that is not kCellOutside (0: it holds
// one). A ray outside the object in a brick at distance k >= 1 can leave the box of bricks within k − 1 of it in one
// move: every cell of that box is outside, so no surface is passed (find_entry, integrator.h).
template <typename T>
struct SDFGrid {
  const T* sdf = nullptr;            // (D+1, H+1, W+1) corner values, mm
  const uint8_t* cell = nullptr;     // (D, H, W) CellKind, derived from sdf by the glue
  const uint8_t* skip = nullptr;     // (⌈D/4⌉, ⌈H/4⌉, ⌈W/4⌉) brick distances; nullptr: no skipping
  int64_t bricks[3] = {0, 0, 0};     // bricks along x, y, z

  // The brick distance of cell idx (0 without skipping).
  TA_HD TA_INLINE int skip_distance(const int64_t idx[3]) const {
    if (skip == nullptr) return 0;
    return skip[brick_index(bricks, idx)];
  }

  TA_HD TA_INLINE void corners(const Medium<T>& M, const int64_t idx[3], T c[8]) const {
    const int64_t W1 = M.W + 1, HW1 = (M.H + 1) * W1;
    const T* base = sdf + idx[2] * HW1 + idx[1] * W1 + idx[0];
    c[0] = base[0];
    c[1] = base[1];
    c[2] = base[W1];
    c[3] = base[W1 + 1];
    c[4] = base[HW1];
    c[5] = base[HW1 + 1];
    c[6] = base[HW1 + W1];
    c[7] = base[HW1 + W1 + 1];
  }

  // Trilinear value and world-space gradient (per mm) at the grid-local point p inside cell idx.
  TA_HD TA_INLINE T value_gradient(const Medium<T>& M, const int64_t idx[3], const T p[3], T grad[3]) const {
    T c[8];
    corners(M, idx, c);
    T x[3];
    for (int a = 0; a < 3; ++a) x[a] = tmin(T(1), tmax(T(0), p[a] / M.voxel[a] - T(idx[a])));
    const T c00 = c[0] + (c[1] - c[0]) * x[0], c10 = c[2] + (c[3] - c[2]) * x[0];
    const T c01 = c[4] + (c[5] - c[4]) * x[0], c11 = c[6] + (c[7] - c[6]) * x[0];
    const T c0 = c00 + (c10 - c00) * x[1], c1 = c01 + (c11 - c01) * x[1];
    // derivatives in unit-cell coordinates
    const T dx0 = (c[1] - c[0]) * (1 - x[1]) + (c[3] - c[2]) * x[1];
    const T dx1 = (c[5] - c[4]) * (1 - x[1]) + (c[7] - c[6]) * x[1];
    grad[0] = (dx0 * (1 - x[2]) + dx1 * x[2]) / M.voxel[0];
    grad[1] = ((c10 - c00) * (1 - x[2]) + (c11 - c01) * x[2]) / M.voxel[1];
    grad[2] = (c1 - c0) / M.voxel[2];
    return c0 + (c1 - c0) * x[2];
  }

  // Outward unit normal at p (the normalised gradient); falls back to −d where the gradient vanishes.
  TA_HD inline void normal(const Medium<T>& M, const int64_t idx[3], const T p[3], const T d[3], T n[3]) const {
    value_gradient(M, idx, p, n);
    const T len2 = dot3(n, n);
    if (!(len2 > T(0))) {
      for (int k = 0; k < 3; ++k) n[k] = -d[k];
      return;
    }
    const T inv = T(1) / tsqrt(len2);
    for (int k = 0; k < 3; ++k) n[k] *= inv;
  }

  // First crossing of the surface along p + d·t, t in [t0, t1], inside cell idx. `side` = +1 when the ray is
  // inside (looking for f >= 0), −1 when outside (looking for f <= 0). A crossing is where h = side·f rises to
  // h >= 0; the returned t lies on the far side (h(t) >= 0), so the new side is consistent with the field.
  TA_HD inline bool crossing(const Medium<T>& M, const int64_t idx[3], const T p[3], const T d[3], T t0, T t1,
                             T side, T* t_hit) const {
    T c[8];
    corners(M, idx, c);
    // unit-cell coordinates x(τ) = a + b·τ with τ = t − t0
    T a[3], b[3];
    for (int k = 0; k < 3; ++k) {
      a[k] = (p[k] + d[k] * t0) / M.voxel[k] - T(idx[k]);
      b[k] = d[k] / M.voxel[k];
    }
    // h(τ) = side·Σ c_corner · Π_axes (1 − x or x): a product of three linear factors per corner
    T k0 = 0, k1 = 0, k2 = 0, k3 = 0;
    for (int corner = 0; corner < 8; ++corner) {
      const int ix = corner & 1, iy = (corner >> 1) & 1, iz = (corner >> 2) & 1;
      const T p0 = ix ? a[0] : T(1) - a[0], p1 = ix ? b[0] : -b[0];
      const T q0 = iy ? a[1] : T(1) - a[1], q1 = iy ? b[1] : -b[1];
      const T r0 = iz ? a[2] : T(1) - a[2], r1 = iz ? b[2] : -b[2];
      const T w = side * c[corner];
      k0 += w * p0 * q0 * r0;
      k1 += w * (p1 * q0 * r0 + p0 * q1 * r0 + p0 * q0 * r1);
      k2 += w * (p1 * q1 * r0 + p1 * q0 * r1 + p0 * q1 * r1);
      k3 += w * p1 * q1 * r1;
    }
    const T L = t1 - t0;
    if (!(L > T(0))) return false;
    // split points: roots of h'(τ) = 3k3 τ² + 2k2 τ + k1 inside (0, L)
    T split[4];
    int ns = 0;
    split[ns++] = T(0);
    {
      const T A = T(3) * k3, B = T(2) * k2, C = k1;
      T r[2];
      int nr = 0;
      if (A != T(0)) {
        const T disc = B * B - T(4) * A * C;
        if (disc > T(0)) {
          const T sq = tsqrt(disc);
          const T q = T(-0.5) * (B + tcopysign(sq, B));  // numerically stable quadratic roots
          r[nr++] = q / A;
          if (q != T(0)) r[nr++] = C / q;
        }
      } else if (B != T(0)) {
        r[nr++] = -C / B;
      }
      if (nr == 2 && r[1] < r[0]) {
        const T tmp = r[0];
        r[0] = r[1];
        r[1] = tmp;
      }
      for (int i = 0; i < nr; ++i)
        if (r[i] > T(0) && r[i] < L) split[ns++] = r[i];
    }
    split[ns++] = L;
    auto h = [&](T s) { return ((k3 * s + k2) * s + k1) * s + k0; };
    for (int i = 0; i + 1 < ns; ++i) {
      const T s0 = split[i], s1 = split[i + 1];
      const T h0 = h(s0), h1 = h(s1);
      if (!(h1 > h0) || h1 < T(0)) continue;  // not rising, or still on this side at the piece's end
      if (h0 >= T(0)) {
        *t_hit = t0 + s0;
        return true;
      }
      // h(lo) < 0 <= h(hi), h monotone on [lo, hi]: safeguarded Newton down to adjacent numbers, what bisection
      // reaches in ~25 (float) or ~53 (double) halvings, in about 5 steps (float: 5.4 on average, at most 13, on
      // 20000 random monotone cubic pieces; the result on the far side always, within 9 ulps of bisection's).
      // Newton starts from the end whose |h| is smaller; a step that stays within one ulp of its start takes that
      // ulp (a converged Newton still closes the bracket); a step that leaves the bracket (or a flat derivative)
      // bisects, and so does every step after three in a row on the same side (the bracket keeps shrinking).
      T lo = s0, hi = s1, hl = h0, hh = h1;
      int same = 0, last = 0;
      for (int it = 0; it < 160; ++it) {
        T m;
        if (same >= 3) {
          m = T(0.5) * (lo + hi);
          same = 0;
        } else {
          const bool from_lo = -hl < hh;
          const T s = from_lo ? lo : hi, hs = from_lo ? hl : hh;
          m = s - hs / ((T(3) * k3 * s + T(2) * k2) * s + k1);
          const T nb = tnextafter(s, from_lo ? hi : lo);
          if (from_lo ? (m < nb && m >= s) : (m > nb && m <= s)) m = nb;
          if (!(m > lo && m < hi)) m = T(0.5) * (lo + hi);
        }
        if (!(m > lo && m < hi)) break;  // lo and hi are adjacent numbers: exhausted at this precision
        const T hm = h(m);
        const int side_m = hm >= T(0) ? 1 : -1;
        if (side_m > 0) {
          hi = m;
          hh = hm;
        } else {
          lo = m;
          hl = hm;
        }
        same = side_m == last ? same + 1 : 0;
        last = side_m;
      }
      *t_hit = t0 + hi;
      return true;
    }
    return false;
  }
};

}  // namespace core
}  // namespace ta
