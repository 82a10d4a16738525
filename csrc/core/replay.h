// The path replay of one path (radiative backpropagation), as every device runs it: a recording walk into a
// caller-owned tape (tape.h), then the deposit of ∂/∂θ through the Adjoint's deposit policy; a path longer than the
// tape is walked once more, depositing as it goes (the two-pass replay). The CPU glue passes a per-thread tape that
// grows after an overflow (volpath/replay.h); the CUDA glue a fixed tape in each thread's local memory and an atomic
// deposit (csrc/cuda/). Beside it, what every kernel does with the walks' terms: an element's image from their sums.
#pragma once

#include "core/defs.h"
#include "core/integrator.h"

namespace ta {
namespace core {

// What a replay adds to its element's image when forward and backward share the walk (the one walk of the ema
// estimator, scene_forward_backward): acc[c] += V_c · L_e,c (V_c alone for a constant emitter, which the caller
// multiplies by its radiance), in the forward kernel's terms; `truncated` counts the walks cut by max_depth.
struct ImageTerms {
  double* acc = nullptr;  // 3 channels of the element
  int64_t truncated = 0;
};

// A sensor element's radiance in channel c from the sum over its samples of the walks' terms (V·L_e, or V alone for a
// constant emitter, whose radiance is applied here): how every kernel, on every device, writes its image.
template <typename T>
TA_HD inline T element_radiance(const Scene<T>& S, double sum, int c) {
  return S.emitter.kind == kConstant ? T(sum * double(S.emitter.radiance[c]) / double(S.spp)) : T(sum / double(S.spp));
}

// Replays path (element t, sample s, channel ch of a one-lane walk): a single walk that records its events in
// `tape`, then the deposit of ∂/∂θ (only escaped paths that see a non-zero emitter carry any). A path that does not
// fit the tape is walked once more, depositing as it goes, and sets *two_pass. `g` is grad_output of the element
// (3 channels); `image` (optional) takes the walk's term of the image. Returns the walks' scatter events.
template <typename T, int LANES, int B, bool DIEL, bool HERO, typename Deposit>
TA_HD inline int64_t replay_path(const Scene<T>& S, int64_t t, int64_t s, int ch, const T* g,
                                 const Adjoint<T, Deposit>& A, Tape<T, LANES>& tape, ImageTerms* image,
                                 bool* two_pass) {
  tape.clear();
  const auto r1 = trace_path<T, LANES, B, DIEL, true, false, true, HERO>(S, t, s, ch, nullptr, nullptr, A, &tape);
  T Le[3];
  if (r1.escaped) S.emitter.eval(r1.direction, Le);
  if (image != nullptr) {
    image->truncated += r1.truncated;
    for (int l = 0; l < LANES; ++l) {
      const int c = LANES == 1 ? ch : l;
      if (S.emitter.kind == kConstant) image->acc[c] += double(r1.value[l]);
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
    deposit_tape<T, LANES>(tape, r1.value, r1.prod_nonzero, r1.zeros, ch, adj, A);
    return r1.scatter_events;
  }
  *two_pass = true;
  const auto r2 = trace_path<T, LANES, B, DIEL, true, true, false, HERO>(S, t, s, ch, &r1, adj, A);
  return r1.scatter_events + r2.scatter_events;
}

}  // namespace core
}  // namespace ta
