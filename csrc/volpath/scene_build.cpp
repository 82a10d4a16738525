// Scene building (see scene_build.h).
#include "volpath/scene_build.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <map>

namespace ta {
namespace volpath {
namespace detail {
namespace {

template <typename T>
void copy3(const std::vector<double>& v, T out[3]) {
  for (int k = 0; k < 3; ++k) out[k] = T(v[k]);
}

std::atomic<bool> g_skipping{true};  // set_empty_space_skipping (tests)
std::atomic<bool> g_core_walk{true};  // set_core_walk (tests)

// One pass of the separable Chebyshev distance transform along lines of n values at stride `stride`:
// g(i) = min_j max(|i − j|, f(j)), searched outwards from i until |i − j| reaches the best value found.
void minmax_pass(std::vector<int32_t>& f, int64_t lines, int64_t n, int64_t stride,
                 const std::vector<int64_t>& starts) {
  at::parallel_for(0, lines, 1, [&](int64_t l0, int64_t l1) {
    std::vector<int32_t> line(n), out(n);
    for (int64_t l = l0; l < l1; ++l) {
      const int64_t base = starts[l];
      for (int64_t i = 0; i < n; ++i) line[i] = f[base + i * stride];
      for (int64_t i = 0; i < n; ++i) {
        int32_t best = line[i];
        for (int64_t r = 1; r < best && (i - r >= 0 || i + r < n); ++r) {
          if (i - r >= 0) best = std::min(best, std::max(int32_t(r), line[i - r]));
          if (i + r < n) best = std::min(best, std::max(int32_t(r), line[i + r]));
        }
        out[i] = best;
      }
      for (int64_t i = 0; i < n; ++i) f[base + i * stride] = out[i];
    }
  });
}

// The exact Chebyshev distance transform of a brick grid (bx, by, bz) in which f holds 0 for the bricks that count
// and 255 for the others, capped at 255.
std::vector<uint8_t> chebyshev_bricks(std::vector<int32_t>& f, int64_t bx, int64_t by, int64_t bz) {
  std::vector<int64_t> starts;
  for (int64_t z = 0; z < bz; ++z)
    for (int64_t y = 0; y < by; ++y) starts.push_back((z * by + y) * bx);
  minmax_pass(f, bz * by, bx, 1, starts);
  starts.clear();
  for (int64_t z = 0; z < bz; ++z)
    for (int64_t x = 0; x < bx; ++x) starts.push_back(z * by * bx + x);
  minmax_pass(f, bz * bx, by, bx, starts);
  starts.clear();
  for (int64_t y = 0; y < by; ++y)
    for (int64_t x = 0; x < bx; ++x) starts.push_back(y * bx + x);
  minmax_pass(f, by * bx, bz, bx * by, starts);
  return std::vector<uint8_t>(f.begin(), f.end());
}

// The counts of bricks (core::kBrick³ voxels) along x, y, z of a D×H×W grid.
void brick_counts(int64_t D, int64_t H, int64_t W, int64_t bricks[3]) {
  const int64_t B = core::kBrick;
  bricks[0] = (W + B - 1) / B;
  bricks[1] = (H + B - 1) / B;
  bricks[2] = (D + B - 1) / B;
}

}  // namespace

std::vector<uint8_t> skip_distances(const uint8_t* cells, int64_t D, int64_t H, int64_t W, int64_t bricks[3]) {
  const int64_t B = core::kBrick;
  brick_counts(D, H, W, bricks);
  const int64_t bx = bricks[0], by = bricks[1], bz = bricks[2];
  // 0 for a brick holding a cell that is not outside, 255 otherwise
  std::vector<int32_t> f(bx * by * bz, 255);
  at::parallel_for(0, bz, 1, [&](int64_t z0, int64_t z1) {
    for (int64_t k = z0 * B; k < std::min(D, z1 * B); ++k)
      for (int64_t j = 0; j < H; ++j) {
        const uint8_t* row = cells + (k * H + j) * W;
        int32_t* brow = f.data() + ((k / B) * by + j / B) * bx;
        for (int64_t i = 0; i < W; ++i)
          if (row[i] != core::kCellOutside) brow[i / B] = 0;
      }
  });
  return chebyshev_bricks(f, bx, by, bz);
}

template <typename T>
void build_core(core::Scene<T>& S, SceneStorage& store, const bool* asked) {
  auto& M = S.medium;
  M.core = nullptr;
  if (!g_core_walk.load() || S.sdf.cell == nullptr) return;
  const int64_t B = core::kBrick, D = M.D, H = M.H, W = M.W, N = M.voxels();
  brick_counts(D, H, W, M.core_bricks);
  const int64_t bx = M.core_bricks[0], by = M.core_bricks[1], bz = M.core_bricks[2];
  // the values of voxel v: σ_t and albedo per channel, in the parameters and in the reference
  const auto values = [&](int64_t v, T out[12]) {
    for (int c = 0; c < 3; ++c) {
      out[c] = M.sigma_t[c * N + v];
      out[3 + c] = M.albedo[c * N + v];
      out[6 + c] = M.ref_sigma_t[c * N + v];
      out[9 + c] = M.ref_albedo[c * N + v];
    }
  };
  // per brick, its first voxel if the brick is uniform (else -1)
  std::vector<int64_t> first(bx * by * bz, -1);
  at::parallel_for(0, bz, 1, [&](int64_t z0, int64_t z1) {
    T ref[12], val[12];
    for (int64_t z = z0; z < z1; ++z)
      for (int64_t y = 0; y < by; ++y)
        for (int64_t x = 0; x < bx; ++x) {
          int64_t v0 = -1;
          bool uniform = true;
          for (int64_t k = z * B; uniform && k < std::min(D, (z + 1) * B); ++k)
            for (int64_t j = y * B; uniform && j < std::min(H, (y + 1) * B); ++j)
              for (int64_t i = x * B; uniform && i < std::min(W, (x + 1) * B); ++i) {
                const int64_t v = (k * H + j) * W + i;
                if (S.sdf.cell[v] != core::kCellInside || (asked != nullptr && asked[v])) {
                  uniform = false;
                } else if (v0 < 0) {
                  v0 = v;
                  values(v, ref);
                  for (int c = 0; c < 3; ++c)
                    uniform &= std::isfinite(ref[c]) && ref[c] > T(0) && std::isfinite(ref[3 + c]) &&
                               ref[6 + c] == ref[c] && ref[9 + c] == ref[3 + c];
                } else {
                  values(v, val);
                  for (int m = 0; m < 12; ++m) uniform &= val[m] == ref[m];
                }
              }
          first[(z * by + y) * bx + x] = uniform ? v0 : -1;
        }
  });
  // the tuple that most uniform bricks hold (ties: the smallest tuple)
  std::map<std::array<T, 6>, int64_t> count;
  const auto tuple = [&](int64_t v) {
    T val[12];
    values(v, val);
    std::array<T, 6> t;
    for (int m = 0; m < 6; ++m) t[m] = val[m];
    return t;
  };
  for (int64_t v : first)
    if (v >= 0) ++count[tuple(v)];
  if (count.empty()) return;
  auto best = count.begin();
  for (auto it = count.begin(); it != count.end(); ++it)
    if (it->second > best->second) best = it;
  std::vector<int32_t> f(first.size(), 0);  // 0 for the bricks that are not core
  for (size_t b = 0; b < first.size(); ++b)
    if (first[b] >= 0 && tuple(first[b]) == best->first) f[b] = 255;
  store.core = chebyshev_bricks(f, bx, by, bz);
  M.core = store.core.data();
  for (int c = 0; c < 3; ++c) {
    M.core_sigma_t[c] = best->first[c];
    M.core_albedo[c] = best->first[3 + c];
  }
}

template void build_core<float>(core::Scene<float>&, SceneStorage&, const bool*);
template void build_core<double>(core::Scene<double>&, SceneStorage&, const bool*);

// The scene of a D×H×W grid without its medium values (the caller points S.medium's channels at them).
template <typename T>
core::Scene<T> make_scene(const SceneOptions& o, int64_t D, int64_t H, int64_t W, at::ScalarType dtype,
                    SceneStorage& store) {
  core::Scene<T> S;
  auto& M = S.medium;
  M.D = D;
  M.H = H;
  M.W = W;
  copy3(o.voxel_size, M.voxel);
  copy3(o.origin, M.origin);
  if (o.boundary.kind == 1) {
    store.sdf = o.boundary.sdf.to(dtype).contiguous();
    const T* s = store.sdf.data_ptr<T>();
    store.cells.assign(M.voxels(), 0);
    const int64_t W1 = M.W + 1, HW1 = (M.H + 1) * W1;
    uint8_t* cells = store.cells.data();
    at::parallel_for(0, M.D, 1, [&](int64_t k0, int64_t k1) {
      for (int64_t k = k0; k < k1; ++k)
        for (int64_t j = 0; j < M.H; ++j)
          for (int64_t i = 0; i < M.W; ++i) {
            const T* b = s + k * HW1 + j * W1 + i;
            const T c[8] = {b[0], b[1], b[W1], b[W1 + 1], b[HW1], b[HW1 + 1], b[HW1 + W1], b[HW1 + W1 + 1]};
            bool all_neg = true, all_pos = true;
            for (T x : c) {
              all_neg &= x < T(0);
              all_pos &= x > T(0);
            }
            cells[(k * M.H + j) * M.W + i] = all_neg ? core::kCellInside : (all_pos ? core::kCellOutside : core::kCellMixed);
          }
    });
    S.sdf.sdf = s;
    S.sdf.cell = cells;
    if (g_skipping.load()) {
      store.skip = skip_distances(cells, M.D, M.H, M.W, S.sdf.bricks);
      S.sdf.skip = store.skip.data();
    }
  }
  S.ior = T(o.boundary.ior > 0 ? o.boundary.ior : 1.0);
  auto& se = S.sensor;
  se.kind = o.sensor.kind;
  se.face = o.sensor.face;
  if (se.kind == core::kSurfaceTexels) {
    store.points = o.sensor.points.to(dtype).contiguous();
    store.normals = o.sensor.normals.to(dtype).contiguous();
    store.radius = o.sensor.radius.to(dtype).contiguous();
    se.points = store.points.data_ptr<T>();
    se.normals = store.normals.data_ptr<T>();
    se.radius = store.radius.data_ptr<T>();
    se.count = store.points.size(0);
    se.lift = T(o.sensor.lift);
  }
  copy3(o.sensor.origin, se.origin);
  copy3(o.sensor.forward, se.forward);
  copy3(o.sensor.right, se.right);
  copy3(o.sensor.up, se.up);
  se.rows = o.sensor.rows;
  se.cols = o.sensor.cols;
  se.width = T(o.sensor.width);
  se.height = T(o.sensor.height);
  se.tan_half_fov = T(o.sensor.tan_half_fov);
  auto& e = S.emitter;
  e.kind = o.emitter.kind;
  copy3(o.emitter.radiance, e.radiance);
  copy3(o.emitter.ambient, e.ambient);
  copy3(o.emitter.direction, e.direction);
  e.cos_max = T(o.emitter.cos_max);
  if (e.kind == core::kEnvMap) {
    store.map = o.emitter.map.to(dtype).contiguous();
    e.map = store.map.data_ptr<T>();
    e.map_h = store.map.size(0);
    e.map_w = store.map.size(1);
  }
  S.g = T(o.g);
  S.spp = o.spp;
  S.seed = uint64_t(o.seed);
  S.max_depth = o.max_depth;
  S.rr_depth = o.rr_depth;
  return S;
}

template <typename T>
core::Scene<T> make_scene(const SceneOptions& o, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
                    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, SceneStorage& store) {
  core::Scene<T> S = make_scene<T>(o, sigma_t.size(1), sigma_t.size(2), sigma_t.size(3), sigma_t.scalar_type(), store);
  S.medium.sigma_t = sigma_t.data_ptr<T>();
  S.medium.albedo = albedo.data_ptr<T>();
  S.medium.ref_sigma_t = ref_sigma_t.data_ptr<T>();
  S.medium.ref_albedo = ref_albedo.data_ptr<T>();
  return S;
}


template <typename T>
core::Scene<T> make_palette_scene(const SceneOptions& o, const torch::Tensor& index, const torch::Tensor& sigma_t_table,
                                  const torch::Tensor& albedo_table, SceneStorage& store) {
  const int64_t D = index.size(0), H = index.size(1), W = index.size(2);
  core::Scene<T> S = make_scene<T>(o, D, H, W, sigma_t_table.scalar_type(), store);
  core::Channels<T> st, al;
  st.index = al.index = index.data_ptr<uint8_t>();
  st.voxels = al.voxels = D * H * W;
  st.entries = al.entries = sigma_t_table.size(1);
  st.plain = al.plain = false;
  st.palette = sigma_t_table.data_ptr<T>();
  al.palette = albedo_table.data_ptr<T>();
  S.medium.sigma_t = S.medium.ref_sigma_t = st;
  S.medium.albedo = S.medium.ref_albedo = al;
  build_core(S, store, nullptr);
  return S;
}

template core::Scene<float> make_palette_scene<float>(const SceneOptions&, const torch::Tensor&, const torch::Tensor&,
                                                      const torch::Tensor&, SceneStorage&);
template core::Scene<double> make_palette_scene<double>(const SceneOptions&, const torch::Tensor&,
                                                        const torch::Tensor&, const torch::Tensor&, SceneStorage&);

template core::Scene<float> make_scene<float>(const SceneOptions&, int64_t, int64_t, int64_t, at::ScalarType,
                                              SceneStorage&);
template core::Scene<double> make_scene<double>(const SceneOptions&, int64_t, int64_t, int64_t, at::ScalarType,
                                                SceneStorage&);
template core::Scene<float> make_scene<float>(const SceneOptions&, const torch::Tensor&, const torch::Tensor&,
                                              const torch::Tensor&, const torch::Tensor&, SceneStorage&);
template core::Scene<double> make_scene<double>(const SceneOptions&, const torch::Tensor&, const torch::Tensor&,
                                                const torch::Tensor&, const torch::Tensor&, SceneStorage&);

std::vector<int64_t> image_shape(const SceneOptions& o, int64_t H, int64_t W) {
  switch (o.sensor.kind) {
    case core::kFaceTexels:
      if (o.sensor.face == core::kFaceBoth) return {2, H, W, 3};
      return {H, W, 3};
    case core::kSurfaceTexels: return {o.sensor.points.size(0), 3};
    default: return {o.sensor.rows, o.sensor.cols, 3};
  }
}

}  // namespace detail

bool set_empty_space_skipping(bool on) { return detail::g_skipping.exchange(on); }
bool set_core_walk(bool on) { return detail::g_core_walk.exchange(on); }

}  // namespace volpath
}  // namespace ta
