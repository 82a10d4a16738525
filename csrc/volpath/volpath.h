// Differentiable heterogeneous-volume path tracer: forward + radiative backpropagation (path replay).
//
// One pair of entry points over one core (csrc/core/integrator.h), for every scene (render_scene; render_texels
// builds the slab scene: box boundary, face texels, constant environment):
//
//   scene_forward_cpu / scene_backward_cpu  the scene's pieces in SceneOptions (one struct per piece, flattened
//                                           from the Python dataclass of the same role).
//   scene_forward_indexed_cpu               the forward of a palette medium (a quantised print).
//
// Files, one concern each (as nvdiffrast keeps one glue file per concern; the torch-free core is csrc/core/):
//   checks.{h,cpp}          the input checks (TORCH_CHECK messages naming the argument, expected and received)
//   scene_build.{h,cpp}     SceneOptions flattened into core::Scene<T>, the converted tensors kept alive
//   threading.h             the static work split over threads, the process's share, per-chunk gradient buffers
//                           and their reduction in chunk order (deterministic for a given thread count)
//   simd_glue.{h,cpp}       the SIMD slab walk (slab_simd.h): which width runs, whether it serves a scene, its chunks
//   replay.h                the scalar path replay of one path (tape, or the two-pass fallback)
//   dispatch.h              runtime scene flags → template instance
//   forward_cpu.cpp         the forward kernel and scene_forward_cpu, scene_forward_indexed_cpu
//   backward_cpu.cpp        the backward kernel and scene_backward_cpu (forward and backward compile in parallel)
//
// Medium: a grid of D×H×W voxels with edges voxel_size = (sx, sy, sz) mm occupying
// origin + [0, W·sx]×[0, H·sy]×[0, D·sz] (x ↔ W, y ↔ H, z ↔ D). Piecewise-constant σ_t (mm⁻¹) and single-scattering
// albedo per voxel and RGB channel, Henyey–Greenstein phase g.
//
// Tensors (CPU, contiguous, float32 or float64, all of one dtype):
//   sigma_t, albedo               (3, D, H, W)  the parameters θ
//   ref_sigma_t, ref_albedo       (3, D, H, W)  the sampling (reference) medium; paths are drawn from it and
//                                               weighted by f(θ)/p_ref when `ratio` is true. Must be > 0 wherever
//                                               the parameters are > 0 for the estimator to be unbiased.
//   grad_output                   the shape of the forward's image
// Scalars: spp >= 1, seed, max_depth >= 1 and rr_depth >= 0 (interactions: scatterings plus internal
// reflections; SDF boundaries also count crossings), `lanes` 3 = one walk for all channels (requires an achromatic
// ref_sigma_t unless `hero`), 1 = one walk per channel; `hero` = 1 (with lanes 3): one walk for all channels of a
// chromatic ref_sigma_t, distances sampled with a hero channel's density and weighted by the balance heuristic
// over the channels (core/integrator.h, HERO).
#pragma once

#include <torch/extension.h>

#include <string>
#include <tuple>
#include <utility>
#include <vector>

