// The scalar path replay of one path (radiative backpropagation) on the CPU: core::replay_path (a recording walk into
// a per-thread tape, then the deposit; a path longer than the tape is walked once more, depositing as it goes) with a
// tape that grows after an overflow. Shared by the backward kernel (backward_cpu.cpp) and the SIMD glue (a path too
// long for its lane's tape).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <vector>

#include "core/integrator.h"
#include "core/replay.h"

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

// What a replay adds to its element's image (core/replay.h).
using core::ImageTerms;

// Replays one path (core::replay_path) with the thread's tape; after a path that did not fit it, the tape grows for
// the paths to come. `g` is grad_output of the element (3 channels); `image` (optional) takes the walk's term of the
// image. Returns the walks' scatter events.
template <typename T, int LANES, int B, bool DIEL, bool HERO>
inline int64_t replay(const core::Scene<T>& S, int64_t t, int64_t s, int ch, const T* g, const core::Adjoint<T>& A,
                      TapeStore<T, LANES>& store, ImageTerms* image = nullptr) {
  bool two_pass = false;
  const int64_t events = core::replay_path<T, LANES, B, DIEL, HERO>(S, t, s, ch, g, A, store.tape, image, &two_pass);
  if (two_pass) store.grow();
  return events;
}

}  // namespace detail
}  // namespace volpath
}  // namespace ta
