// SIMD glue: the SIMD walks (eight or sixteen paths per thread at once) where the scene allows them: the slab walk
// (slab_simd.h: box boundary, face texels) and the object walk (object_simd.h: SDF boundary, any sensor and emitter;
// object_simd_glue.cpp). Which walk runs (the CPU, TA_SIMD, set_simd), whether it serves a scene, and its forward and
// replay of one chunk of sensor elements, with the same per-element sums and the same deposits as the scalar
// kernels.
#pragma once

#include <algorithm>
#include <cstdint>
#include <memory>
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
void deposit_simd_tape(const simd::WalkOut& o, int ch, float adj, const core::Adjoint<float>& A);
// core::deposit_tape<float, 3> for the compact tape of a path that serves the three channels (adj per channel).
void deposit_simd_tape3(const simd::WalkOut& o, const float adj[3], const core::Adjoint<float>& A);

// The image of a batch of n elements from each path's term by item ((k·spp + sample)·3 + channel), summed in sample
// order as the scalar kernel adds them.
void write_batch_image(const core::Scene<float>& S, const int64_t* elems, int64_t n, const std::vector<double>& values,
                       float* out);

// The term of a finished path in its element's image, in double as the scalar kernels add it: V for a constant
// emitter (whose radiance element_radiance applies), V·L_e along the escape direction for the others. `l` is the
// path's value of channel ch ([0] for a path of one channel, [ch] for a path of three).
inline double image_term(const core::Scene<float>& S, const simd::WalkOut& o, int l, int ch) {
  if (S.emitter.kind == core::kConstant) return double(o.value[l]);
  if (!o.escaped) return 0.0;
  float Le[3];
  S.emitter.eval(o.direction, Le);
  return double(o.value[l]) * double(Le[ch]);
}

// Each channel's term of a finished path into `values` by item (a path of three channels fills three items).
inline void store_terms(const core::Scene<float>& S, const simd::WalkOut& o, std::vector<double>& values) {
  if (o.channels == 3) {
    for (int c = 0; c < 3; ++c) values[size_t(o.item + c)] = image_term(S, o, c, c);
  } else {
    values[size_t(o.item)] = image_term(S, o, 0, int(o.item % 3));
  }
}

// The forward of one chunk by a SIMD walk (simd_forward_chunk, simd_object_forward_chunk): the elements that
// for_elements(body) hands out, in batches of kSimdBatch, each walked by walk(elems, n, done, ctx); every path's term
// by item, then the batch's image in sample order (write_batch_image), and the walks' counts.
template <typename ForElements, typename Walk>
ForwardCounts simd_forward_batches(const core::Scene<float>& S, float* out, const ForElements& for_elements,
                                   const Walk& walk) {
  struct Ctx {
    const core::Scene<float>* S;
    std::vector<double> values;
    ForwardCounts counts;
  } ctx{&S, {}, {}};
  const simd::WalkDone done = [](void* p, const simd::WalkOut& o) {
    auto* x = static_cast<Ctx*>(p);
    store_terms(*x->S, o, x->values);
    x->counts.scatter_events += o.scatter_events;
    x->counts.truncated_paths += o.truncated;
    x->counts.voxel_steps += o.voxel_steps;
    x->counts.outside_steps += o.outside_steps;
    x->counts.core_events += o.core_events;
  };
  std::vector<int64_t> elems;
  elems.reserve(kSimdBatch);
  auto flush = [&]() {
    if (elems.empty()) return;
    const int64_t n = int64_t(elems.size());
    ctx.values.assign(size_t(n * S.spp * 3), 0.0);
    walk(elems.data(), n, done, &ctx);
    write_batch_image(S, elems.data(), n, ctx.values, out);
    elems.clear();
  };
  for_elements([&](int64_t t) {
    elems.push_back(t);
    if (int64_t(elems.size()) == kSimdBatch) flush();
  });
  flush();
  return ctx.counts;
}

