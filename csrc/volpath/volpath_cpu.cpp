// Glue between PyTorch tensors and the tracing core (tracer.h): checks, template dispatch, threading.
#include "volpath/volpath.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "volpath/tracer.h"

namespace ta {
namespace volpath {
namespace {

constexpr int64_t kTexelBlock = 8;  // texels handed out together (limits false sharing of output rows)

void check_grid(const torch::Tensor& x, const char* name, const torch::Tensor& like) {
  TORCH_CHECK(x.defined(), name, ": expected a tensor, got None");
  TORCH_CHECK(x.device().is_cpu(), name, ": expected a CPU tensor, got device ", x.device());
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, name,
              ": expected dtype float32 or float64, got ", x.scalar_type());
  TORCH_CHECK(x.dim() == 4 && x.size(0) == 3, name, ": expected shape (3, D, H, W), got ", x.sizes());
  TORCH_CHECK(x.is_contiguous(), name, ": expected a contiguous tensor");
  TORCH_CHECK(x.sizes() == like.sizes(), name, ": expected shape ", like.sizes(), " (that of sigma_t), got ",
              x.sizes());
  TORCH_CHECK(x.scalar_type() == like.scalar_type(), name, ": expected dtype ", like.scalar_type(),
              " (that of sigma_t), got ", x.scalar_type());
}

// Values are checked again here (the Python layer checks first): nothing reaches the walk that could
// make it loop forever or produce NaN.
template <typename T>
void check_values(const torch::Tensor& x, const char* name, T lo, T hi) {
  const T* p = x.data_ptr<T>();
  const int64_t n = x.numel();
  bool ok = true;
  for (int64_t i = 0; i < n; ++i) ok &= (p[i] >= lo) & (p[i] <= hi);  // false for NaN
  TORCH_CHECK(ok, name, ": expected finite values in [", lo, ", ", hi, "]");
}

void check_options(const TraceOptions& o, int64_t D, int64_t H, int64_t W) {
  TORCH_CHECK(D >= 1 && H >= 1 && W >= 1, "sigma_t: expected a non-empty grid, got (3, ", D, ", ", H, ", ", W, ")");
  TORCH_CHECK(D * H * W < (int64_t(1) << 40) && 2 * H * W < (int64_t(1) << 32),
              "sigma_t: grid too large for 32-bit texel counters");
  TORCH_CHECK(o.voxel_size.size() == 3, "voxel_size: expected 3 edges (x, y, z), got ", o.voxel_size.size());
  for (double s : o.voxel_size)
    TORCH_CHECK(std::isfinite(s) && s > 0, "voxel_size: expected finite edges > 0, got ", s);
  TORCH_CHECK(o.face >= 0 && o.face <= 2, "face: expected 0 (top), 1 (bottom) or 2 (both), got ", o.face);
  TORCH_CHECK(std::isfinite(o.g) && std::abs(o.g) < 1, "g: expected -1 < g < 1, got ", o.g);
  TORCH_CHECK(o.ior <= 0 || (std::isfinite(o.ior) && o.ior >= 1), "ior: expected >= 1 (or <= 0 for index matched), got ",
              o.ior);
  TORCH_CHECK(o.environment.size() == 3, "environment: expected 3 values, got ", o.environment.size());
  for (double e : o.environment)
    TORCH_CHECK(std::isfinite(e) && e >= 0, "environment: expected finite values >= 0, got ", e);
  TORCH_CHECK(o.spp >= 1 && o.spp < (int64_t(1) << 32), "spp: expected 1 <= spp < 2^32, got ", o.spp);
  TORCH_CHECK(o.max_depth >= 1, "max_depth: expected >= 1, got ", o.max_depth);
  TORCH_CHECK(o.rr_depth >= 0, "rr_depth: expected >= 0, got ", o.rr_depth);
  TORCH_CHECK(o.lanes == 1 || o.lanes == 3, "lanes: expected 1 or 3, got ", o.lanes);
}

template <typename T>
Params<T> make_params(const TraceOptions& o, const torch::Tensor& sigma_t) {
  Params<T> P;
  P.D = sigma_t.size(1);
  P.H = sigma_t.size(2);
  P.W = sigma_t.size(3);
  for (int a = 0; a < 3; ++a) P.voxel[a] = T(o.voxel_size[a]);
  P.g = T(o.g);
  P.ior = T(o.ior > 0 ? o.ior : 1.0);
  for (int c = 0; c < 3; ++c) P.env[c] = T(o.environment[c]);
  P.spp = o.spp;
  P.seed = uint64_t(o.seed);
  P.max_depth = o.max_depth;
  P.rr_depth = o.rr_depth;
  P.face = o.face;
  return P;
}

// Static, strided work split: chunk c owns texel blocks c, c + n, c + 2n, ... . The split depends only on the
// number of chunks (= threads), so sums are deterministic for a given thread count, and strided blocks balance
// spatially varying path lengths.
template <typename F>
void for_each_chunk(int64_t nchunks, const F& body) {
  at::parallel_for(0, nchunks, 1, [&](int64_t begin, int64_t end) {
    for (int64_t c = begin; c < end; ++c) body(c);
  });
}

template <typename F>
void for_texels_of_chunk(int64_t c, int64_t nchunks, int64_t ntexels, const F& body) {
  for (int64_t b0 = c * kTexelBlock; b0 < ntexels; b0 += nchunks * kTexelBlock)
    for (int64_t t = b0, e = std::min(ntexels, b0 + kTexelBlock); t < e; ++t) body(t);
}

int64_t num_chunks(int64_t ntexels) {
  const int64_t blocks = (ntexels + kTexelBlock - 1) / kTexelBlock;
  return std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), blocks));
}

