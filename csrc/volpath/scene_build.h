// Scene building: the SceneOptions of the entry points flattened into the torch-free core's Scene<T> (each piece
// into the core struct of the same name), with the converted tensors kept alive beside it.
#pragma once

#include <torch/extension.h>

#include <cstdint>
#include <vector>

#include "core/integrator.h"
#include "volpath/volpath.h"

namespace ta {
namespace volpath {
namespace detail {

// Keeps the converted tensors alive while a Scene<T> points into them.
struct SceneStorage {
  torch::Tensor sdf, points, normals, radius, map;
  std::vector<uint8_t> cells;
  std::vector<uint8_t> skip;  // brick distances of empty-space skipping (core::SDFGrid::skip)
  std::vector<uint8_t> core;  // brick distances of the homogeneous core (core::Medium::core)
};

// The brick distances of empty-space skipping (core::kBrick, core::SDFGrid::skip) of the (D, H, W) cell kinds:
// the exact Chebyshev distance in bricks to the nearest brick holding a cell that is not kCellOutside, capped at 255.
// Returns (⌈D/B⌉, ⌈H/B⌉, ⌈W/B⌉) values; `bricks` receives their counts along x, y, z.
std::vector<uint8_t> skip_distances(const uint8_t* cells, int64_t D, int64_t H, int64_t W, int64_t bricks[3]);

// The scene of a D×H×W grid without its medium values (the caller points S.medium's channels at them).
template <typename T>
core::Scene<T> make_scene(const SceneOptions& o, int64_t D, int64_t H, int64_t W, at::ScalarType dtype,
                          SceneStorage& store);

// The scene of the dense grids (3, D, H, W) (checked by check_all).
template <typename T>
core::Scene<T> make_scene(const SceneOptions& o, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
                          const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, SceneStorage& store);

// The scene of a palette volume: `index` (D, H, W) uint8 entries of the tables (P, 3) `sigma_t_table` and
// `albedo_table` (checked by check_palette), the parameters and the reference alike (plain weights), with its
// homogeneous core (build_core). The tensors must outlive the scene.
template <typename T>
core::Scene<T> make_palette_scene(const SceneOptions& o, const torch::Tensor& index, const torch::Tensor& sigma_t_table,
                                  const torch::Tensor& albedo_table, SceneStorage& store);

// The homogeneous core of an SDF scene's medium (core::Medium::core), once S.medium's channels are final: the bricks
// whose voxels all lie inside the object (kCellInside) and hold one tuple of values, σ_t and albedo of every channel,
// equal in the parameters and the reference, finite, σ_t > 0: the tuple that most such bricks hold. In a gradient
// replay `asked` (D, H, W), the voxels whose gradients are returned, keeps its bricks out of the core. Leaves the
// medium without a core when no brick qualifies, for box scenes, or when switched off (set_core_walk).
template <typename T>
void build_core(core::Scene<T>& S, SceneStorage& store, const bool* asked);

// The image's shape: (F, H, W, 3)/(H, W, 3) for face texels, (N, 3) for surface texels, (rows, cols, 3) for cameras.
std::vector<int64_t> image_shape(const SceneOptions& o, int64_t H, int64_t W);

}  // namespace detail
}  // namespace volpath
}  // namespace ta