// The gradient replay of one chunk by a SIMD walk (simd_backward_chunk, simd_object_backward_chunk): the elements
// that for_elements(body) hands out, in batches of kSimdBatch, each walked by walk(elems, live, n, tapes, done, ctx)
// with every lane recording its tape; each path is deposited when it ends (deposit_simd_tape, or deposit_simd_tape3
// for the paths of a walk that serves three channels, LANES = 3), and a path longer than its lane's tape is replayed
// by the scalar code from the start (walk and deposit), so every deposit belongs to the walk that produced its
// weight. With `image` every channel is walked and the batch's image written (write_batch_image); `cut` takes the
// truncated walks. Returns the scatter events.
template <int B, bool DIEL, int LANES, typename ForElements, typename Walk>
int64_t simd_replay_chunk(const core::Scene<float>& S, const float* grad_out, const core::Adjoint<float>& A,
                          TapeStore<float, LANES>& store, float* image, int64_t* cut, const ForElements& for_elements,
                          const Walk& walk) {
  const int64_t seg_cap = std::min(kSimdSegments, g_initial_tape_segments.load());  // (tests set it to 0 or 4)
  // the lanes' tapes, for all the batches of this chunk (not zeroed: only the pages the paths reach are touched)
  simd::LaneTapes tapes;
  tapes.seg_cap = seg_cap;
  tapes.col_cap = seg_cap / 2;
  std::unique_ptr<simd::TapeSegmentF[]> seg_buf(new simd::TapeSegmentF[size_t(simd::kMaxLanes * (seg_cap + 1))]);
  std::unique_ptr<simd::TapeCollisionF[]> col_buf;
  std::unique_ptr<simd::TapeCollision3F[]> col3_buf;
  if (LANES == 3) col3_buf.reset(new simd::TapeCollision3F[size_t(simd::kMaxLanes * (tapes.col_cap + 1))]);
  else col_buf.reset(new simd::TapeCollisionF[size_t(simd::kMaxLanes * (tapes.col_cap + 1))]);
  tapes.segs = seg_buf.get();
  tapes.cols = col_buf.get();
  tapes.cols3 = col3_buf.get();
  struct Ctx {
    const core::Scene<float>* S;
    const float* grad_out;
    const core::Adjoint<float>* A;
    TapeStore<float, LANES>* store;
    const int64_t* elems;
    bool image;
    std::vector<double> values;  // with an image: each path's term, by item
    int64_t ev = 0, cut = 0;
  } ctx{&S, grad_out, &A, &store, nullptr, image != nullptr, {}};
  const simd::WalkDone done = [](void* p, const simd::WalkOut& o) {
    auto* x = static_cast<Ctx*>(p);
    const core::Scene<float>& S = *x->S;
    const int64_t spp = S.spp;
    const int ch = int(o.item % 3);
    const int64_t s = (o.item / 3) % spp, t = x->elems[o.item / (3 * spp)];
    const float* g = x->grad_out + t * 3;
    x->ev += o.scatter_events;
    x->cut += o.truncated;
    if (o.overflow) {  // too long for the lane's tape: the scalar replay walks it again and deposits
      double acc[3] = {0, 0, 0};
      ImageTerms terms;
      terms.acc = acc;
      x->ev += replay<float, LANES, B, DIEL, false>(S, t, s, ch, g, *x->A, *x->store, x->image ? &terms : nullptr);
      if (x->image)  // the terms of the walk that deposited
        for (int l = 0; l < LANES; ++l) x->values[size_t(o.item + l)] = acc[LANES == 1 ? ch : l];
      return;
    }
    if (x->image) store_terms(S, o, x->values);
    if (!o.escaped) return;
    float Le[3] = {S.emitter.radiance[0], S.emitter.radiance[1], S.emitter.radiance[2]};
    if (S.emitter.kind != core::kConstant) S.emitter.eval(o.direction, Le);
    if constexpr (LANES == 3) {
      float adj[3];
      bool any = false;
      for (int l = 0; l < 3; ++l) {
        adj[l] = g[l] * Le[l] / float(spp);
        any |= adj[l] != 0.0f;
      }
      if (any) deposit_simd_tape3(o, adj, *x->A);
    } else {
      const float adj = g[ch] * Le[ch] / float(spp);
      if (adj == 0.0f) return;
      deposit_simd_tape(o, ch, adj, *x->A);
    }
  };
  std::vector<int64_t> elems;
  std::vector<uint8_t> live;
  elems.reserve(kSimdBatch);
  live.reserve(kSimdBatch);
  const bool constant = S.emitter.kind == core::kConstant;
  auto flush = [&]() {
    if (elems.empty()) return;
    const int64_t n = int64_t(elems.size());
    ctx.elems = elems.data();
    if (image != nullptr) ctx.values.assign(size_t(n * S.spp * 3), 0.0);
    walk(elems.data(), live.data(), n, &tapes, done, &ctx);
    if (image != nullptr) write_batch_image(S, elems.data(), n, ctx.values, image);
    elems.clear();
    live.clear();
  };
  for_elements([&](int64_t t) {
    const float* g = grad_out + t * 3;
    uint8_t bitsv = 0;
    for (int ch = 0; ch < 3; ++ch)
      if ((image != nullptr || g[ch] != 0.0f) && !(constant && S.emitter.radiance[ch] == 0.0f))
        bitsv |= uint8_t(1 << ch);
    if (!bitsv && image == nullptr) return;
    elems.push_back(t);
    live.push_back(bitsv);
    if (int64_t(elems.size()) == kSimdBatch) flush();
  });
  flush();
  if (cut != nullptr) *cut = ctx.cut;
  return ctx.ev;
}

