// Exact regular tracking: the voxels that a ray crosses, in order, as an iterator object in the manner of pbrt-v4's
// DDAMajorantIterator (src/pbrt/media.h). There the cells of a coarse majorant grid bound the density; here the cells
// are the voxels of the piecewise-constant grid itself, so each segment's density is exact and a flight needs no
// null collisions. The walk's flight (integrator.h) and the search for an SDF surface from outside share it.
//
// The ray p + t·d (grid-local mm, unit d, t >= 0) starts in voxel `cell`. The current segment is voxel idx between
// the ray parameters t0 and t1 (mm), where the ray leaves it through the face normal to `axis`; next() moves on to
// the neighbour through that face. Same arithmetic, in the same order, as the loops it replaces.
#pragma once

#include "core/defs.h"
#include "core/medium.h"

namespace ta {
namespace core {

template <typename T>
struct VoxelDDA {
  int64_t idx[3];  // the current voxel (x, y, z)
  T t0 = 0;        // where the ray enters it (0 for the first: the ray's start), mm
  T t1 = 0;        // where the ray leaves it, mm
  int axis = 0;    // the axis of the face through which it leaves
  T tnext[3], tdelta[3];
  int64_t step[3], dims[3];

  TA_HD TA_INLINE VoxelDDA(const Medium<T>& M, const T p[3], const T d[3], const int64_t cell[3]) {
    dims[0] = M.W;
    dims[1] = M.H;
    dims[2] = M.D;
    for (int a = 0; a < 3; ++a) {
      idx[a] = cell[a];
      const T vs = M.voxel[a];
      if (d[a] > T(0)) {
        step[a] = 1;
        tdelta[a] = vs / d[a];
        tnext[a] = tmax(T(0), (T(idx[a] + 1) * vs - p[a]) / d[a]);
      } else if (d[a] < T(0)) {
        step[a] = -1;
        tdelta[a] = -vs / d[a];
        tnext[a] = tmax(T(0), (T(idx[a]) * vs - p[a]) / d[a]);
      } else {
        step[a] = 0;
        tdelta[a] = tinf<T>();
        tnext[a] = tinf<T>();
      }
    }
    pick();
  }

  // The box of whole bricks (kBrick³ voxels, medium.h) within k − 1 bricks of the current voxel's brick, clipped to
  // the grid (the caller knows that box to be uniform: empty space, or homogeneous core), and where the ray p + t·d
  // (the same p and d as at construction) leaves it.
  struct BrickBox {
    int64_t lo[3], hi[3];  // voxels, hi exclusive
    T t;                   // where the ray leaves the box, mm (>= t0)
    int axis;              // the axis of that face (-1: none, only for a zero direction)
  };
  TA_HD TA_INLINE BrickBox brick_box(const Medium<T>& M, const T p[3], const T d[3], int k) const {
    BrickBox b;
    b.t = tinf<T>();
    b.axis = -1;
    for (int a = 0; a < 3; ++a) {
      const int64_t brick = idx[a] / kBrick;
      b.lo[a] = tmax(int64_t(0), (brick - (k - 1)) * kBrick);
      b.hi[a] = tmin(dims[a], (brick + k) * kBrick);
      if (step[a] == 0) continue;
      const T ta = (T(step[a] > 0 ? b.hi[a] : b.lo[a]) * M.voxel[a] - p[a]) / d[a];
      if (ta < b.t) {
        b.t = ta;
        b.axis = a;
      }
    }
    b.t = tmax(b.t, t0);
    return b;
  }

  // The voxel of the point p + t·d of the box b, clamped to the box (against rounding; NaN → lo).
  TA_HD TA_INLINE static void voxel_in(const BrickBox& b, const Medium<T>& M, const T p[3], const T d[3], T t,
                                       int64_t cell[3]) {
    for (int a = 0; a < 3; ++a) {
      const T q = (p[a] + d[a] * t) / M.voxel[a];  // floor(q) by truncation, q > lo >= 0 (as Medium::locate)
      cell[a] = q >= T(b.hi[a] - 1) ? b.hi[a] - 1 : (q > T(b.lo[a]) ? int64_t(q) : b.lo[a]);
    }
  }

  // Moves on past the box b to the voxel the ray enters where it leaves it, as if it had stepped there (the exit
  // distances are computed anew from p, not accumulated). False when the ray leaves the grid there instead: idx is
  // then the box's voxel at the exit, t0 where it leaves and `axis` the axis of that face, as next() leaves them.
  TA_HD TA_INLINE bool leave(const BrickBox& b, const Medium<T>& M, const T p[3], const T d[3]) {
    int64_t cell[3];
    voxel_in(b, M, p, d, b.t, cell);
    t0 = b.t;
    if (b.axis < 0) return false;
    const int64_t out = step[b.axis] > 0 ? b.hi[b.axis] : b.lo[b.axis] - 1;
    if (out < 0 || out >= dims[b.axis]) {
      for (int a = 0; a < 3; ++a) idx[a] = cell[a];
      axis = b.axis;
      return false;
    }
    cell[b.axis] = out;
    for (int a = 0; a < 3; ++a) {
      idx[a] = cell[a];
      if (step[a] != 0) {
        const T plane = T(step[a] > 0 ? idx[a] + 1 : idx[a]) * M.voxel[a];
        tnext[a] = tmax(t0, (plane - p[a]) / d[a]);
      }
    }
    pick();
    return true;
  }

  // Flat index of the current voxel in one channel plane of the grid.
  TA_HD TA_INLINE int64_t voxel() const { return (idx[2] * dims[1] + idx[1]) * dims[0] + idx[0]; }

  // Flat index of the voxel that next() will step into (the current one where the ray leaves the grid there).
  TA_HD TA_INLINE int64_t next_voxel() const {
    int64_t n[3] = {idx[0], idx[1], idx[2]};
    n[axis] = tmin(dims[axis] - 1, tmax(int64_t(0), n[axis] + step[axis]));
    return (n[2] * dims[1] + n[1]) * dims[0] + n[0];
  }

  // Steps into the next voxel (t0 = the old t1). False when the ray leaves the grid instead: idx stays the last
  // voxel, t0 is where the ray leaves the grid and `axis` the axis of that face.
  TA_HD TA_INLINE bool next() {
    t0 = t1;
    idx[axis] += step[axis];
    if (idx[axis] < 0 || idx[axis] >= dims[axis]) {
      idx[axis] -= step[axis];
      return false;
    }
    tnext[axis] += tdelta[axis];
    pick();
    return true;
  }

 private:
  TA_HD TA_INLINE void pick() {
    axis = tnext[0] < tnext[1] ? (tnext[0] < tnext[2] ? 0 : 2) : (tnext[1] < tnext[2] ? 1 : 2);
    t1 = tnext[axis];
  }
};

}  // namespace core
}  // namespace ta