template <typename T, int LANES, bool DIEL, bool RATIO>
ForwardCounts forward_kernel(const Params<T>& P, const Grids<T>& G, T* out) {
  const int64_t ntex = P.faces() * P.texels_per_face();
  const int64_t nchunks = num_chunks(ntex);
  std::vector<ForwardCounts> counts(nchunks);
  const Adjoint<T> none;
  for_each_chunk(nchunks, [&](int64_t c) {
    int64_t ev = 0, cut = 0;
    for_texels_of_chunk(c, nchunks, ntex, [&](int64_t t) {
      double acc[3] = {0, 0, 0};
      for (int64_t s = 0; s < P.spp; ++s) {
        if (LANES == 3) {
          const auto r = trace_path<T, 3, DIEL, RATIO, false>(P, G, t, s, 0, nullptr, nullptr, none);
          ev += r.scatter_events;
          cut += r.truncated;
          for (int l = 0; l < 3; ++l) acc[l] += double(r.value[l]);
        } else {
          for (int ch = 0; ch < 3; ++ch) {
            const auto r = trace_path<T, 1, DIEL, RATIO, false>(P, G, t, s, ch, nullptr, nullptr, none);
            ev += r.scatter_events;
            cut += r.truncated;
            acc[ch] += double(r.value[0]);
          }
        }
      }
      for (int ch = 0; ch < 3; ++ch) out[t * 3 + ch] = T(acc[ch] * double(P.env[ch]) / double(P.spp));
    });
    counts[c] = {ev, cut};
  });
  ForwardCounts total;
  for (const auto& k : counts) {
    total.scatter_events += k.scatter_events;
    total.truncated_paths += k.truncated_paths;
  }
  return total;
}

// Replays one path twice: first for its final weight, then depositing ∂/∂θ (only escaped paths carry any).
template <typename T, int LANES, bool DIEL>
inline int64_t replay(const Params<T>& P, const Grids<T>& G, int64_t t, int64_t s, int ch, const T* adj,
                      const Adjoint<T>& A) {
  const Adjoint<T> none;
  const auto r1 = trace_path<T, LANES, DIEL, true, false>(P, G, t, s, ch, nullptr, nullptr, none);
  if (!r1.escaped) return r1.scatter_events;
  const auto r2 = trace_path<T, LANES, DIEL, true, true>(P, G, t, s, ch, &r1, adj, A);
  return r1.scatter_events + r2.scatter_events;
}

