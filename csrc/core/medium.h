// The medium: a D×H×W grid of piecewise-constant voxels placed in world space, per-channel σ_t (mm⁻¹) and
// single-scattering albedo, channel-planar (3, D, H, W). ref_* is the detached sampling (reference) medium that
// paths are drawn from; the walk carries the ratio weights f(θ)/p_ref when it differs from the parameters.
#pragma once

#include "core/defs.h"

namespace ta {
namespace core {

// Per-channel values of the grid, channel-planar (3, D, H, W), read as x[c * N + v] (N voxels): a dense array
// (floored at `floor`, so that the sampling medium of the replay, max(σ_t, floor), needs no copy of the grid), or a
// (D, H, W) byte index into a (3, P) palette (a quantised print: one byte per voxel instead of 3 values).
template <typename T>
struct Channels {
  const T* data = nullptr;         // dense (3, D, H, W)
  T floor = T(0);                  // dense values read as max(data, floor); 0 leaves the (non-negative) data as is
  const uint8_t* index = nullptr;  // or: palette entry of each voxel
  const T* palette = nullptr;      // (3, P) channel-planar palette
  int64_t voxels = 0, entries = 0;  // N, P
  bool plain = true;               // dense and not floored: read as is (the common, fast path)
  Channels() = default;
  TA_HD Channels(const T* dense) : data(dense) {}  // NOLINT(google-explicit-constructor): a plain grid pointer
  TA_HD TA_INLINE T operator[](int64_t i) const {
    if (plain) return data[i];
    if (index == nullptr) return tmax(data[i], floor);
    const int64_t c = i / voxels;
    return palette[c * entries + index[i - c * voxels]];
  }
};

template <typename T>
struct Medium {
  int64_t D = 0, H = 0, W = 0;  // grid size (z, y, x)
  T voxel[3] = {1, 1, 1};       // voxel edges along x, y, z in mm (anisotropic printers: 600×300×940 DPI)
  T origin[3] = {0, 0, 0};      // world position (mm) of the grid corner; voxel (k, j, i) spans
                                // origin + [i, i+1]·sx × [j, j+1]·sy × [k, k+1]·sz
  Channels<T> sigma_t, albedo, ref_sigma_t, ref_albedo;

  TA_HD int64_t voxels() const { return D * H * W; }
  TA_HD int64_t dim(int a) const { return a == 0 ? W : (a == 1 ? H : D); }
  TA_HD T extent(int a) const { return T(dim(a)) * voxel[a]; }
  TA_HD int64_t index(const int64_t idx[3]) const { return (idx[2] * H + idx[1]) * W + idx[0]; }
  // Voxel containing the grid-local point p (mm), clamped to the grid.
  TA_HD TA_INLINE void locate(const T p[3], int64_t idx[3]) const {
    for (int a = 0; a < 3; ++a) {
      const T f = tfloor(p[a] / voxel[a]);
      const int64_t n = dim(a);
      idx[a] = f >= T(0) ? (f < T(n) ? int64_t(f) : n - 1) : 0;  // NaN → 0: never an index out of range
    }
  }
};

}  // namespace core
}  // namespace ta
