// Emitters, evaluated inside the walk when a path escapes, in its escape direction (world space). Consulted once
// per path: a tagged struct dispatched by `switch`.
//
//   Constant     uniform environment radiance L (RGB).
//   EnvMap       lat-long map (Hm, Wm, 3), linear RGB, z up: θ = acos(d_z) ∈ [0, π], φ = atan2(d_y, d_x);
//                column coordinate (φ/2π mod 1)·Wm − ½, row coordinate (θ/π)·Hm − ½; bilinear between pixel
//                centres, wrapping in columns, clamped in rows.
//   Disc         distant disc light of angular radius δ around the unit direction w (pointing from the scene to the
//                light): L + ambient where d·w >= cos δ, ambient elsewhere.
#pragma once

#include "core/defs.h"

namespace ta {
namespace core {

enum EmitterKind : int { kConstant = 0, kEnvMap = 1, kDisc = 2 };

template <typename T>
struct Emitter {
  int kind = kConstant;
  T radiance[3] = {1, 1, 1};  // kConstant, kDisc
  T ambient[3] = {0, 0, 0};   // kDisc
  T direction[3] = {0, 0, 1}; // kDisc: unit vector towards the light
  T cos_max = 1;              // kDisc: cos δ
  const T* map = nullptr;     // kEnvMap: (Hm, Wm, 3)
  int64_t map_h = 0, map_w = 0;

  TA_HD inline void eval(const T d[3], T L[3]) const {
    switch (kind) {
      case kEnvMap: {
        const T z = tmin(T(1), tmax(T(-1), d[2]));
        const T theta = tacos(z);
        T phi = tatan2(d[1], d[0]) * T(1.0 / (2 * kPi));
        phi -= tfloor(phi);                               // [0, 1)
        if (!(phi >= T(0) && phi < T(1))) phi = T(0);     // non-finite direction: never an index out of range
        const T x = phi * T(map_w) - T(0.5);
        const T y = tmin(T(map_h - 1), tmax(T(0), theta * T(1.0 / kPi) * T(map_h) - T(0.5)));
        const T xf = tfloor(x), yf = tfloor(y);
        const T fx = x - xf, fy = y - yf;
        int64_t x0 = int64_t(xf) % map_w;
        if (x0 < 0) x0 += map_w;
        const int64_t x1 = (x0 + 1) % map_w;
        const int64_t y0 = int64_t(yf);
        const int64_t y1 = y0 + 1 < map_h ? y0 + 1 : y0;
        const T* r0 = map + y0 * map_w * 3;
        const T* r1 = map + y1 * map_w * 3;
        for (int c = 0; c < 3; ++c) {
          const T top = r0[x0 * 3 + c] * (T(1) - fx) + r0[x1 * 3 + c] * fx;
          const T bot = r1[x0 * 3 + c] * (T(1) - fx) + r1[x1 * 3 + c] * fx;
          L[c] = top * (T(1) - fy) + bot * fy;
        }
        return;
      }
      case kDisc: {
        const bool in = dot3(d, direction) >= cos_max;
        for (int c = 0; c < 3; ++c) L[c] = ambient[c] + (in ? radiance[c] : T(0));
        return;
      }
      default:
        for (int c = 0; c < 3; ++c) L[c] = radiance[c];
        return;
    }
  }
};

}  // namespace core
}  // namespace ta
