// The backward kernel (radiative backpropagation by path replay) and its entry points scene_backward_cpu and
// scene_forward_backward_cpu (the image of the same walks too, for an adjoint known before the render): per sensor
// element, each sample's path replayed (replay.h, or the SIMD slab or object walk where it serves), deposited into
// per-chunk gradient buffers that are added in chunk order.
#include <ATen/Parallel.h>

#include <atomic>
#include <cstdlib>
#include <memory>
#include <type_traits>
#include <vector>

#include "core/integrator.h"
#include "volpath/checks.h"
#include "volpath/dispatch.h"
#include "volpath/interrupt.h"
#include "volpath/replay.h"
#include "volpath/scene_build.h"
#include "volpath/simd_glue.h"
#include "volpath/threading.h"
#include "volpath/volpath.h"

namespace ta {
namespace volpath {
namespace detail {

std::atomic<int64_t> g_initial_tape_segments{int64_t(1) << 14};  // set_tape_capacity (tests)

}  // namespace detail

namespace {

using core::Adjoint;
using core::Scene;
using namespace detail;

// With `image` (not null): forward and backward share the walk (scene_forward_backward). Every channel of every
// element is walked (not only those with a non-zero grad_output) and each walk's term goes into the element's image,
// summed in sample order and scaled as in the forward kernel; `cut` takes the truncated walks.
// With `asked` (grad_support) every chunk deposits into compact buffers of the asked voxels only (AskedVoxels), which
// are summed in chunk order and written into the outputs' asked voxels (whose other values stay 0, untouched).
template <typename T, int LANES, int B, bool DIEL, bool HERO>
int64_t backward_kernel(const Scene<T>& S, const T* grad_out, T* gs, T* ga, const Share& share, T* image = nullptr,
                        int64_t* cut = nullptr, const AskedVoxels* asked = nullptr) {
  const int64_t nchunks = num_chunks(share.count);
  const int64_t N = S.medium.voxels();
  const int64_t plane = asked != nullptr ? asked->count : N;  // the buffers' values per channel
  // chunk 0 accumulates into the outputs (or, asked, its own compact buffers); the others into their own buffers,
  // summed in chunk order below
  std::vector<ZeroedBuffer<T>> bufs_s, bufs_a;
  std::vector<HugeArray<T>> compact_s, compact_a;
  for (int64_t c = asked != nullptr ? 0 : 1; c < nchunks; ++c) {
    if (asked != nullptr) {
      if (gs) compact_s.emplace_back(3 * plane).fill(T(0));
      if (ga) compact_a.emplace_back(3 * plane).fill(T(0));
    } else {
      if (gs) bufs_s.emplace_back(3 * plane);
      if (ga) bufs_a.emplace_back(3 * plane);
    }
  }
  std::vector<int64_t> events(nchunks, 0), truncated(nchunks, 0);
  const bool constant = S.emitter.kind == core::kConstant;
  const bool simd = simd_serves<T, LANES, B, HERO>(S);
  const bool simd_object = simd_serves_object<T, LANES, B, HERO>(S);
  std::vector<float> ref_pair;
  if constexpr (std::is_same_v<T, float>)
    if (simd) ref_pair = pack_reference(S);
  for_each_chunk(nchunks, [&](int64_t c) {
    Adjoint<T> A;
    A.plane = plane;
    if (asked != nullptr) {
      A.rank = asked->rank.data();
      if (gs) A.grad_sigma_t = compact_s[c].data();
      if (ga) A.grad_albedo = compact_a[c].data();
    } else {
      if (gs) A.grad_sigma_t = c == 0 ? gs : bufs_s[c - 1].data();
      if (ga) A.grad_albedo = c == 0 ? ga : bufs_a[c - 1].data();
    }
    int64_t ev = 0;
    TapeStore<T, LANES> store;
    if constexpr (std::is_same_v<T, float> && LANES == 1 && B == core::kBoxBoundary && !HERO) {
      if (simd) {
        events[c] = simd_backward_chunk<DIEL>(S, ref_pair.data(), grad_out, A, store, c, nchunks, share, image,
                                              &truncated[c]);
        return;
      }
    }
    if constexpr (std::is_same_v<T, float> && B == core::kSDFBoundary && !HERO) {
      if (simd_object) {
        events[c] = simd_object_backward_chunk<DIEL, LANES>(S, grad_out, A, store, c, nchunks, share, image,
                                                            &truncated[c]);
        return;
      }
    }
    ImageTerms terms;
    for_chunk_elements(S, c, nchunks, share, [&](int64_t t) {
      const T* g = grad_out + t * 3;
      bool live[3], any = false;  // channels whose paths can carry a derivative (or, with an image, any light)
      for (int ch = 0; ch < 3; ++ch) {
        live[ch] = (image != nullptr || g[ch] != T(0)) && !(constant && S.emitter.radiance[ch] == T(0));
        any |= live[ch];
      }
      double acc[3] = {0, 0, 0};
      terms.acc = image != nullptr ? acc : nullptr;
      ImageTerms* ip = image != nullptr ? &terms : nullptr;
      if (any) {
        for (int64_t s = 0; s < S.spp; ++s) {
          if constexpr (LANES == 3) {
            ev += replay<T, 3, B, DIEL, HERO>(S, t, s, 0, g, A, store, ip);
          } else {
            for (int ch = 0; ch < 3; ++ch)
              if (live[ch]) ev += replay<T, 1, B, DIEL, false>(S, t, s, ch, g, A, store, ip);
          }
        }
      }
      if (image != nullptr)
        for (int ch = 0; ch < 3; ++ch) image[t * 3 + ch] = element_radiance(S, acc[ch], ch);
    });
    events[c] = ev;
    truncated[c] = terms.truncated;
  });
  if (asked != nullptr) {
    if (gs) asked->scatter(sum_in_chunk_order(compact_s), gs);
    if (ga) asked->scatter(sum_in_chunk_order(compact_a), ga);
  } else {
    reduce_in_chunk_order(gs, bufs_s, 3 * N);
    reduce_in_chunk_order(ga, bufs_a, 3 * N);
  }
  int64_t total = 0;
  for (int64_t e : events) total += e;
  if (cut != nullptr)
    for (int64_t k : truncated) *cut += k;
  return total;
}

}  // namespace

int64_t set_tape_capacity(int64_t segments) {
  TORCH_CHECK(segments >= 0, "segments: expected >= 0, got ", segments);
  return g_initial_tape_segments.exchange(segments);
}

namespace {

// A tensor of zeros like x in fresh memory from calloc: a large block comes from the kernel as pages that are zero
// until written, so the pages that nothing writes are never resident (the asked voxels of a print's shell are written
// once, each page first by a write, which allocates it without copying the shared zero page).
torch::Tensor untouched_zeros_like(const torch::Tensor& x) {
  void* p = std::calloc(size_t(x.numel()), x.element_size());
  TORCH_CHECK(p != nullptr, "volpath backward: could not allocate a gradient of ", x.numel() * x.element_size(),
              " bytes");
  return torch::from_blob(p, x.sizes(), [](void* q) { std::free(q); }, x.options());
}

// The replay of scene_backward_cpu, and `with_image` also the image of the same walks (scene_forward_backward_cpu).
// Returns (image or undefined, grad_sigma_t, grad_albedo, scatter events, truncated walks).
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, int64_t, int64_t> backward_impl(
    const torch::Tensor& grad_output, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, bool need_sigma_t, bool need_albedo,
    const SceneOptions& opt, double sigma_t_floor, double albedo_floor, bool with_image) {
  check_floors(sigma_t_floor, albedo_floor);
  check_all(sigma_t, albedo, ref_sigma_t, ref_albedo, opt, sigma_t_floor);
  int64_t expected = 1;
  for (int64_t s : image_shape(opt, sigma_t.size(2), sigma_t.size(3))) expected *= s;
  check_grad_output(grad_output, sigma_t, expected);
  const auto go = grad_output.contiguous();
  // with grad_support (a print's shell): compact gradient buffers of the asked voxels (AskedVoxels), written into
  // fresh zero grids whose other pages are never touched
  std::unique_ptr<AskedVoxels> asked;
  const int64_t N = sigma_t.numel() / 3;
  if (opt.grad_support.defined() && (need_sigma_t || need_albedo) && N < (int64_t(1) << 31))
    asked = std::make_unique<AskedVoxels>(opt.grad_support.data_ptr<bool>(), N);
  torch::Tensor gs, ga;
  if (need_sigma_t) gs = asked ? untouched_zeros_like(sigma_t) : torch::zeros_like(sigma_t);
  if (need_albedo) ga = asked ? untouched_zeros_like(albedo) : torch::zeros_like(albedo);
  int64_t events = 0, cut = 0;
  torch::Tensor image;
  if (with_image)
    image = opt.part_world > 1 ? torch::zeros(image_shape(opt, sigma_t.size(2), sigma_t.size(3)), sigma_t.options())
                               : torch::empty(image_shape(opt, sigma_t.size(2), sigma_t.size(3)), sigma_t.options());
  if (!need_sigma_t && !need_albedo && !with_image) return {image, gs, ga, events, cut};
  const InterruptScope interrupt;
  AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "volpath_backward", [&] {
    using T = scalar_t;
    check_finite<T>(go, "grad_output");
    const T* g = go.data_ptr<T>();
    SceneStorage store;
    Scene<T> S = make_scene<T>(opt, sigma_t, albedo, ref_sigma_t, ref_albedo, store);
    S.medium.ref_sigma_t.floor = T(sigma_t_floor);  // the sampling medium max(ref, floor), read without a copy
    S.medium.ref_albedo.floor = T(albedo_floor);
    S.medium.ref_sigma_t.plain = !(sigma_t_floor > 0);
    S.medium.ref_albedo.plain = !(albedo_floor > 0);
    if (opt.grad_support.defined()) build_core(S, store, opt.grad_support.data_ptr<bool>());
    T* pgs = need_sigma_t ? gs.data_ptr<T>() : nullptr;
    T* pga = need_albedo ? ga.data_ptr<T>() : nullptr;
    T* pim = image.defined() ? image.data_ptr<T>() : nullptr;
    dispatch_scene(opt, [&]<int L, bool HERO, int B, bool DIEL>() {
      events = backward_kernel<T, L, B, DIEL, HERO>(S, g, pgs, pga, Share(S.elements(), opt.part_rank,
                                                                         opt.part_world), pim, &cut,
                                                    asked.get());
    });
  });
  interrupt.throw_if_interrupted();
  if (opt.grad_support.defined() && !asked) {  // only the asked voxels' gradients are complete: the others are 0
    const auto keep = opt.grad_support.unsqueeze(0);
    if (need_sigma_t) gs.mul_(keep);
    if (need_albedo) ga.mul_(keep);
  }
  return {image, gs, ga, events, cut};
}

}  // namespace

std::tuple<torch::Tensor, torch::Tensor, int64_t> scene_backward_cpu(
    const torch::Tensor& grad_output, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, bool need_sigma_t, bool need_albedo,
    const SceneOptions& opt, double sigma_t_floor, double albedo_floor) {
  auto [image, gs, ga, events, cut] = backward_impl(grad_output, sigma_t, albedo, ref_sigma_t, ref_albedo,
                                                    need_sigma_t, need_albedo, opt, sigma_t_floor, albedo_floor, false);
  return {gs, ga, events};
}

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, ForwardCounts> scene_forward_backward_cpu(
    const torch::Tensor& grad_output, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, bool need_sigma_t, bool need_albedo,
    const SceneOptions& opt, double sigma_t_floor, double albedo_floor) {
  auto [image, gs, ga, events, cut] = backward_impl(grad_output, sigma_t, albedo, ref_sigma_t, ref_albedo,
                                                    need_sigma_t, need_albedo, opt, sigma_t_floor, albedo_floor, true);
  ForwardCounts counts;
  counts.scatter_events = events;
  counts.truncated_paths = cut;
  return {image, gs, ga, counts};
}

}  // namespace volpath
}  // namespace ta
