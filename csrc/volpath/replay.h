// The scalar path replay of one path (radiative backpropagation): a recording walk into a per-thread tape, then
// the deposit (core/tape.h); a path longer than the tape is walked once more, depositing as it goes. Shared by the
// backward kernel (backward_cpu.cpp) and the SIMD glue (a path too long for its lane's tape).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <vector>

#include "core/integrator.h"

namespace ta {
namespace volpath {
namespace detail {

// The initial per-thread tape capacity (segments; collisions get half): set_tape_capacity (tests).
extern std::atomic<int64_t> g_initial_tape_segments;

// Per-thread tape of the single-walk replay (core/tape.h). It starts small and doubles (up to a cap) when a path
// overflows it; a path that overflows is replayed with the two-pass method, so every path is exact.
template <typename T, int LANES>
struct TapeStore {
  static constexpr int64_t kMaxSegments = int64_t(1) << 21;  // float: 32 MiB of segments + 32 MiB of collisions
  std::vector<core::TapeSegment<T, LANES>> segs;
  std::vector<core::TapeCollision<T, LANES>> cols;
  core::Tape<T, LANES> tape;

  TapeStore() { resize(std::min(kMaxSegments, g_initial_tape_segments.load())); }
  void resize(int64_t nseg) {
    segs.resize(nseg);
    cols.resize(nseg / 2);
    tape.segs = segs.data();
    tape.cols = cols.data();
    tape.seg_cap = int64_t(segs.size());
    tape.col_cap = int64_t(cols.size());
  }
  // After an overflow: a larger tape for the paths to come, while the cap allows.
  void grow() {
    if (tape.seg_cap > 0 && tape.seg_cap < kMaxSegments) resize(std::min(kMaxSegments, 2 * tape.seg_cap));
  }
};

// What a replay adds to its element's image when forward and backward share the walk (scene_forward_backward):
// acc[c] += V_c · L_e,c (V_c alone for a constant emitter, which the caller multiplies by its radiance), in the
// forward kernel's terms; `truncated` counts the walks cut by max_depth.
struct ImageTerms {
  double* acc = nullptr;  // 3 channels of the element
  int64_t truncated = 0;
};

// Replays one path: a single walk that records its events in the tape, then the deposit of ∂/∂θ (only escaped paths
// that see a non-zero emitter carry any). A path that does not fit the tape is walked once more, depositing as it
// goes (the two-pass replay). `g` is grad_output of the element (3 channels); `image` (optional) takes the walk's
// term of the image. Returns the walks' scatter events.
template <typename T, int LANES, int B, bool DIEL, bool HERO>
inline int64_t replay(const core::Scene<T>& S, int64_t t, int64_t s, int ch, const T* g, const core::Adjoint<T>& A,
                      TapeStore<T, LANES>& store, ImageTerms* image = nullptr) {
  auto& tape = store.tape;
  tape.clear();
  const auto r1 =
      core::trace_path<T, LANES, B, DIEL, true, false, true, HERO>(S, t, s, ch, nullptr, nullptr, A, &tape);
  T Le[3];
  if (r1.escaped) S.emitter.eval(r1.direction, Le);
  if (image != nullptr) {
    image->truncated += r1.truncated;
    for (int l = 0; l < LANES; ++l) {
      const int c = LANES == 1 ? ch : l;
      if (S.emitter.kind == core::kConstant) image->acc[c] += double(r1.value[l]);
      else if (r1.escaped) image->acc[c] += double(r1.value[l]) * double(Le[c]);
    }
  }
  if (!r1.escaped) return r1.scatter_events;
  T adj[LANES];
  bool any = false;
  for (int l = 0; l < LANES; ++l) {
    const int c = LANES == 1 ? ch : l;
    adj[l] = g[c] * Le[c] / T(S.spp);
    any |= adj[l] != T(0);
  }
  if (!any) return r1.scatter_events;
  if (!tape.overflow) {
    core::deposit_tape<T, LANES>(tape, r1.value, r1.prod_nonzero, r1.zeros, ch, adj, A);
    return r1.scatter_events;
  }
  store.grow();
  const auto r2 = core::trace_path<T, LANES, B, DIEL, true, true, false, HERO>(S, t, s, ch, &r1, adj, A);
  return r1.scatter_events + r2.scatter_events;
}

}  // namespace detail
}  // namespace volpath
}  // namespace ta
