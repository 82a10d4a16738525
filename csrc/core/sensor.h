// Sensors: where paths start. Consulted once per path, so a tagged struct dispatched by `switch`.
//
//   Face           one texel per voxel column of the box's top (z = D·sz) and/or bottom (z = 0) face; a sample
//                  starts at a uniform point of the texel's square footprint, along the inward normal, already
//                  inside the box (generate_on_face, in the grid's own frame).
//   SurfaceTexels  an arbitrary list of texels: surface point P, outward unit normal n, footprint radius r. A
//                  sample is a uniform point of the disc of radius r around P in the tangent plane, lifted
//                  outwards by `lift` mm, shot along −n; the texel value is the radiance leaving along n.
//   Orthographic   pixel (r, c) starts at origin + right·((c + ξ1)/cols − ½)·width + up·(½ − (r + ξ2)/rows)·height,
//                  direction forward.
//   Perspective    pinhole at origin; direction normalise(forward + x·right + y·up) with
//                  x = (2(c + ξ1)/cols − 1)·tan(fov_y/2)·cols/rows, y = (1 − 2(r + ξ2)/rows)·tan(fov_y/2).
// Row 0 of an image is the `up` side, column 0 the left side. Positions are world mm.
#pragma once

#include "core/defs.h"
#include "core/optics.h"

namespace ta {
namespace core {

enum SensorKind : int { kFaceTexels = 0, kSurfaceTexels = 1, kOrthographic = 2, kPerspective = 3 };
enum Face : int { kFaceTop = 0, kFaceBottom = 1, kFaceBoth = 2 };

template <typename T>
struct Sensor {
  int kind = kFaceTexels;
  int face = kFaceTop;         // kFaceTexels
  const T* points = nullptr;   // kSurfaceTexels: (N, 3) world mm
  const T* normals = nullptr;  //                 (N, 3) outward unit normals
  const T* radius = nullptr;   //                 (N,) footprint radius, mm
  int64_t count = 0;           // kSurfaceTexels: N
  T lift = 0;                  //                 start offset along n, mm
  T origin[3] = {0, 0, 0};     // cameras: eye position (world mm) and orthonormal frame
  T forward[3] = {0, 0, -1};
  T right[3] = {1, 0, 0};
  T up[3] = {0, 1, 0};
  int64_t rows = 0, cols = 0;  // cameras: image size
  T width = 0, height = 0;     // kOrthographic: image extent, mm
  T tan_half_fov = 0;          // kPerspective: tan(fov_y / 2)

  // kFaceTexels: the start of element `e` in the grid-local frame of a D×H×W grid with voxel edges vs (mm): the
  // point (u[0], u[1]) of the texel's footprint on its face, the inward normal d, and the voxel idx of the point
  // (u[2] is left for the Fresnel event at the face).
  TA_HD TA_INLINE void generate_on_face(int64_t e, int64_t D, int64_t H, int64_t W, const T vs[3], const T u[4], T p[3],
                                     T d[3], int64_t idx[3]) const {
    const int64_t HW = H * W;
    const int f = face == kFaceBoth ? int(e / HW) : face;
    const int64_t ti = e % HW;
    const int64_t tj = ti / W, tx = ti % W;
    p[0] = (T(tx) + u[0]) * vs[0];
    p[1] = (T(tj) + u[1]) * vs[1];
    p[2] = f == kFaceTop ? T(D) * vs[2] : T(0);
    d[0] = d[1] = T(0);
    d[2] = f == kFaceTop ? T(-1) : T(1);
    idx[0] = tx;
    idx[1] = tj;
    idx[2] = f == kFaceTop ? D - 1 : 0;
  }

  // World-space start ray of element `e` of the other kinds, from the uniforms u[0], u[1] (u[2] is left for the
  // first Fresnel event).
  TA_HD TA_INLINE void generate(int64_t e, const T u[4], T o[3], T d[3]) const {
    switch (kind) {
      case kSurfaceTexels: {
        const T* P = points + 3 * e;
        const T* n = normals + 3 * e;
        T b1[3], b2[3];
        tangent_frame(n, b1, b2);
        const T rho = radius[e] * tsqrt(u[0]);
        const T phi = T(2 * kPi) * u[1];
        const T cx = rho * tcos(phi), cy = rho * tsin(phi);
        for (int k = 0; k < 3; ++k) {
          o[k] = P[k] + cx * b1[k] + cy * b2[k] + lift * n[k];
          d[k] = -n[k];
        }
        return;
      }
      case kOrthographic: {
        const int64_t r = e / cols, c = e % cols;
        const T sx = ((T(c) + u[0]) / T(cols) - T(0.5)) * width;
        const T sy = (T(0.5) - (T(r) + u[1]) / T(rows)) * height;
        for (int k = 0; k < 3; ++k) {
          o[k] = origin[k] + right[k] * sx + up[k] * sy;
          d[k] = forward[k];
        }
        return;
      }
      default: {  // kPerspective
        const int64_t r = e / cols, c = e % cols;
        const T x = (T(2) * (T(c) + u[0]) / T(cols) - T(1)) * tan_half_fov * T(cols) / T(rows);
        const T y = (T(1) - T(2) * (T(r) + u[1]) / T(rows)) * tan_half_fov;
        for (int k = 0; k < 3; ++k) {
          o[k] = origin[k];
          d[k] = forward[k] + x * right[k] + y * up[k];
        }
        normalize3(d);
        return;
      }
    }
  }
};

}  // namespace core
}  // namespace ta
