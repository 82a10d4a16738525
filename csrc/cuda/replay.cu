// The replay kernels (radiative backpropagation by path replay): one thread per path replays it with the core's
// replay (core::replay_path: a recording walk into a tape, then the deposit; a path longer than the tape is walked
// again, depositing as it goes), as the CPU's backward kernel does (volpath/backward_cpu.cpp). The tape lives in the
// thread's local memory (kTapeSegments segments, half as many collisions) and the deposits are atomic adds into the
// gradient grids, or into compact buffers of the asked voxels (Adjoint::rank, grad_support). With `image` not null
// the same walks also add their terms into their elements' sums (the one walk of the ema estimator,
// scene_forward_backward): every channel is walked then, as on the CPU; ta_image_* (forward.cu) writes the image.
//
// One kernel per configuration the CPU's backward dispatches (volpath/dispatch.h, backward_kernel's arguments):
//   ta_replay_<dtype>_<lanes>_<boundary>_<optics>    (names as in forward.cu; the replay always carries ratio weights)
// Parameters: (Scene<T> S, Launch L, const T* grad_out (elements, 3), T* grad_sigma_t, T* grad_albedo (either null
// when not asked; channel-planar, `plane` values per channel), int64_t plane, const int32_t* rank (or null: dense
// grids), double* image (count, 3) or null, unsigned long long* counts[3]: scatter events, truncated walks (with an
// image), paths replayed in two passes).
#include "cuda/launch.cuh"

#ifndef TA_CUDA_TAPE_SEGMENTS
#define TA_CUDA_TAPE_SEGMENTS 64  // a compile option of the launcher (-DTA_CUDA_TAPE_SEGMENTS=n)
#endif

namespace ta {
namespace cuda {

constexpr int kTapeSegments = TA_CUDA_TAPE_SEGMENTS;

template <typename T, int LANES, int B, bool DIEL, bool HERO>
__device__ inline void replay_paths(const core::Scene<T>& S, const Launch& L, const T* grad_out, T* grad_sigma_t,
                                    T* grad_albedo, int64_t plane, const int32_t* rank, double* image,
                                    unsigned long long* counts) {
  const int64_t p = L.first + int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  long long n[3] = {0, 0, 0};
  if (p < L.first + L.paths) {  // no early return: the whole warp sums the counters
    const PathIndex i = path_index<LANES>(L, S.spp, p);
    const T* g = grad_out + i.t * 3;
    // the channels whose paths can carry a derivative (or, with an image, any light), as the CPU decides
    const bool constant = S.emitter.kind == core::kConstant;
    bool live = false;
    for (int c = 0; c < 3; ++c)
      if (LANES == 3 || c == i.ch)
        live |= (image != nullptr || g[c] != T(0)) && !(constant && S.emitter.radiance[c] == T(0));
    if (live) {
      core::Adjoint<T, AtomicAdd> A;
      A.grad_sigma_t = grad_sigma_t;
      A.grad_albedo = grad_albedo;
      A.plane = plane;
      A.rank = rank;
      core::TapeSegment<T, LANES> segs[kTapeSegments];
      core::TapeCollision<T, LANES> cols[kTapeSegments / 2];
      core::Tape<T, LANES> tape;
      tape.segs = segs;
      tape.cols = cols;
      tape.seg_cap = kTapeSegments;
      tape.col_cap = kTapeSegments / 2;
      double acc[3] = {0, 0, 0};
      core::ImageTerms terms;
      terms.acc = acc;
      bool two_pass = false;
      n[0] = core::replay_path<T, LANES, B, DIEL, HERO>(S, i.t, i.s, i.ch, g, A, tape,
                                                         image != nullptr ? &terms : nullptr, &two_pass);
      n[1] = terms.truncated;
      n[2] = two_pass;
      if (image != nullptr)
        for (int c = 0; c < 3; ++c) add_term(image, i.u, c, acc[c]);
    }
  }
  add_counts(counts, n);
}

}  // namespace cuda
}  // namespace ta

#define TA_REPLAY_KERNEL(T, TN, LN, NL, H, BN, B, DN, D)                                                       \
  extern "C" __global__ void __launch_bounds__(ta::cuda::kBlock) ta_replay_##TN##_##LN##_##BN##_##DN(          \
      const ta::core::Scene<T> S, const ta::cuda::Launch launch, const T* grad_out, T* grad_sigma_t,           \
      T* grad_albedo, int64_t plane, const int32_t* rank, double* image, unsigned long long* counts) {         \
    ta::cuda::replay_paths<T, NL, B, D, H>(S, launch, grad_out, grad_sigma_t, grad_albedo, plane, rank, image, \
                                          counts);                                                             \
  }
#define TA_REPLAY_OPTICS(T, TN, LN, NL, H, BN, B)       \
  TA_REPLAY_KERNEL(T, TN, LN, NL, H, BN, B, diel, true) \
  TA_REPLAY_KERNEL(T, TN, LN, NL, H, BN, B, matched, false)
#define TA_REPLAY_BOUNDARY(T, TN, LN, NL, H)                      \
  TA_REPLAY_OPTICS(T, TN, LN, NL, H, box, ta::core::kBoxBoundary) \
  TA_REPLAY_OPTICS(T, TN, LN, NL, H, sdf, ta::core::kSDFBoundary)
#define TA_REPLAY_LANES(T, TN)                                                    \
  TA_REPLAY_BOUNDARY(T, TN, l1, 1, false) TA_REPLAY_BOUNDARY(T, TN, l3, 3, false) \
  TA_REPLAY_BOUNDARY(T, TN, hero, 3, true)

#if TA_CUDA_DTYPE == 32
TA_REPLAY_LANES(float, f32)
#endif
#if TA_CUDA_DTYPE == 64
TA_REPLAY_LANES(double, f64)
#endif
