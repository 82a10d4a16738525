// SIMD glue: the SIMD walks (eight or sixteen paths per thread at once) where the scene allows them: the slab walk
// (slab_simd.h: box boundary, face texels) and the object walk (object_simd.h: SDF boundary, any sensor and emitter;
// object_simd_glue.cpp). Which walk runs (the CPU, TA_SIMD, set_simd), whether it serves a scene, and its forward and
// replay of one chunk of sensor elements, with the same per-element sums and the same deposits as the scalar
// kernels.
#pragma once

#include <cstdint>
#include <type_traits>
#include <vector>

#include "core/integrator.h"
#include "volpath/slab_simd.h"
#include "volpath/replay.h"
#include "volpath/threading.h"
#include "volpath/volpath.h"

namespace ta {
namespace volpath {
namespace detail {

// The widest SIMD walk this CPU runs: 2 AVX-512F, 1 AVX2, 0 none.
int cpu_simd_level();
// The walk in use: 0 scalar, 1 AVX2, 2 AVX-512 (the CPU and TA_SIMD decide at first use; set_simd overrides).
int simd_level();
inline bool simd_enabled() { return simd_level() > 0; }

// Whether the SIMD slab walk serves this scene: float32 dense grids, box boundary, face texels, constant emitter.
template <typename T, int LANES, int B, bool HERO>
bool simd_serves(const core::Scene<T>& S) {
  if constexpr (!std::is_same_v<T, float> || LANES != 1 || B != core::kBoxBoundary || HERO) {
    return false;
  } else {
    const auto& M = S.medium;
    return simd_enabled() && S.sensor.kind == core::kFaceTexels && S.emitter.kind == core::kConstant &&
           M.sigma_t.index == nullptr && M.albedo.index == nullptr && M.ref_sigma_t.index == nullptr &&
           M.ref_albedo.index == nullptr && M.sigma_t.plain && M.albedo.plain && 3 * M.voxels() < (int64_t(1) << 31);
  }
}

constexpr int64_t kSimdBatch = 256;                 // sensor elements per call of a SIMD walk
constexpr int64_t kSimdSegments = int64_t(1) << 16;  // tape entries per lane (longer paths: scalar replay)
static_assert(kSimdSegments <= simd::kMaxTapeCap, "the SIMD walks' tape offsets are int32");

// TA_SIMD_ENDED_LANES: flights that end before a SIMD walk's collision phase runs (0: its default); for tuning.
int simd_ended_lanes();

// core::deposit_tape<float, 1> for a SIMD walk's compact tape: the deposits of the path `o` of channel ch.
void deposit_simd_tape(const simd::WalkOut& o, int ch, float adj, const core::Adjoint<float>& A, int64_t N);

// The image of a batch of n elements from each path's term by item ((k·spp + sample)·3 + channel), summed in sample
// order as the scalar kernel adds them.
void write_batch_image(const core::Scene<float>& S, const int64_t* elems, int64_t n, const std::vector<double>& values,
                       float* out);

// Whether the SIMD object walk (object_simd.h) serves this scene: float32 dense grids (the reference may be floored)
// or one palette medium (a quantised print's forward), an SDF boundary, one walk per channel (not hero), no tally.
template <typename T, int LANES, int B, bool HERO>
bool simd_serves_object(const core::Scene<T>& S) {
  if constexpr (!std::is_same_v<T, float> || LANES != 1 || B != core::kSDFBoundary || HERO) {
    return false;
  } else {
    const auto& M = S.medium;
    const bool dense = M.sigma_t.index == nullptr && M.albedo.index == nullptr && M.ref_sigma_t.index == nullptr &&
                       M.ref_albedo.index == nullptr && M.sigma_t.plain && M.albedo.plain;
    const bool palette = M.sigma_t.index != nullptr && M.albedo.index == M.sigma_t.index &&
                         M.ref_sigma_t.index == M.sigma_t.index && M.ref_albedo.index == M.sigma_t.index &&
                         M.ref_sigma_t.palette == M.sigma_t.palette && M.ref_albedo.palette == M.albedo.palette &&
                         M.sigma_t.entries == M.albedo.entries && M.sigma_t.entries <= 256;
    return simd_enabled() && S.tally == nullptr && S.sdf.cell != nullptr && (dense || palette) &&
           3 * M.voxels() < (int64_t(1) << 31) && S.elements() < (int64_t(1) << 31) &&
           (M.D + 1) * (M.H + 1) * (M.W + 1) < (int64_t(1) << 31);
  }
}

// Forward and gradient replay of chunk c with the SIMD object walk, as simd_forward_chunk and simd_backward_chunk
// (which they follow for an object: the sensor's elements in strided blocks, any emitter; ForwardCounts in full).
template <bool DIEL, bool RATIO>
ForwardCounts simd_object_forward_chunk(const core::Scene<float>& S, float* out, int64_t c, int64_t nchunks,
                                        const Share& share);
template <bool DIEL>
int64_t simd_object_backward_chunk(const core::Scene<float>& S, const float* grad_out, const core::Adjoint<float>& A,
                                   TapeStore<float, 1>& store, int64_t c, int64_t nchunks, const Share& share,
                                   float* image, int64_t* cut);

// The reference σ_t and albedo side by side, voxel by voxel (SlabWalkScene::ref_pair), for the SIMD walk.
std::vector<float> pack_reference(const core::Scene<float>& S);

// Forward of chunk c with the SIMD walk: per batch of elements, every path's value, then the per-element sums in
// sample order (as the scalar kernel adds them, so the image does not depend on the order the lanes finish in).
template <bool DIEL, bool RATIO>
ForwardCounts simd_forward_chunk(const core::Scene<float>& S, const float* ref_pair, float* out, int64_t c,
                                 int64_t nchunks, const Share& share);

// Gradient replay of chunk c with the SIMD walk: the lanes record their paths' tapes, and each path is deposited
// when it ends; a path longer than its lane's tape is replayed by the scalar code from the start (walk and deposit),
// so every deposit belongs to the walk that produced its weight. With `image` (not null) every channel is walked and
// the elements' image of these walks is written as simd_forward_chunk writes it (scene_forward_backward); `cut`
// takes the truncated walks. Returns the scatter events.
template <bool DIEL>
int64_t simd_backward_chunk(const core::Scene<float>& S, const float* ref_pair, const float* grad_out,
                            const core::Adjoint<float>& A, TapeStore<float, 1>& store, int64_t c, int64_t nchunks,
                            const Share& share, float* image, int64_t* cut);

}  // namespace detail
}  // namespace volpath
}  // namespace ta