template <typename T, int LANES, bool DIEL>
int64_t backward_kernel(const Params<T>& P, const Grids<T>& G, const T* grad_out, T* gs, T* ga) {
  const int64_t ntex = P.faces() * P.texels_per_face();
  const int64_t nchunks = num_chunks(ntex);
  const int64_t n = 3 * P.voxels();
  // chunk 0 accumulates into the outputs; the others into their own buffers, summed in chunk order below
  std::vector<std::vector<T>> bufs_s(gs ? nchunks - 1 : 0), bufs_a(ga ? nchunks - 1 : 0);
  std::vector<int64_t> events(nchunks, 0);
  for_each_chunk(nchunks, [&](int64_t c) {
    Adjoint<T> A;
    if (gs) {
      if (c == 0) A.grad_sigma_t = gs;
      else { bufs_s[c - 1].assign(n, T(0)); A.grad_sigma_t = bufs_s[c - 1].data(); }
    }
    if (ga) {
      if (c == 0) A.grad_albedo = ga;
      else { bufs_a[c - 1].assign(n, T(0)); A.grad_albedo = bufs_a[c - 1].data(); }
    }
    int64_t ev = 0;
    for_texels_of_chunk(c, nchunks, ntex, [&](int64_t t) {
      T adj[3];
      bool any = false;
      for (int ch = 0; ch < 3; ++ch) {
        adj[ch] = grad_out[t * 3 + ch] * P.env[ch] / T(P.spp);
        any |= adj[ch] != T(0);
      }
      if (!any) return;
      for (int64_t s = 0; s < P.spp; ++s) {
        if (LANES == 3) {
          ev += replay<T, 3, DIEL>(P, G, t, s, 0, adj, A);
        } else {
          for (int ch = 0; ch < 3; ++ch)
            if (adj[ch] != T(0)) ev += replay<T, 1, DIEL>(P, G, t, s, ch, &adj[ch], A);
        }
      }
    });
    events[c] = ev;
  });
  // deterministic reduction in chunk order, parallel over voxels
  auto reduce = [&](T* out, std::vector<std::vector<T>>& bufs) {
    if (!out || bufs.empty()) return;
    at::parallel_for(0, n, 1 << 14, [&](int64_t b, int64_t e) {
      for (const auto& buf : bufs)
        for (int64_t i = b; i < e; ++i) out[i] += buf[i];
    });
  };
  reduce(gs, bufs_s);
  reduce(ga, bufs_a);
  int64_t total = 0;
  for (int64_t e : events) total += e;
  return total;
}

// Runtime flags → template instance.
template <typename F>
void dispatch_scene(int64_t lanes, bool dielectric, const F& f) {
  auto with_diel = [&](auto lanes_c) {
    if (dielectric) f(lanes_c, std::true_type{});
    else f(lanes_c, std::false_type{});
  };
  if (lanes == 3) with_diel(std::integral_constant<int, 3>{});
  else with_diel(std::integral_constant<int, 1>{});
}

void check_all(const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
               const torch::Tensor& ref_albedo, const TraceOptions& opt) {
  check_grid(sigma_t, "sigma_t", sigma_t);
  check_grid(albedo, "albedo", sigma_t);
  check_grid(ref_sigma_t, "sampling_sigma_t", sigma_t);
  check_grid(ref_albedo, "sampling_albedo", sigma_t);
  check_options(opt, sigma_t.size(1), sigma_t.size(2), sigma_t.size(3));
  AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "volpath_check", [&] {
    const scalar_t inf = std::numeric_limits<scalar_t>::max();
    check_values<scalar_t>(sigma_t, "sigma_t", 0, inf);
    check_values<scalar_t>(albedo, "albedo", 0, 1);
    if (!ref_sigma_t.is_same(sigma_t)) check_values<scalar_t>(ref_sigma_t, "sampling_sigma_t", 0, inf);
    if (!ref_albedo.is_same(albedo)) check_values<scalar_t>(ref_albedo, "sampling_albedo", 0, 1);
    if (opt.lanes == 3) {
      const scalar_t* r = ref_sigma_t.data_ptr<scalar_t>();
      const int64_t n = ref_sigma_t.numel() / 3;
      bool same = true;
      for (int64_t i = 0; i < n; ++i) same &= (r[i] == r[n + i]) & (r[i] == r[2 * n + i]);
      TORCH_CHECK(same, "sampling_sigma_t: lanes=3 (one walk for all channels) needs equal channels");
    }
  });
}

}  // namespace

