// The slab walk eight or sixteen paths at a time (AVX2, AVX-512): the hot loop of print optimisation on slabs (box
// boundary, face texels, one walk per colour channel, constant environment) as a wavefront of independent walks, one
// per SIMD lane. A lane whose path ends takes the next path of its batch, so the lanes stay busy while paths differ
// in length. The walk is written once (slab_simd_walk.h) and compiled per instruction set.
//
// Same estimator, same random numbers (Philox4x32-10 keyed as in core/rng.h, counter (element, sample, channel,
// event)) and the same event order as core::trace_path<float, 1, kBoxBoundary, ...>; what differs is the last bits of
// log, sin and cos (polynomials here, libm there), so a path may part from its scalar twin after many events, never
// in distribution; the two widths give the same bits. Selected at run time by the CPU (AVX-512F, else AVX2) and
// TA_SIMD (0 off, avx2 at most AVX2); otherwise the scalar walk runs.
//
// This header is plain C++ (no torch, no std::): the SIMD translation units include nothing that could be
// instantiated there and linked into scalar code.
#pragma once

#include <stdint.h>

namespace ta {
namespace simd {

// One channel-planar (3, D, H, W) float32 grid pair and the reference (sampling) pair read as max(ref, floor). The walk
// reads the reference through ref_pair; the planar pointers tell it whether the reference is the medium itself.
struct SlabWalkScene {
  const float* sigma_t = nullptr;
  const float* albedo = nullptr;
  const float* ref_sigma_t = nullptr;
  const float* ref_albedo = nullptr;
  // the reference pair voxel by voxel, (3·D·H·W, 2) = (ref_sigma_t, ref_albedo) side by side (not floored): the
  // walk reads it, so a collision's albedo lies in the cache line of the σ_t that its flight just read
  const float* ref_pair = nullptr;
  float ref_sigma_t_floor = 0, ref_albedo_floor = 0;
  int32_t D = 0, H = 0, W = 0;  // 3·D·H·W < 2^31
  float voxel[3] = {1, 1, 1};   // x, y, z edges (mm)
  float g = 0;                  // Henyey–Greenstein
  float ior = 1;                // with dielectric
  bool dielectric = false;
  int face = 0;                 // 0 top, 1 bottom, 2 both
  uint64_t seed = 0;
  int64_t max_depth = 1, rr_depth = 0;
  int64_t spp = 1;
};

// The recording walk's tape, compact (the sixteen lanes' tapes share the first-level cache with the grid): a segment
// of a flight in one voxel, and a collision with the segments before it (seg_end) and its factors, as in core/tape.h.
struct TapeSegmentF {
  int32_t v;  // voxel within the channel plane
  float len;
};
struct TapeCollisionF {
  int32_t v;
  int32_t seg_end;
  float sref, inv_psq, fs, fa;
};
// a collision of a walk that serves the three channels at once (the object walk with three channels per lane), the
// fields of core::TapeCollision<float, 3>
struct TapeCollision3F {
  int32_t v;
  int32_t seg_end;
  float sref, inv_psq, fs[3], fa[3];
};

// Room for the tapes of every lane (kMaxLanes × (cap + 1) entries of each kind), owned by the caller and reused from
// call to call: lane l's tape starts at l·(cap + 1); the extra entry per lane takes the writes of a full tape.
// The walk addresses the entries with int32 lane offsets: caps at most kMaxTapeCap (3 · 16 · (2^20 + 1) < 2^31).
constexpr int kMaxLanes = 16;
constexpr int64_t kMaxTapeCap = int64_t(1) << 20;
struct LaneTapes {
  TapeSegmentF* segs = nullptr;
  TapeCollisionF* cols = nullptr;    // one channel per lane
  TapeCollision3F* cols3 = nullptr;  // three channels per lane (the object walk's ObjectWalkScene::channels == 3)
  int64_t seg_cap = 0, col_cap = 0;
};

// A finished path. `item` = (k·spp + sample)·3 + channel for the k-th element of the batch; a path that serves the
// three channels (channels == 3) has channel 0 in its item and a value per channel.
struct WalkOut {
  int64_t item;
  int32_t channels = 1;   // 1: the channel of `item`, in [0]; 3: channels 0, 1, 2
  float value[3];         // V / L_e (0 unless escaped)
  float prod_nonzero[3];  // product of the non-zero factors (RATIO)
  int32_t zeros[3];       // exactly-zero factors (RATIO)
  bool escaped, truncated;
  int64_t scatter_events;
  // RECORD: the path's tape (valid during the callback), overflow when it did not fit; cols3 for three channels
  const TapeSegmentF* segs;
  const TapeCollisionF* cols;
  const TapeCollision3F* cols3 = nullptr;
  int64_t nseg, ncol;
  bool overflow;
  // the object walk's (object_simd.h) escape direction and counts; the slab walk leaves them as they are
  float direction[3] = {0, 0, 0};
  int64_t voxel_steps = 0, outside_steps = 0, core_events = 0;
};

typedef void (*WalkDone)(void* ctx, const WalkOut& out);

// Walks every path of a batch (call only on a CPU with the instruction set; simd_glue.cpp checks): for each
// element k < n of `elems` (flat texel index, < 2^32) and sample s < spp, the channels whose bit is set in live[k]
// (all three when live is null). `ratio`: weights f/p_ref (the replay); `tapes` (not null: implies ratio): record
// each path's tape for the replay's deposit (a path with more than the caps is reported with `overflow`).
// `ended_lanes`: the collision phase runs once this many lanes have ended their flights (0: three quarters of the
// lanes; a tuning knob, the paths do not depend on it). Calls done() once per path, in the order the paths end.
void slab_walks_avx2(const SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                     const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx);
void slab_walks_avx512(const SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                       const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx);

}  // namespace simd
}  // namespace ta
