// SIMD glue for objects (simd_glue.h): the scalar steps that the SIMD object walk (object_simd.h) hands its lanes
// to, the walk's scene, and its forward and replay of one chunk of sensor elements. Compiled for the baseline
// instruction set, so the scalar steps are the very functions of core::trace_path.
#include <ATen/Parallel.h>

#include <atomic>
#include <memory>
#include <vector>

#include "core/integrator.h"
#include "volpath/object_simd.h"
#include "volpath/replay.h"
#include "volpath/simd_glue.h"

namespace ta {
namespace volpath {
namespace detail {

std::atomic<bool> g_simd_exact_math{false};  // set_simd_exact_math (tests)

namespace {

using core::Adjoint;
using core::PathResult;
using core::PathState;
using core::Scene;

// A lane's state as the scalar walk's (one channel, or three in one walk; not hero).
template <int LANES>
void load_lane(const Scene<float>& S, const simd::ObjectLane& o, PathState<float, LANES>& st,
               PathResult<float, LANES>& res) {
  for (int a = 0; a < 3; ++a) {
    st.p[a] = o.p[a];
    st.d[a] = o.d[a];
    st.idx[a] = o.idx[a];
    res.direction[a] = 0.0f;
  }
  st.inside = true;
  st.ch0 = LANES == 1 ? o.chan : 0;
  st.depth = o.depth;
  st.rng = core::PathRng<float>{S.seed, uint32_t(o.elem), uint32_t(o.sample), uint32_t(o.chan)};
  st.event = o.event;
  st.u[0] = st.u[2] = st.u[3] = 0.0f;
  st.u[1] = o.u1;
  st.u_fresnel = o.u_fresnel;
  st.fresh = o.fresh != 0;
  for (int l = 0; l < LANES; ++l) {
    st.w[l] = o.w[l];
    st.wref[l] = o.wref[l];
    res.value[l] = 0.0f;
    res.prod_nonzero[l] = o.prod[l];
    res.zeros[l] = o.zeros[l];
  }
}

template <int LANES>
void store_lane(const PathState<float, LANES>& st, const PathResult<float, LANES>& res, bool alive,
                simd::ObjectLane& o) {
  for (int a = 0; a < 3; ++a) {
    o.p[a] = st.p[a];
    o.d[a] = st.d[a];
    o.idx[a] = int32_t(st.idx[a]);
    o.dir[a] = res.direction[a];
  }
  o.depth = int32_t(st.depth);
  o.event = st.event;
  o.u_fresnel = st.u_fresnel;
  o.fresh = st.fresh;
  for (int l = 0; l < LANES; ++l) {
    o.w[l] = st.w[l];
    o.wref[l] = st.wref[l];
    o.prod[l] = res.prod_nonzero[l];
    o.zeros[l] = res.zeros[l];
  }
  o.outside_steps += res.outside_steps;
  o.status = alive ? simd::kLaneInside : (res.escaped ? simd::kLaneEscaped : simd::kLaneTruncated);
}

// Outside the object until the walk is inside it again (true) or has ended.
template <bool DIEL, int LANES>
bool into_object(const Scene<float>& S, PathState<float, LANES>& st, PathResult<float, LANES>& res) {
  while (!st.inside)
    if (!core::enter_from_outside<float, LANES, core::kSDFBoundary, DIEL, false>(S, st, res)) return false;
  return true;
}

template <bool DIEL, int LANES>
void lane_start(void* ctx, simd::ObjectLane& o) {
  const Scene<float>& S = *static_cast<const Scene<float>*>(ctx);
  PathState<float, LANES> st;
  PathResult<float, LANES> res;
  core::begin_path<float, LANES, false>(S, o.elem, o.sample, o.chan, st, res);
  const bool alive = core::start_at_sensor<float, LANES, core::kSDFBoundary, DIEL, false>(S, o.elem, st, res) &&
                     into_object<DIEL>(S, st, res);
  store_lane(st, res, alive, o);
}

template <bool DIEL, int LANES>
void lane_surface(void* ctx, simd::ObjectLane& o, int32_t end, int32_t axis) {
  const Scene<float>& S = *static_cast<const Scene<float>*>(ctx);
  PathState<float, LANES> st;
  PathResult<float, LANES> res;
  load_lane(S, o, st, res);
  core::Flight f;
  f.end = end;
  f.axis = axis;
  const bool alive = core::cross_from_inside<float, LANES, core::kSDFBoundary, DIEL, false>(S, st, res, f) &&
                     into_object<DIEL>(S, st, res);
  store_lane(st, res, alive, o);
}

template <bool DIEL, int LANES>
simd::ObjectWalkScene object_scene(const Scene<float>& S) {
  simd::ObjectWalkScene W;
  const auto& M = S.medium;
  W.sigma_t = M.sigma_t.data;
  W.albedo = M.albedo.data;
  W.ref_sigma_t = M.ref_sigma_t.data;
  W.ref_albedo = M.ref_albedo.data;
  W.ref_sigma_t_floor = M.ref_sigma_t.plain ? 0.0f : M.ref_sigma_t.floor;
  W.ref_albedo_floor = M.ref_albedo.plain ? 0.0f : M.ref_albedo.floor;
  if (M.sigma_t.index != nullptr) {  // a palette medium (simd_serves_object: the same palette throughout)
    W.index = M.sigma_t.index;
    W.sigma_t_table = M.sigma_t.palette;
    W.albedo_table = M.albedo.palette;
    W.entries = int32_t(M.sigma_t.entries);
  }
  W.cell = S.sdf.cell;
  W.sdf = S.sdf.sdf;
  W.core = M.core;
  for (int a = 0; a < 3; ++a) {
    W.core_bricks[a] = int32_t(M.core_bricks[a]);
    W.core_sigma_t[a] = M.core_sigma_t[a];
    W.core_albedo[a] = M.core_albedo[a];
    W.voxel[a] = M.voxel[a];
  }
  W.D = int32_t(M.D);
  W.H = int32_t(M.H);
  W.W = int32_t(M.W);
  W.g = S.g;
  W.channels = LANES;
  W.seed = S.seed;
  W.max_depth = S.max_depth;
  W.rr_depth = S.rr_depth;
  W.spp = S.spp;
  W.exact_math = g_simd_exact_math.load();
  W.steps = const_cast<Scene<float>*>(&S);
  W.start = &lane_start<DIEL, LANES>;
  W.surface = &lane_surface<DIEL, LANES>;
  return W;
}

void object_walks(const simd::ObjectWalkScene& W, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                  const simd::LaneTapes* tapes, simd::WalkDone done, void* ctx) {
  if (simd_level() == 2) simd::object_walks_avx512(W, elems, live, n, ratio, tapes, simd_ended_lanes(), done, ctx);
  else simd::object_walks_avx2(W, elems, live, n, ratio, tapes, simd_ended_lanes(), done, ctx);
}

}  // namespace

template <bool DIEL, bool RATIO, int LANES>
ForwardCounts simd_object_forward_chunk(const Scene<float>& S, float* out, int64_t c, int64_t nchunks,
                                        const Share& share) {
  const simd::ObjectWalkScene W = object_scene<DIEL, LANES>(S);
  return simd_forward_batches(
      S, out, [&](const auto& body) { for_elements_of_chunk(c, nchunks, share, body); },
      [&](const int64_t* elems, int64_t n, simd::WalkDone done, void* ctx) {
        object_walks(W, elems, nullptr, n, RATIO, nullptr, done, ctx);
      });
}

template <bool DIEL, int LANES>
int64_t simd_object_backward_chunk(const Scene<float>& S, const float* grad_out, const Adjoint<float>& A,
                                   TapeStore<float, LANES>& store, int64_t c, int64_t nchunks, const Share& share,
                                   float* image, int64_t* cut) {
  const simd::ObjectWalkScene W = object_scene<DIEL, LANES>(S);
  return simd_replay_chunk<core::kSDFBoundary, DIEL>(
      S, grad_out, A, store, image, cut,
      [&](const auto& body) { for_elements_of_chunk(c, nchunks, share, body); },
      [&](const int64_t* elems, const uint8_t* live, int64_t n, const simd::LaneTapes* tapes, simd::WalkDone done,
          void* ctx) { object_walks(W, elems, live, n, true, tapes, done, ctx); });
}

#define TA_OBJECT_CHUNKS(DIEL, LANES)                                                                                \
  template ForwardCounts simd_object_forward_chunk<DIEL, false, LANES>(const Scene<float>&, float*, int64_t, int64_t, \
                                                                       const Share&);                                 \
  template ForwardCounts simd_object_forward_chunk<DIEL, true, LANES>(const Scene<float>&, float*, int64_t, int64_t,  \
                                                                      const Share&);                                  \
  template int64_t simd_object_backward_chunk<DIEL, LANES>(const Scene<float>&, const float*, const Adjoint<float>&,   \
                                                           TapeStore<float, LANES>&, int64_t, int64_t, const Share&,  \
                                                           float*, int64_t*);
TA_OBJECT_CHUNKS(false, 1)
TA_OBJECT_CHUNKS(true, 1)
TA_OBJECT_CHUNKS(false, 3)
TA_OBJECT_CHUNKS(true, 3)
#undef TA_OBJECT_CHUNKS

}  // namespace detail

bool set_simd_exact_math(bool on) { return detail::g_simd_exact_math.exchange(on); }

}  // namespace volpath
}  // namespace ta
