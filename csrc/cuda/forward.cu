// The forward kernels: one thread per path walks core::trace_path as the CPU's forward kernel does
// (volpath/forward_cpu.cpp) and adds its term, V·L_e (V alone for a constant emitter), into its element's sum; a
// second launch (ta_image_*) turns the sums into the image (core::element_radiance). The sums are doubles added
// atomically, so an image equals the CPU's up to the order of its samples' additions.
//
// One kernel per configuration the CPU dispatches (volpath/dispatch.h, forward_kernel's template arguments):
//   ta_forward_<dtype>_<lanes>_<boundary>_<optics>_<weights>
//     dtype     f32, f64
//     lanes     l1 (one walk per channel), l3 (one walk for three channels), hero (l3 with hero-channel MIS)
//     boundary  box, sdf
//     optics    diel (smooth dielectric), matched (index matched)
//     weights   ratio (sampled from a reference medium, ratio weights), plain (reference = parameters; also the
//               palette render of a quantised print, whose Channels read the palette)
// Parameters: (Scene<T> S, Launch L, double* acc (count, 3), unsigned long long* counts[5]: scatter events,
// truncated walks, voxel steps, outside steps, core events, as volpath's ForwardCounts).
#include "cuda/launch.cuh"

namespace ta {
namespace cuda {

template <typename T, int LANES, int B, bool DIEL, bool RATIO, bool HERO>
__device__ inline void forward_paths(const core::Scene<T>& S, const Launch& L, double* acc,
                                     unsigned long long* counts) {
  const int64_t p = L.first + int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  long long n[5] = {0, 0, 0, 0, 0};
  if (p < L.first + L.paths) {  // no early return: the whole warp sums the counters
    const PathIndex i = path_index<LANES>(L, S.spp, p);
    const core::Adjoint<T> none;
    const auto r = core::trace_path<T, LANES, B, DIEL, RATIO, false, false, HERO>(S, i.t, i.s, i.ch, nullptr,
                                                                                   nullptr, none);
    n[0] = r.scatter_events;
    n[1] = r.truncated;
    n[2] = r.voxel_steps;
    n[3] = r.outside_steps;
    n[4] = r.core_events;
    const bool constant = S.emitter.kind == core::kConstant;
    T Le[3];
    if (!constant && r.escaped) S.emitter.eval(r.direction, Le);
    for (int l = 0; l < LANES; ++l) {
      const int c = LANES == 1 ? i.ch : l;
      if (constant) add_term(acc, i.u, c, double(r.value[l]));
      else if (r.escaped) add_term(acc, i.u, c, double(r.value[l]) * double(Le[c]));
    }
  }
  add_counts(counts, n);
}

}  // namespace cuda
}  // namespace ta

// The configurations, as nested lists: each level passes its choices on to the next.
#define TA_FWD_KERNEL(T, TN, LN, NL, H, BN, B, DN, D, RN, R)                                                 \
  extern "C" __global__ void __launch_bounds__(ta::cuda::kBlock)                                             \
      ta_forward_##TN##_##LN##_##BN##_##DN##_##RN(const ta::core::Scene<T> S, const ta::cuda::Launch launch, \
                                                  double* acc, unsigned long long* counts) {                 \
    ta::cuda::forward_paths<T, NL, B, D, R, H>(S, launch, acc, counts);                                      \
  }
#define TA_FWD_WEIGHTS(T, TN, LN, NL, H, BN, B, DN, D)       \
  TA_FWD_KERNEL(T, TN, LN, NL, H, BN, B, DN, D, ratio, true) \
  TA_FWD_KERNEL(T, TN, LN, NL, H, BN, B, DN, D, plain, false)
#define TA_FWD_OPTICS(T, TN, LN, NL, H, BN, B) \
  TA_FWD_WEIGHTS(T, TN, LN, NL, H, BN, B, diel, true) TA_FWD_WEIGHTS(T, TN, LN, NL, H, BN, B, matched, false)
#define TA_FWD_BOUNDARY(T, TN, LN, NL, H)                      \
  TA_FWD_OPTICS(T, TN, LN, NL, H, box, ta::core::kBoxBoundary) \
  TA_FWD_OPTICS(T, TN, LN, NL, H, sdf, ta::core::kSDFBoundary)
#define TA_FWD_LANES(T, TN) \
  TA_FWD_BOUNDARY(T, TN, l1, 1, false) TA_FWD_BOUNDARY(T, TN, l3, 3, false) TA_FWD_BOUNDARY(T, TN, hero, 3, true)

#if TA_CUDA_DTYPE == 32
TA_FWD_LANES(float, f32)
#endif
#if TA_CUDA_DTYPE == 64
TA_FWD_LANES(double, f64)
#endif

// The image of the share's elements from their sums: (Scene<T> S, Launch L, const double* acc (count, 3), T* out),
// one thread per element. Also the image of the one walk of the ema estimator (replay.cu).
#if TA_CUDA_DTYPE == 32
extern "C" __global__ void __launch_bounds__(ta::cuda::kBlock)
    ta_image_f32(const ta::core::Scene<float> S, const ta::cuda::Launch launch, const double* acc, float* out) {
  ta::cuda::write_image(S, launch, acc, out);
}
#endif
#if TA_CUDA_DTYPE == 64
extern "C" __global__ void __launch_bounds__(ta::cuda::kBlock)
    ta_image_f64(const ta::core::Scene<double> S, const ta::cuda::Launch launch, const double* acc, double* out) {
  ta::cuda::write_image(S, launch, acc, out);
}
#endif
