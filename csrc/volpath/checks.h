// The input checks of the entry points (the Python layer checks first; the C++ side checks again, so that nothing
// reaches the walk that could make it loop forever, read out of range or produce NaN). Messages name the argument,
// what was expected and what was received.
#pragma once

#include <torch/extension.h>

#include <cstdint>
#include <vector>

#include "volpath/volpath.h"

namespace ta {
namespace volpath {
namespace detail {

// Values of x in [lo, hi] (false for NaN), checked in parallel.
template <typename T>
void check_values(const torch::Tensor& x, const char* name, T lo, T hi);

// The scene's options for a D×H×W grid: sizes, scalars and each piece (boundary, sensor, emitter).
void check_scene(const SceneOptions& o, int64_t D, int64_t H, int64_t W);

// The four grids (one dtype, shape (3, D, H, W), contiguous CPU tensors), their values and the scene; with lanes 3
// (not hero) the sampling σ_t read as max(ref, sigma_t_floor) must be achromatic.
void check_all(const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
               const torch::Tensor& ref_albedo, const SceneOptions& opt, double sigma_t_floor = 0);

// The inputs of the palette forward: index (D, H, W) uint8 entries < P of the (3, P) tables, and the scene.
void check_palette(const torch::Tensor& index, const torch::Tensor& sigma_t_table, const torch::Tensor& albedo_table,
                   const SceneOptions& opt);

// The floors of the backward's sampling medium: sigma_t_floor finite >= 0, albedo_floor in [0, 1].
void check_floors(double sigma_t_floor, double albedo_floor);

// grad_output of the backward: a CPU tensor of sigma_t's dtype with `expected` elements (its values: check_finite).
void check_grad_output(const torch::Tensor& grad_output, const torch::Tensor& sigma_t, int64_t expected);

// Finite values of a contiguous tensor of dtype T.
template <typename T>
void check_finite(const torch::Tensor& x, const char* name);

}  // namespace detail
}  // namespace volpath
}  // namespace ta
