// The object walk eight or sixteen paths at a time (AVX2, AVX-512): objects with an SDF boundary (boundary.h), seen
// by any sensor (surface texels, cameras) under any emitter, as a wavefront of independent walks, one per SIMD lane,
// as the slab walk (slab_simd.h) runs slabs. A lane walks one colour channel, or, where the sampling density is the
// same in the three channels (ObjectWalkScene::channels == 3, the scalar walk's LANES = 3), one path that serves all
// three, with a weight per channel.
//
// The lanes share what every path does at every step: the free flights through the voxels inside the object (the
// DDA, the homogeneous core's boxes of bricks crossed or collided in one move, where a flight crosses the surface in
// a mixed cell: SDFGrid::crossing in lanes), the flights' ratio weights and recorded segments, and the collisions
// (roulette, factors, recorded collisions, the new direction). What only some paths do, and rarely, each lane hands
// to the scalar steps of core::trace_path (compiled for the baseline instruction set by the glue,
// object_simd_glue.cpp), through the callbacks below:
//   start     begin_path and start_at_sensor, then outside the object up to its surface and into it (or escape);
//   surface   the surface (or the grid's box) reached from inside: Fresnel, reflection or refraction, and outside
//             the object up to its next surface point and into it, or escape (cross_from_inside, enter_from_outside).
// So each lane follows core::trace_path<float, LANES, kSDFBoundary, DIELECTRIC, RATIO, false, RECORD> step by step, on
// the same random numbers; what differs is the last bits of log, exp, sin and cos (the polynomials of simd_math.h,
// where trace_path calls libm), so a path may part from its scalar twin after many events, never in distribution.
// With `exact_math` the lanes call libm as the scalar walk does, and every path is the scalar walk's to the bit (a
// test mode: the tests compare the two walks path by path).
//
// Plain C++ (no torch, no std::), for the reason given in slab_simd.h.
#pragma once

#include <stdint.h>

#include "volpath/slab_simd.h"

namespace ta {
namespace simd {

// What a lane's path is after a scalar step.
enum LaneStatus : int32_t { kLaneInside = 0, kLaneEscaped = 1, kLaneTruncated = 2 };

// One lane's path state, as the scalar steps read and write it (core::PathState and PathResult): the weights of
// its channel in [0], or of the three channels.
struct ObjectLane {
  float p[3], d[3];        // grid-local position (mm) and unit direction
  int32_t idx[3];          // the voxel of p
  int32_t elem, sample, chan;  // chan: the channel, or 3 (the random stream of a walk of three channels)
  int32_t depth;           // interactions so far
  uint32_t event;          // the path's next random event
  float u1;                // the current flight's u1 (the Fresnel event where it ends at the surface)
  float u_fresnel;         // the first Fresnel event from outside (drawn with the start)
  int32_t fresh;           // no surface hit from outside yet
  float w[3], wref[3], prod[3];  // weight, reference weight, product of the non-zero factors
  int32_t zeros[3];              // exactly-zero factors
  int32_t status;          // out: LaneStatus
  float dir[3];            // out: the escape direction
  int64_t outside_steps;   // cells visited outside the object (added to)
};

// The scalar steps (the glue's): `ctx` is ObjectWalkScene::steps.
typedef void (*LaneStep)(void* ctx, ObjectLane& lane);
typedef void (*LaneSurface)(void* ctx, ObjectLane& lane, int32_t end, int32_t axis);  // end: core::FlightEnd

struct ObjectWalkScene {
  // channel-planar (3, D, H, W) float32 grids; the reference is read as max(ref, floor)
  const float* sigma_t = nullptr;
  const float* albedo = nullptr;
  const float* ref_sigma_t = nullptr;
  const float* ref_albedo = nullptr;
  float ref_sigma_t_floor = 0, ref_albedo_floor = 0;
  // or a palette medium (forward only; the grids above are null): voxel v holds entry index[v] of the channel-planar
  // (3, entries) tables, in the parameters and the reference alike (core::Channels)
  const uint8_t* index = nullptr;
  const float* sigma_t_table = nullptr;
  const float* albedo_table = nullptr;
  int32_t entries = 0;
  const uint8_t* cell = nullptr;  // (D, H, W) core::CellKind of the SDF
  const float* sdf = nullptr;     // (D+1, H+1, W+1) corner values (core::SDFGrid::sdf), < 2^31 of them
  // the homogeneous core (core::Medium::core), or none
  const uint8_t* core = nullptr;
  int32_t core_bricks[3] = {0, 0, 0};
  float core_sigma_t[3] = {0, 0, 0}, core_albedo[3] = {0, 0, 0};
  int32_t D = 0, H = 0, W = 0;  // 3·D·H·W < 2^31
  float voxel[3] = {1, 1, 1};
  float g = 0;
  // 1: a lane walks one channel; 3: one path serves the three channels (the reference σ_t is the same in the three,
  // and the walk samples its flights with channel 0's; dense grids only)
  int32_t channels = 1;
  uint64_t seed = 0;
  int64_t max_depth = 1, rr_depth = 0;
  int64_t spp = 1;
  bool exact_math = false;
  void* steps = nullptr;
  LaneStep start = nullptr;
  LaneSurface surface = nullptr;
};

// Walks every path of a batch as slab_walks_* do (same items, tapes, `ended_lanes` and callback), for an object.
// `elems` are sensor elements (< 2^31). WalkOut::direction holds the escape direction, and the counts are filled.
void object_walks_avx2(const ObjectWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                       const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx);
void object_walks_avx512(const ObjectWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                         const LaneTapes* tapes, int ended_lanes, WalkDone done, void* ctx);

}  // namespace simd
}  // namespace ta