namespace ta {
namespace volpath {

// ---- general scenes: one struct per piece, flattened from the Python dataclass of the same role
struct BoundaryOptions {
  int kind = 0;        // 0 box, 1 signed-distance grid
  double ior = -1.0;   // <= 0: index matched, else smooth dielectric (>= 1)
  torch::Tensor sdf;   // kind 1: (D+1, H+1, W+1) mm at voxel corners, < 0 inside, > 0 on the grid's outer corners
};

struct SensorOptions {
  int kind = 0;  // 0 face texels, 1 surface texels, 2 orthographic camera, 3 perspective camera
  int face = 0;  // kind 0: 0 top, 1 bottom, 2 both
  torch::Tensor points, normals, radius;  // kind 1: (N, 3) mm, (N, 3) unit, (N,) mm
  double lift = 0.0;                      // kind 1: start offset along the normal, mm
  std::vector<double> origin{0, 0, 0}, forward{0, 0, -1}, right{1, 0, 0}, up{0, 1, 0};  // cameras (orthonormal)
  int64_t rows = 0, cols = 0;
  double width = 0.0, height = 0.0;  // kind 2: mm
  double tan_half_fov = 0.0;         // kind 3
};

struct EmitterOptions {
  int kind = 0;  // 0 constant, 1 lat-long environment map, 2 distant disc light (+ ambient)
  std::vector<double> radiance{1, 1, 1}, ambient{0, 0, 0}, direction{0, 0, 1};
  double cos_max = 1.0;
  torch::Tensor map;  // kind 1: (Hm, Wm, 3) linear RGB
};

struct SceneOptions {
  std::vector<double> voxel_size{1.0, 1.0, 1.0};
  std::vector<double> origin{0.0, 0.0, 0.0};
  double g = 0.0;
  BoundaryOptions boundary;
  SensorOptions sensor;
  EmitterOptions emitter;
  int64_t spp = 1;
  int64_t seed = 0;
  int64_t max_depth = 1;
  int64_t rr_depth = 0;
  int64_t lanes = 1;
  int64_t hero = 0;        // 1 (with lanes 3): one hero-channel walk with spectral MIS serves a chromatic reference
  int64_t part_rank = 0;   // data-parallel share: this process traces the sensor elements t with
  int64_t part_world = 1;  // t % part_world == part_rank (others: 0 in the image, no gradient); the random
                           // numbers are keyed by the global t, so the shares of all ranks sum to the full image
  // optional (D, H, W) bool: the voxels whose gradients the backward returns (0 elsewhere), so that the replay may
  // cross the homogeneous core without gradient bookkeeping (core::Medium::core); undefined: every voxel's
  torch::Tensor grad_support;
};

struct ForwardCounts {
  int64_t scatter_events = 0;
  int64_t truncated_paths = 0;  // walks cut by max_depth (each channel's walk counts once)
  // the voxel visits of the scalar and the SIMD object walks (the SIMD slab walk leaves them 0): by the free flights
  // inside the object, and outside it in the search for the surface
  int64_t voxel_steps = 0;
  int64_t outside_steps = 0;
  int64_t core_events = 0;  // scattering events in the homogeneous core (core::Medium::core)
  // with set_tally: per bin b of its labels, tally[2b] scattering events and tally[2b + 1] voxel moves
  std::vector<int64_t> tally;
};

// General scenes. The image is (F, H, W, 3)/(H, W, 3) for face texels, (N, 3) for surface texels,
// (rows, cols, 3) for cameras.
std::tuple<torch::Tensor, ForwardCounts> scene_forward_cpu(const torch::Tensor& sigma_t, const torch::Tensor& albedo,
                                                           const torch::Tensor& ref_sigma_t,
                                                           const torch::Tensor& ref_albedo, bool ratio,
                                                           const SceneOptions& opt);

// sigma_t_floor, albedo_floor: the replay samples max(ref, floor) (read on the fly: no floored copy of the grids).
std::tuple<torch::Tensor, torch::Tensor, int64_t> scene_backward_cpu(
    const torch::Tensor& grad_output, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, bool need_sigma_t, bool need_albedo,
    const SceneOptions& opt, double sigma_t_floor, double albedo_floor);

// The image and the replay of one set of walks, for a grad_output (the adjoint) known before the render, e.g. a loss's
// gradient taken at a running mean of past renders: each walk samples the replay's medium max(ref, floor) with
// the options' seed, adds its term to the image and deposits its derivative, so forward and backward cost one walk.
// The image is that of scene_forward_cpu(ratio = true) with the floored reference and the same seed (bitwise on the
// scalar walk); the gradients those of scene_backward_cpu. Every channel is walked (grad_output may hold zeros).
// Returns (image, grad_sigma_t, grad_albedo, counts: scatter events of the walks, truncated walks).
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, ForwardCounts> scene_forward_backward_cpu(
    const torch::Tensor& grad_output, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, bool need_sigma_t, bool need_albedo,
    const SceneOptions& opt, double sigma_t_floor, double albedo_floor);

// Forward only, of a palette medium: index (D, H, W) uint8 entries of the (3, P) tables sigma_t_table and
// albedo_table (a quantised print: one byte per voxel instead of 2 × 3 values). Equals scene_forward_cpu of the
// dense grids table[:, index] (paths sampled from the medium itself, no ratio weights).
std::tuple<torch::Tensor, ForwardCounts> scene_forward_indexed_cpu(const torch::Tensor& index,
                                                                   const torch::Tensor& sigma_t_table,
                                                                   const torch::Tensor& albedo_table,
                                                                   const SceneOptions& opt);

// ---- another device (scene_device.cpp; the CUDA launcher, torch_appearance/render/cuda_launch.py): the scene of a
// render built on the host as the CPU entry points build it, relocated (relocate.h) into tensors on `device`.
// Returns (the bytes of the core::Scene<T>: a CPU uint8 tensor of sizeof(Scene<T>), the tensors its pointers point
// into: keep them alive while the scene is used). Grids already on `device` are used in place; the scene's own
// tensors (SDF, texels, map) are copied there. `replay`: the gradient replay's scene (the sampling medium
// max(ref, floor), the homogeneous core outside grad_support's voxels, as scene_backward_cpu); else the forward's.
std::tuple<torch::Tensor, std::vector<torch::Tensor>> scene_to_device(
    const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
    const torch::Tensor& ref_albedo, const SceneOptions& opt, double sigma_t_floor, double albedo_floor, bool replay,
    const torch::Device& device);
// The palette medium's scene (as scene_forward_indexed_cpu's) on `device`.
std::tuple<torch::Tensor, std::vector<torch::Tensor>> scene_to_device_indexed(const torch::Tensor& index,
                                                                              const torch::Tensor& sigma_t_table,
                                                                              const torch::Tensor& albedo_table,
                                                                              const SceneOptions& opt,
                                                                              const torch::Device& device);
// Test-only: scene_to_device on the CPU with every buffer copied (the grids too), then every original buffer
// overwritten with poison (relocate.h; the caller's grids too, the options' tensors are copied first) and kept alive
// in the returned list; `skip` names one pointer member left pointing at its (poisoned) original.
std::tuple<torch::Tensor, std::vector<torch::Tensor>> relocate_scene_for_test(
    const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
    const torch::Tensor& ref_albedo, const SceneOptions& opt, bool replay, double sigma_t_floor, double albedo_floor,
    const std::string& skip);
// Test-only: the forward of scene_forward_cpu over a scene given as its bytes (a relocated scene whose pointers are
// host memory): the kernel configuration of `opt` (lanes, hero, boundary, optics) and `ratio`, the image of the
// scene's grid, the share of opt.part_rank / part_world.
std::tuple<torch::Tensor, ForwardCounts> scene_forward_from_bytes_cpu(const torch::Tensor& scene_bytes,
                                                                      at::ScalarType dtype, bool ratio,
                                                                      const SceneOptions& opt);
// The layout of core::Scene<T> on this host: its size and alignment, the byte offsets of its pointer members
// (relocate.h's names) and of a few other members, for a check that the CUDA compiler lays it out alike.
struct SceneLayout {
  int64_t size = 0, align = 0;
  std::vector<std::pair<std::string, int64_t>> pointers, fields;
};
SceneLayout scene_layout(at::ScalarType dtype);

// Test-only: the initial per-thread tape capacity of the replay (segments; collisions get half). 0 makes every path
// take the two-pass fallback, so tests can compare both replays. Returns the previous value.
int64_t set_tape_capacity(int64_t segments);
// Test-only: whether SDF scenes skip empty space outside the object in bricks (core::SDFGrid::skip; default on).
// Returns the previous setting.
bool set_empty_space_skipping(bool on);
// Test-only: whether SDF scenes cross their homogeneous core in bricks (core::Medium::core; default on). Returns the
// previous setting.
bool set_core_walk(bool on);
// Diagnostics: a (D, H, W) uint8 tensor of bins (or an undefined tensor: off) by which the scalar walk of the
// next forward passes counts its scattering events and voxel moves (ForwardCounts::tally; the SIMD slab walk
// counts nothing). The forward refuses a grid of another shape.
void set_tally(const torch::Tensor& bins);
// The SIMD walks (slab_simd.h, object_simd.h): -1 automatic (the CPU's widest, TA_SIMD), 0 scalar, 1 AVX2,
// 2 AVX-512; returns the level before.
int64_t set_simd(int64_t mode);
// Whether the SIMD object walk calls libm per lane (the scalar walk's log, exp, sin and cos: every path the scalar
// one, for tests) instead of its polynomials; returns the previous setting.
bool set_simd_exact_math(bool on);

}  // namespace volpath
}  // namespace ta