// Whether the SIMD object walk (object_simd.h) serves this scene: float32 dense grids (the reference may be floored)
// or, with one walk per channel, one palette medium (a quantised print's forward); an SDF boundary, one walk per
// channel or one for the three (not hero), no tally.
template <typename T, int LANES, int B, bool HERO>
bool simd_serves_object(const core::Scene<T>& S) {
  if constexpr (!std::is_same_v<T, float> || B != core::kSDFBoundary || HERO) {
    return false;
  } else {
    const auto& M = S.medium;
    const bool dense = M.sigma_t.index == nullptr && M.albedo.index == nullptr && M.ref_sigma_t.index == nullptr &&
                       M.ref_albedo.index == nullptr && M.sigma_t.plain && M.albedo.plain;
    const bool palette = M.sigma_t.index != nullptr && M.albedo.index == M.sigma_t.index &&
                         M.ref_sigma_t.index == M.sigma_t.index && M.ref_albedo.index == M.sigma_t.index &&
                         M.ref_sigma_t.palette == M.sigma_t.palette && M.ref_albedo.palette == M.albedo.palette &&
                         M.sigma_t.entries == M.albedo.entries && M.sigma_t.entries <= 256;
    return simd_enabled() && S.tally == nullptr && S.sdf.cell != nullptr && (dense || (palette && LANES == 1)) &&
           3 * M.voxels() < (int64_t(1) << 31) && S.elements() < (int64_t(1) << 31) &&
           (M.D + 1) * (M.H + 1) * (M.W + 1) < (int64_t(1) << 31);
  }
}

// Forward and gradient replay of chunk c with the SIMD object walk, as simd_forward_chunk and simd_backward_chunk
// (which they follow for an object: the sensor's elements in strided blocks, any emitter; ForwardCounts in full).
// LANES: one walk per channel (1) or one for the three (3), as the scalar kernels' LANES.
template <bool DIEL, bool RATIO, int LANES>
ForwardCounts simd_object_forward_chunk(const core::Scene<float>& S, float* out, int64_t c, int64_t nchunks,
                                        const Share& share);
template <bool DIEL, int LANES>
int64_t simd_object_backward_chunk(const core::Scene<float>& S, const float* grad_out, const core::Adjoint<float>& A,
                                   TapeStore<float, LANES>& store, int64_t c, int64_t nchunks, const Share& share,
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