std::tuple<torch::Tensor, ForwardCounts> forward_cpu(const torch::Tensor& sigma_t, const torch::Tensor& albedo,
                                               const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo,
                                               bool ratio, const TraceOptions& opt) {
  check_all(sigma_t, albedo, ref_sigma_t, ref_albedo, opt);
  const int64_t F = opt.face == Face::Both ? 2 : 1;
  auto out = torch::empty({F, sigma_t.size(2), sigma_t.size(3), 3}, sigma_t.options());
  ForwardCounts counts;
  AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "volpath_forward", [&] {
    using T = scalar_t;
    const Params<T> P = make_params<T>(opt, sigma_t);
    const Grids<T> G{sigma_t.data_ptr<T>(), albedo.data_ptr<T>(), ref_sigma_t.data_ptr<T>(),
                     ref_albedo.data_ptr<T>()};
    dispatch_scene(opt.lanes, opt.ior > 0, [&](auto lanes_c, auto diel_c) {
      constexpr int L = decltype(lanes_c)::value;
      constexpr bool DIEL = decltype(diel_c)::value;
      counts = ratio ? forward_kernel<T, L, DIEL, true>(P, G, out.data_ptr<T>())
                     : forward_kernel<T, L, DIEL, false>(P, G, out.data_ptr<T>());
    });
  });
  if (F == 1) out = out.squeeze(0);
  return {out, counts};
}

std::tuple<torch::Tensor, torch::Tensor, int64_t> backward_cpu(
    const torch::Tensor& grad_output, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, bool need_sigma_t, bool need_albedo,
    const TraceOptions& opt) {
  check_all(sigma_t, albedo, ref_sigma_t, ref_albedo, opt);
  const int64_t F = opt.face == Face::Both ? 2 : 1;
  TORCH_CHECK(grad_output.device().is_cpu() && grad_output.scalar_type() == sigma_t.scalar_type(),
              "grad_output: expected a CPU tensor of dtype ", sigma_t.scalar_type());
  TORCH_CHECK(grad_output.numel() == F * sigma_t.size(2) * sigma_t.size(3) * 3,
              "grad_output: expected ", F * sigma_t.size(2) * sigma_t.size(3) * 3, " elements, got ",
              grad_output.numel());
  const auto go = grad_output.contiguous();
  torch::Tensor gs, ga;
  if (need_sigma_t) gs = torch::zeros_like(sigma_t);
  if (need_albedo) ga = torch::zeros_like(albedo);
  int64_t events = 0;
  if (!need_sigma_t && !need_albedo) return {gs, ga, events};
  AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "volpath_backward", [&] {
    using T = scalar_t;
    bool finite = true;
    const T* g = go.data_ptr<T>();
    for (int64_t i = 0; i < go.numel(); ++i) finite &= std::isfinite(g[i]);
    TORCH_CHECK(finite, "grad_output: expected finite values");
    const Params<T> P = make_params<T>(opt, sigma_t);
    const Grids<T> G{sigma_t.data_ptr<T>(), albedo.data_ptr<T>(), ref_sigma_t.data_ptr<T>(),
                     ref_albedo.data_ptr<T>()};
    T* pgs = need_sigma_t ? gs.data_ptr<T>() : nullptr;
    T* pga = need_albedo ? ga.data_ptr<T>() : nullptr;
    dispatch_scene(opt.lanes, opt.ior > 0, [&](auto lanes_c, auto diel_c) {
      constexpr int L = decltype(lanes_c)::value;
      constexpr bool DIEL = decltype(diel_c)::value;
      events = backward_kernel<T, L, DIEL>(P, G, g, pgs, pga);
    });
  });
  return {gs, ga, events};
}

}  // namespace volpath
}  // namespace ta
