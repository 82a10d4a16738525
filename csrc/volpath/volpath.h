// Differentiable heterogeneous-volume path tracer (slab scenes, texel sensor): forward + radiative backpropagation.
//
// Scene: a grid of D×H×W voxels with edges voxel_size = (sx, sy, sz) mm occupying [0, W·sx]×[0, H·sy]×[0, D·sz]
// (x ↔ W, y ↔ H, z ↔ D). Piecewise-constant σ_t (mm⁻¹) and single-scattering albedo per voxel and RGB channel, Henyey–Greenstein
// phase g, index-matched (ior <= 0) or smooth-dielectric (ior >= 1) box boundary, uniform environment radiance.
// Texel sensor on face 0 = top (z = D·s), 1 = bottom (z = 0), 2 = both; texel [j, i] is voxel column (j, i).
//
// Tensors (CPU, contiguous, float32 or float64, all of one dtype):
//   sigma_t, albedo               (3, D, H, W)  the parameters θ
//   ref_sigma_t, ref_albedo       (3, D, H, W)  the sampling (reference) medium; paths are drawn from it and
//                                               weighted by f(θ)/p_ref when `ratio` is true. Must be > 0 wherever
//                                               the parameters are > 0 for the estimator to be unbiased.
//   grad_output                   (F, H, W, 3)  F = 1 (one face) or 2 (both faces)
// Scalars: environment (3 floats), spp >= 1, seed, max_depth >= 1 and rr_depth >= 0 (interactions: scatterings
// plus internal reflections), `lanes` 3 = one walk for all channels (requires an achromatic ref_sigma_t),
// 1 = one walk per channel.
#pragma once

#include <torch/extension.h>

#include <tuple>
#include <vector>

namespace ta {
namespace volpath {

struct TraceOptions {
  std::vector<double> voxel_size{1.0, 1.0, 1.0};  // voxel edges (x, y, z), mm
  int face = 0;
  double g = 0.0;
  double ior = -1.0;  // <= 0: index matched
  std::vector<double> environment{1.0, 1.0, 1.0};
  int64_t spp = 1;
  int64_t seed = 0;
  int64_t max_depth = 1;
  int64_t rr_depth = 0;
  int64_t lanes = 1;
};

struct ForwardCounts {
  int64_t scatter_events = 0;
  int64_t truncated_paths = 0;  // walks cut by max_depth (each channel's walk counts once)
};

// Returns (image (F, H, W, 3) or (H, W, 3) for one face, counts).
std::tuple<torch::Tensor, ForwardCounts> forward_cpu(const torch::Tensor& sigma_t, const torch::Tensor& albedo,
                                               const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo,
                                               bool ratio, const TraceOptions& opt);

// Path replay. Returns (grad_sigma_t or undefined, grad_albedo or undefined, scatter events of both replays).
std::tuple<torch::Tensor, torch::Tensor, int64_t> backward_cpu(
    const torch::Tensor& grad_output, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, bool need_sigma_t, bool need_albedo,
    const TraceOptions& opt);

}  // namespace volpath
}  // namespace ta
