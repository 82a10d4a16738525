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

// Bricks of kBrick³ voxels: the unit of empty-space skipping outside an object (boundary.h) and of the homogeneous
// core inside it (Medium::core). A brick grid holds one byte per brick, (⌈D/4⌉, ⌈H/4⌉, ⌈W/4⌉), x fastest.
constexpr int64_t kBrick = 4;

// Flat index in a brick grid of `bricks` = (x, y, z) counts of the brick holding voxel idx.
TA_HD TA_INLINE int64_t brick_index(const int64_t bricks[3], const int64_t idx[3]) {
  return ((idx[2] / kBrick) * bricks[1] + idx[1] / kBrick) * bricks[0] + idx[0] / kBrick;
}

template <typename T>
struct Medium {
  int64_t D = 0, H = 0, W = 0;  // grid size (z, y, x)
  T voxel[3] = {1, 1, 1};       // voxel edges along x, y, z in mm (anisotropic printers: 600×300×940 DPI)
  T origin[3] = {0, 0, 0};      // world position (mm) of the grid corner; voxel (k, j, i) spans
                                // origin + [i, i+1]·sx × [j, j+1]·sy × [k, k+1]·sz
  Channels<T> sigma_t, albedo, ref_sigma_t, ref_albedo;
  // The homogeneous core (objects; set by the glue, else absent): per brick the Chebyshev distance in bricks to the
  // nearest brick that is not core (0: not core; capped at 255). Every voxel of a core brick lies inside the object
  // and holds core_sigma_t and core_albedo in the parameters and in the reference alike (no ratio weights), and in a
  // gradient replay lies outside the voxels whose gradients are asked for. A walk crosses a box of core bricks in
  // one move and reads the core's values without touching the grids (integrator.h).
  const uint8_t* core = nullptr;
  int64_t core_bricks[3] = {0, 0, 0};
  T core_sigma_t[3] = {0, 0, 0}, core_albedo[3] = {0, 0, 0};
  // The core distance of voxel idx (0 without a core).
  TA_HD TA_INLINE int core_distance(const int64_t idx[3]) const {
    return core == nullptr ? 0 : core[brick_index(core_bricks, idx)];
  }

  TA_HD int64_t voxels() const { return D * H * W; }
  TA_HD int64_t dim(int a) const { return a == 0 ? W : (a == 1 ? H : D); }
  TA_HD T extent(int a) const { return T(dim(a)) * voxel[a]; }
  TA_HD int64_t index(const int64_t idx[3]) const { return (idx[2] * H + idx[1]) * W + idx[0]; }
  // Voxel containing the grid-local point p (mm), clamped to the grid.
  TA_HD TA_INLINE void locate(const T p[3], int64_t idx[3]) const {
    for (int a = 0; a < 3; ++a) {
      // floor(q) by truncation where q is in [0, n) (no call to floorf: x86-64 without SSE4.1 has no instruction)
      const T q = p[a] / voxel[a];
      const int64_t n = dim(a);
      idx[a] = q >= T(0) ? (q < T(n) ? int64_t(q) : n - 1) : 0;  // NaN → 0: never an index out of range
    }
  }
};

}  // namespace core
}  // namespace ta
