// The medium: a D×H×W grid of piecewise-constant voxels placed in world space, per-channel σ_t (mm⁻¹) and
// single-scattering albedo, channel-planar (3, D, H, W). ref_* is the detached sampling (reference) medium that
// paths are drawn from; the walk carries the ratio weights f(θ)/p_ref when it differs from the parameters.
#pragma once

#include "core/defs.h"

namespace ta {
namespace core {

template <typename T>
struct Medium {
  int64_t D = 0, H = 0, W = 0;  // grid size (z, y, x)
  T voxel[3] = {1, 1, 1};       // voxel edges along x, y, z in mm (anisotropic printers: 600×300×940 DPI)
  T origin[3] = {0, 0, 0};      // world position (mm) of the grid corner; voxel (k, j, i) spans
                                // origin + [i, i+1]·sx × [j, j+1]·sy × [k, k+1]·sz
  const T* sigma_t = nullptr;
  const T* albedo = nullptr;
  const T* ref_sigma_t = nullptr;
  const T* ref_albedo = nullptr;

  TA_HD int64_t voxels() const { return D * H * W; }
  TA_HD int64_t dim(int a) const { return a == 0 ? W : (a == 1 ? H : D); }
  TA_HD T extent(int a) const { return T(dim(a)) * voxel[a]; }
  TA_HD int64_t index(const int64_t idx[3]) const { return (idx[2] * H + idx[1]) * W + idx[0]; }
  // Voxel containing the grid-local point p (mm), clamped to the grid.
  TA_HD void locate(const T p[3], int64_t idx[3]) const {
    for (int a = 0; a < 3; ++a) {
      const T f = tfloor(p[a] / voxel[a]);
      const int64_t n = dim(a);
      idx[a] = f >= T(0) ? (f < T(n) ? int64_t(f) : n - 1) : 0;  // NaN → 0: never an index out of range
    }
  }
};

// Where the adjoint goes (chunk-local buffers, channel-planar like the grids); null when not requested.
template <typename T>
struct Adjoint {
  T* grad_sigma_t = nullptr;
  T* grad_albedo = nullptr;
};

}  // namespace core
}  // namespace ta
