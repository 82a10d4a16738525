// The forward kernel and its entry points (scene_forward_cpu, scene_forward_indexed_cpu): per sensor element, the
// walks of every sample (core::trace_path, or the SIMD slab or object walk where it serves), summed in sample order.
#include <ATen/Parallel.h>

#include <cstring>
#include <mutex>
#include <type_traits>
#include <vector>

#include "core/integrator.h"
#include "volpath/checks.h"
#include "volpath/dispatch.h"
#include "volpath/interrupt.h"
#include "volpath/scene_build.h"
#include "volpath/simd_glue.h"
#include "volpath/threading.h"
#include "volpath/volpath.h"

namespace ta {
namespace volpath {
namespace {

using core::Adjoint;
using core::Scene;
using namespace detail;

torch::Tensor g_tally;  // set_tally
std::mutex g_tally_mutex;

template <typename T, int LANES, int B, bool DIEL, bool RATIO, bool HERO>
ForwardCounts forward_kernel(const Scene<T>& S0, T* out, const Share& share) {
  std::vector<int64_t> tally;
  const uint8_t* bins = nullptr;
  torch::Tensor held;  // keeps the bins alive through the walk
  {
    const std::lock_guard<std::mutex> lock(g_tally_mutex);
    if (g_tally.defined()) {
      TORCH_CHECK(g_tally.dim() == 3 && g_tally.size(0) == S0.medium.D && g_tally.size(1) == S0.medium.H &&
                      g_tally.size(2) == S0.medium.W,
                  "tally: expected bins of the grid's shape (", S0.medium.D, ", ", S0.medium.H, ", ", S0.medium.W,
                  "), got ", g_tally.sizes());
      held = g_tally;
      bins = held.data_ptr<uint8_t>();
      tally.assign(512, 0);
    }
  }
  std::mutex tally_mutex;
  const int64_t nchunks = num_chunks(share.count);
  const bool constant = S0.emitter.kind == core::kConstant;
  std::vector<ForwardCounts> counts(nchunks);
  const Adjoint<T> none;
  const bool simd = simd_serves<T, LANES, B, HERO>(S0);
  const bool simd_object = bins == nullptr && simd_serves_object<T, LANES, B, HERO>(S0);
  std::vector<float> ref_pair;
  if constexpr (std::is_same_v<T, float>)
    if (simd) ref_pair = pack_reference(S0);
  for_each_chunk(nchunks, [&](int64_t c) {
    if constexpr (std::is_same_v<T, float> && LANES == 1 && B == core::kBoxBoundary && !HERO) {
      if (simd) {
        counts[c] = simd_forward_chunk<DIEL, RATIO>(S0, ref_pair.data(), out, c, nchunks, share);
        return;
      }
    }
    if constexpr (std::is_same_v<T, float> && B == core::kSDFBoundary && !HERO) {
      if (simd_object) {
        counts[c] = simd_object_forward_chunk<DIEL, RATIO, LANES>(S0, out, c, nchunks, share);
        return;
      }
    }
    std::vector<int64_t> local(bins != nullptr ? 512 : 0, 0);  // this chunk's tally
    Scene<T> S = S0;
    if (bins != nullptr) {
      S.tally_bin = bins;
      S.tally = local.data();
    }
    int64_t ev = 0, cut = 0, vsteps = 0, osteps = 0, cevents = 0;
    for_chunk_elements(S, c, nchunks, share, [&](int64_t t) {
      double acc[3] = {0, 0, 0};
      T Le[3];
      for (int64_t s = 0; s < S.spp; ++s) {
        if (LANES == 3) {
          const auto r =
              core::trace_path<T, 3, B, DIEL, RATIO, false, false, HERO>(S, t, s, 0, nullptr, nullptr, none);
          ev += r.scatter_events;
          cut += r.truncated;
          vsteps += r.voxel_steps;
          osteps += r.outside_steps;
          cevents += r.core_events;
          if (constant) {
            for (int l = 0; l < 3; ++l) acc[l] += double(r.value[l]);
          } else if (r.escaped) {
            S.emitter.eval(r.direction, Le);
            for (int l = 0; l < 3; ++l) acc[l] += double(r.value[l]) * double(Le[l]);
          }
        } else {
          for (int ch = 0; ch < 3; ++ch) {
            const auto r = core::trace_path<T, 1, B, DIEL, RATIO, false>(S, t, s, ch, nullptr, nullptr, none);
            ev += r.scatter_events;
            cut += r.truncated;
            vsteps += r.voxel_steps;
            osteps += r.outside_steps;
            cevents += r.core_events;
            if (constant) {
              acc[ch] += double(r.value[0]);
            } else if (r.escaped) {
              S.emitter.eval(r.direction, Le);
              acc[ch] += double(r.value[0]) * double(Le[ch]);
            }
          }
        }
      }
      for (int ch = 0; ch < 3; ++ch) out[t * 3 + ch] = element_radiance(S, acc[ch], ch);
    });
    counts[c] = {ev, cut, vsteps, osteps, cevents, {}};
    if (bins != nullptr) {
      const std::lock_guard<std::mutex> lock(tally_mutex);
      for (int i = 0; i < 512; ++i) tally[i] += local[i];
    }
  });
  ForwardCounts total;
  for (const auto& k : counts) {
    total.scatter_events += k.scatter_events;
    total.truncated_paths += k.truncated_paths;
    total.voxel_steps += k.voxel_steps;
    total.outside_steps += k.outside_steps;
    total.core_events += k.core_events;
  }
  total.tally = std::move(tally);
  return total;
}

}  // namespace

void set_tally(const torch::Tensor& bins) {
  if (bins.defined())
    TORCH_CHECK(bins.dim() == 3 && bins.scalar_type() == torch::kUInt8, "bins: expected a (D, H, W) uint8 tensor, got ",
                bins.sizes(), " ", bins.scalar_type());
  const std::lock_guard<std::mutex> lock(g_tally_mutex);
  g_tally = bins.defined() ? bins.contiguous() : torch::Tensor();
}

// The forward kernel of `opt`'s configuration (dispatch_scene) over this process's share of S's elements.
template <typename T>
ForwardCounts forward_scene(const Scene<T>& S, T* out, bool ratio, const SceneOptions& opt) {
  ForwardCounts counts;
  dispatch_scene(opt, [&]<int L, bool HERO, int B, bool DIEL>() {
    const Share share(S.elements(), opt.part_rank, opt.part_world);
    counts = ratio ? forward_kernel<T, L, B, DIEL, true, HERO>(S, out, share)
                   : forward_kernel<T, L, B, DIEL, false, HERO>(S, out, share);
  });
  return counts;
}

std::tuple<torch::Tensor, ForwardCounts> scene_forward_cpu(const torch::Tensor& sigma_t, const torch::Tensor& albedo,
                                                           const torch::Tensor& ref_sigma_t,
                                                           const torch::Tensor& ref_albedo, bool ratio,
                                                           const SceneOptions& opt) {
  check_all(sigma_t, albedo, ref_sigma_t, ref_albedo, opt);
  auto out = opt.part_world > 1 ? torch::zeros(image_shape(opt, sigma_t.size(2), sigma_t.size(3)), sigma_t.options())
                                : torch::empty(image_shape(opt, sigma_t.size(2), sigma_t.size(3)), sigma_t.options());
  ForwardCounts counts;
  const InterruptScope interrupt;
  AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "volpath_forward", [&] {
    using T = scalar_t;
    SceneStorage store;
    Scene<T> S = make_scene<T>(opt, sigma_t, albedo, ref_sigma_t, ref_albedo, store);
    build_core(S, store, nullptr);
    counts = forward_scene(S, out.data_ptr<T>(), ratio, opt);
  });
  interrupt.throw_if_interrupted();
  return {out, counts};
}

std::tuple<torch::Tensor, ForwardCounts> scene_forward_indexed_cpu(const torch::Tensor& index,
                                                                   const torch::Tensor& sigma_t_table,
                                                                   const torch::Tensor& albedo_table,
                                                                   const SceneOptions& opt) {
  check_palette(index, sigma_t_table, albedo_table, opt);
  const int64_t H = index.size(1), W = index.size(2);
  auto out = opt.part_world > 1 ? torch::zeros(image_shape(opt, H, W), sigma_t_table.options())
                                : torch::empty(image_shape(opt, H, W), sigma_t_table.options());
  ForwardCounts counts;
  const InterruptScope interrupt;
  AT_DISPATCH_FLOATING_TYPES(sigma_t_table.scalar_type(), "volpath_forward_indexed", [&] {
    using T = scalar_t;
    SceneStorage store;
    const Scene<T> S = make_palette_scene<T>(opt, index, sigma_t_table, albedo_table, store);
    counts = forward_scene(S, out.data_ptr<T>(), false, opt);
  });
  interrupt.throw_if_interrupted();
  return {out, counts};
}

std::tuple<torch::Tensor, ForwardCounts> scene_forward_from_bytes_cpu(const torch::Tensor& scene_bytes,
                                                                      at::ScalarType dtype, bool ratio,
                                                                      const SceneOptions& opt) {
  TORCH_CHECK_VALUE(dtype == at::kFloat || dtype == at::kDouble, "dtype: expected float32 or float64, got ", dtype);
  TORCH_CHECK_VALUE(scene_bytes.defined() && scene_bytes.device().is_cpu() && scene_bytes.scalar_type() == at::kByte &&
                        scene_bytes.dim() == 1 && scene_bytes.is_contiguous(),
                    "scene_bytes: expected a contiguous CPU uint8 tensor (N,)");
  TORCH_CHECK_VALUE(opt.lanes == 1 || opt.lanes == 3, "options.lanes: expected 1 or 3, got ", opt.lanes);
  torch::Tensor out;
  ForwardCounts counts;
  const InterruptScope interrupt;
  AT_DISPATCH_FLOATING_TYPES(dtype, "volpath_forward_from_bytes", [&] {
    using T = scalar_t;
    TORCH_CHECK_VALUE(scene_bytes.numel() == int64_t(sizeof(Scene<T>)), "scene_bytes: expected ", sizeof(Scene<T>),
                      " bytes (core::Scene<", dtype, ">), got ", scene_bytes.numel());
    Scene<T> S;
    std::memcpy(&S, scene_bytes.data_ptr(), sizeof(S));
    TORCH_CHECK_VALUE(S.sensor.kind == opt.sensor.kind && (S.sdf.sdf != nullptr) == (opt.boundary.kind == 1) &&
                          S.spp == opt.spp && S.tally == nullptr,
                      "scene_bytes: expected the scene of `options` (sensor, boundary, spp), got another");
    auto shape = image_shape(opt, S.medium.H, S.medium.W);
    out = opt.part_world > 1 ? torch::zeros(shape, torch::TensorOptions().dtype(dtype))
                             : torch::empty(shape, torch::TensorOptions().dtype(dtype));
    counts = forward_scene(S, out.data_ptr<T>(), ratio, opt);
  });
  interrupt.throw_if_interrupted();
  return {out, counts};
}

}  // namespace volpath
}  // namespace ta
