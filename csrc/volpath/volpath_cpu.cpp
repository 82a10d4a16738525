// Glue between PyTorch tensors and the torch-free tracing core (csrc/core/): checks, flattening of the scene
// pieces into core structs, template dispatch, threading.
#include "volpath/volpath.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <type_traits>
#include <vector>

#include "core/integrator.h"
#include "volpath/slab_simd.h"

namespace ta {
namespace volpath {
namespace {

using core::Adjoint;
using core::PathResult;
using core::Scene;

constexpr int64_t kTexelBlock = 8;  // sensor elements handed out together (limits false sharing of output rows)

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
  const bool ok = at::parallel_reduce(
      int64_t(0), x.numel(), int64_t(1) << 16, true,
      [&](int64_t b, int64_t e, bool acc) {
        for (int64_t i = b; i < e; ++i) acc &= (p[i] >= lo) & (p[i] <= hi);  // false for NaN
        return acc;
      },
      [](bool a, bool b) { return a && b; });
  TORCH_CHECK(ok, name, ": expected finite values in [", lo, ", ", hi, "]");
}

// The same grid (the sampling medium is often the medium itself, detached: another tensor over the same memory).
bool same_grid(const torch::Tensor& a, const torch::Tensor& b) {
  return a.is_same(b) || (a.data_ptr() == b.data_ptr() && a.scalar_type() == b.scalar_type() &&
                          a.sizes() == b.sizes() && a.strides() == b.strides());
}

void check_vec(const std::vector<double>& v, const char* name, double lo, double hi) {
  TORCH_CHECK(v.size() == 3, name, ": expected 3 values, got ", v.size());
  for (double x : v) TORCH_CHECK(std::isfinite(x) && x >= lo && x <= hi, name, ": expected finite values in [", lo,
                                 ", ", hi, "], got ", x);
}

void check_unit(const std::vector<double>& v, const char* name) {
  check_vec(v, name, -1.0, 1.0);
  const double n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  TORCH_CHECK(std::abs(n2 - 1.0) < 1e-6, name, ": expected a unit vector, got squared length ", n2);
}

// A (rows..., cols) float tensor that the glue converts to the grid's dtype.
void check_float_tensor(const torch::Tensor& x, const char* name, std::vector<int64_t> shape) {
  TORCH_CHECK(x.defined(), name, ": expected a tensor, got None");
  TORCH_CHECK(x.device().is_cpu(), name, ": expected a CPU tensor, got device ", x.device());
  TORCH_CHECK(x.is_floating_point(), name, ": expected a floating-point tensor, got ", x.scalar_type());
  TORCH_CHECK(x.dim() == int64_t(shape.size()), name, ": expected ", shape.size(), " dimensions, got ", x.sizes());
  for (size_t i = 0; i < shape.size(); ++i)
    TORCH_CHECK(shape[i] < 0 || x.size(i) == shape[i], name, ": expected size ", shape[i], " in dimension ", i,
                ", got ", x.sizes());
  // in chunks: torch::isfinite of a float tensor allocates |x| and a bool tensor of its size (a float32 copy of a
  // 364 M-corner printer-resolution SDF is 1.5 GB)
  const auto flat = x.reshape(-1);
  for (int64_t a = 0; a < flat.numel(); a += int64_t(1) << 22)
    TORCH_CHECK(torch::isfinite(flat.slice(0, a, std::min(flat.numel(), a + (int64_t(1) << 22)))).all().item<bool>(),
                name, ": expected finite values");
}

void check_scene(const SceneOptions& o, int64_t D, int64_t H, int64_t W) {
  TORCH_CHECK(D >= 1 && H >= 1 && W >= 1, "sigma_t: expected a non-empty grid, got (3, ", D, ", ", H, ", ", W, ")");
  TORCH_CHECK(D * H * W < (int64_t(1) << 40), "sigma_t: grid too large");
  TORCH_CHECK(o.voxel_size.size() == 3, "voxel_size: expected 3 edges (x, y, z), got ", o.voxel_size.size());
  for (double s : o.voxel_size)
    TORCH_CHECK(std::isfinite(s) && s > 0, "voxel_size: expected finite edges > 0, got ", s);
  check_vec(o.origin, "origin", -1e30, 1e30);
  TORCH_CHECK(std::isfinite(o.g) && std::abs(o.g) < 1, "g: expected -1 < g < 1, got ", o.g);
  TORCH_CHECK(o.spp >= 1 && o.spp < (int64_t(1) << 32), "spp: expected 1 <= spp < 2^32, got ", o.spp);
  TORCH_CHECK(o.max_depth >= 1, "max_depth: expected >= 1, got ", o.max_depth);
  TORCH_CHECK(o.rr_depth >= 0, "rr_depth: expected >= 0, got ", o.rr_depth);
  TORCH_CHECK(o.lanes == 1 || o.lanes == 3, "lanes: expected 1 or 3, got ", o.lanes);
  TORCH_CHECK(o.hero == 0 || o.hero == 1, "hero: expected 0 or 1, got ", o.hero);
  TORCH_CHECK(o.hero == 0 || o.lanes == 3, "hero: the hero-channel walk serves three lanes, got lanes=", o.lanes);
  TORCH_CHECK(o.part_world >= 1 && o.part_rank >= 0 && o.part_rank < o.part_world,
              "partition: expected 0 <= rank < world, got rank ", o.part_rank, " of ", o.part_world);
  // boundary
  const auto& b = o.boundary;
  TORCH_CHECK(b.kind == 0 || b.kind == 1, "boundary: expected kind 0 (box) or 1 (sdf), got ", b.kind);
  TORCH_CHECK(b.ior <= 0 || (std::isfinite(b.ior) && b.ior >= 1),
              "ior: expected >= 1 (or <= 0 for index matched), got ", b.ior);
  if (b.kind == 1) {
    check_float_tensor(b.sdf, "sdf", {D + 1, H + 1, W + 1});
    const auto& s = b.sdf;  // only the six outer faces are converted (not a float64 copy of the whole grid)
    const auto outer = torch::cat({s.select(0, 0).flatten(), s.select(0, D).flatten(), s.select(1, 0).flatten(),
                                   s.select(1, H).flatten(), s.select(2, 0).flatten(), s.select(2, W).flatten()})
                           .to(at::kDouble);
    TORCH_CHECK((outer > 0).all().item<bool>(),
                "sdf: expected > 0 on the grid's outer corners (the object must lie strictly inside the grid)");
  }
  // sensor
  const auto& se = o.sensor;
  TORCH_CHECK(se.kind >= 0 && se.kind <= 3, "sensor: expected kind 0..3, got ", se.kind);
  if (se.kind == 0) {
    TORCH_CHECK(b.kind == 0, "sensor: face texels need the box boundary");
    TORCH_CHECK(se.face >= 0 && se.face <= 2, "face: expected 0 (top), 1 (bottom) or 2 (both), got ", se.face);
    TORCH_CHECK(2 * H * W < (int64_t(1) << 32), "sigma_t: grid too large for 32-bit texel counters");
  } else if (se.kind == 1) {
    check_float_tensor(se.points, "points", {-1, 3});
    const int64_t n = se.points.size(0);
    TORCH_CHECK(n >= 1 && n < (int64_t(1) << 32), "points: expected 1 <= N < 2^32 texels, got ", n);
    check_float_tensor(se.normals, "normals", {n, 3});
    check_float_tensor(se.radius, "footprint", {n});
    const auto nn = se.normals.to(at::kDouble);
    TORCH_CHECK(((nn * nn).sum(1) - 1).abs().max().item<double>() < 1e-4, "normals: expected unit vectors");
    TORCH_CHECK((se.radius >= 0).all().item<bool>(), "footprint: expected radii >= 0");
    TORCH_CHECK(std::isfinite(se.lift) && se.lift >= 0, "lift: expected a finite value >= 0, got ", se.lift);
  } else {
    check_vec(se.origin, "camera origin", -1e30, 1e30);
    check_unit(se.forward, "camera forward");
    check_unit(se.right, "camera right");
    check_unit(se.up, "camera up");
    TORCH_CHECK(se.rows >= 1 && se.cols >= 1 && se.rows * se.cols < (int64_t(1) << 32),
                "resolution: expected 1 <= rows, cols and rows·cols < 2^32, got (", se.rows, ", ", se.cols, ")");
    if (se.kind == 2) {
      TORCH_CHECK(std::isfinite(se.width) && se.width > 0 && std::isfinite(se.height) && se.height > 0,
                  "extent_mm: expected finite values > 0, got (", se.width, ", ", se.height, ")");
    } else {
      TORCH_CHECK(std::isfinite(se.tan_half_fov) && se.tan_half_fov > 0,
                  "fov_y_deg: expected a field of view in (0, 180) degrees");
    }
  }
  // emitter
  const auto& e = o.emitter;
  TORCH_CHECK(e.kind >= 0 && e.kind <= 2, "emitter: expected kind 0..2, got ", e.kind);
  check_vec(e.radiance, "radiance", 0.0, 1e30);
  check_vec(e.ambient, "ambient", 0.0, 1e30);
  if (e.kind == 1) {
    check_float_tensor(e.map, "image", {-1, -1, 3});
    TORCH_CHECK(e.map.size(0) >= 1 && e.map.size(1) >= 1, "image: expected a non-empty (H, W, 3) map");
    TORCH_CHECK((e.map >= 0).all().item<bool>(), "image: expected radiance >= 0");
  }
  if (e.kind == 2) {
    check_unit(e.direction, "direction");
    TORCH_CHECK(std::isfinite(e.cos_max) && e.cos_max >= -1 && e.cos_max <= 1,
                "angular_radius_deg: expected cos in [-1, 1], got ", e.cos_max);
  }
}

// Keeps the converted tensors alive while a Scene<T> points into them.
struct SceneStorage {
  torch::Tensor sdf, points, normals, radius, map;
  std::vector<uint8_t> cells;
};

template <typename T>
void copy3(const std::vector<double>& v, T out[3]) {
  for (int k = 0; k < 3; ++k) out[k] = T(v[k]);
}

// The scene of a D×H×W grid without its medium values (the caller points S.medium's channels at them).
template <typename T>
Scene<T> make_scene(const SceneOptions& o, int64_t D, int64_t H, int64_t W, at::ScalarType dtype,
                    SceneStorage& store) {
  Scene<T> S;
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
Scene<T> make_scene(const SceneOptions& o, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
                    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, SceneStorage& store) {
  Scene<T> S = make_scene<T>(o, sigma_t.size(1), sigma_t.size(2), sigma_t.size(3), sigma_t.scalar_type(), store);
  S.medium.sigma_t = sigma_t.data_ptr<T>();
  S.medium.albedo = albedo.data_ptr<T>();
  S.medium.ref_sigma_t = ref_sigma_t.data_ptr<T>();
  S.medium.ref_albedo = ref_albedo.data_ptr<T>();
  return S;
}

// Static, strided work split: chunk c owns element blocks c, c + n, c + 2n, ... . The split depends only on the
// number of chunks (= threads), so sums are deterministic for a given thread count, and strided blocks balance
// spatially varying path lengths.
template <typename F>
void for_each_chunk(int64_t nchunks, const F& body) {
  at::parallel_for(0, nchunks, 1, [&](int64_t begin, int64_t end) {
    for (int64_t c = begin; c < end; ++c) body(c);
  });
}

// The sensor elements this process traces: t = rank + world·u for u < count (all of them when world = 1).
struct Share {
  int64_t rank = 0, world = 1, count = 0;
  Share(int64_t n, int64_t r, int64_t w) : rank(r), world(w), count(r < n ? (n - r + w - 1) / w : 0) {}
  int64_t element(int64_t u) const { return rank + world * u; }
};

template <typename F>
void for_elements_of_chunk(int64_t c, int64_t nchunks, const Share& share, const F& body) {
  const int64_t n = share.count;
  for (int64_t b0 = c * kTexelBlock; b0 < n; b0 += nchunks * kTexelBlock)
    for (int64_t u = b0, e = std::min(n, b0 + kTexelBlock); u < e; ++u) body(share.element(u));
}

int64_t num_chunks(int64_t n) {
  const int64_t blocks = (n + kTexelBlock - 1) / kTexelBlock;
  return std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), blocks));
}

// ---- the SIMD slab walk (slab_simd.h): eight or sixteen paths per thread at once where the scene allows it
// The widest SIMD walk this CPU runs: 2 AVX-512F, 1 AVX2, 0 none (libgcc also checks that the OS saves the registers).
int cpu_simd_level() {
#if (defined(__x86_64__) || defined(__i386__)) && defined(__GNUC__)
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx512f")) return 2;
  return __builtin_cpu_supports("avx2") ? 1 : 0;
#else
  return 0;
#endif
}

// -1: not decided yet (the CPU and TA_SIMD decide at first use); 0 the scalar walk; 1 AVX2; 2 AVX-512. set_simd (tests,
// benchmarks) overrides.
std::atomic<int> g_simd{-1};

int simd_level() {
  int v = g_simd.load();
  if (v < 0) {
    const char* env = std::getenv("TA_SIMD");
    v = cpu_simd_level();
    if (env && env[0] == '0') v = 0;
    else if (env && std::strcmp(env, "avx2") == 0) v = std::min(v, 1);
    g_simd.store(v);
  }
  return v;
}
bool simd_enabled() { return simd_level() > 0; }

// TA_SIMD_ENDED_LANES: flights that end before the SIMD walk's collision phase runs (0: its default); for tuning
int simd_ended_lanes() {
  static const int v = [] {
    const char* env = std::getenv("TA_SIMD_ENDED_LANES");
    return env ? std::atoi(env) : 0;
  }();
  return v;
}

// The SIMD walk of the selected width.
void slab_walks(const simd::SlabWalkScene& S, const int64_t* elems, const uint8_t* live, int64_t n, bool ratio,
                const simd::LaneTapes* tapes, simd::WalkDone done, void* ctx) {
  if (simd_level() == 2) simd::slab_walks_avx512(S, elems, live, n, ratio, tapes, simd_ended_lanes(), done, ctx);
  else simd::slab_walks_avx2(S, elems, live, n, ratio, tapes, simd_ended_lanes(), done, ctx);
}

constexpr int64_t kSimdBatch = 256;                 // sensor elements per call of the SIMD walk
constexpr int64_t kSimdSegments = int64_t(1) << 16;  // tape entries per lane (longer paths: scalar replay)
static_assert(kSimdSegments <= simd::kMaxTapeCap, "the SIMD walk's tape offsets are int32");

// Whether the SIMD slab walk serves this scene: float32 dense grids, box boundary, face texels, constant emitter.
template <typename T, int LANES, int B, bool HERO>
bool simd_serves(const Scene<T>& S) {
  if constexpr (!std::is_same_v<T, float> || LANES != 1 || B != core::kBoxBoundary || HERO) {
    return false;
  } else {
    const auto& M = S.medium;
    return simd_enabled() && S.sensor.kind == core::kFaceTexels && S.emitter.kind == core::kConstant &&
           M.sigma_t.index == nullptr && M.albedo.index == nullptr && M.ref_sigma_t.index == nullptr &&
           M.ref_albedo.index == nullptr && M.sigma_t.plain && M.albedo.plain && 3 * M.voxels() < (int64_t(1) << 31);
  }
}

// The reference σ_t and albedo side by side, voxel by voxel (SlabWalkScene::ref_pair), for the SIMD walk.
std::vector<float> pack_reference(const Scene<float>& S) {
  const auto& M = S.medium;
  const int64_t n = 3 * M.voxels();
  std::vector<float> pair(size_t(2 * n));
  const float* s = M.ref_sigma_t.data;
  const float* a = M.ref_albedo.data;
  float* out = pair.data();
  at::parallel_for(0, n, 1 << 16, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) {
      out[2 * i] = s[i];
      out[2 * i + 1] = a[i];
    }
  });
  return pair;
}

simd::SlabWalkScene simd_scene(const Scene<float>& S, const float* ref_pair) {
  simd::SlabWalkScene W;
  const auto& M = S.medium;
  W.ref_pair = ref_pair;
  W.sigma_t = M.sigma_t.data;
  W.albedo = M.albedo.data;
  W.ref_sigma_t = M.ref_sigma_t.data;
  W.ref_albedo = M.ref_albedo.data;
  W.ref_sigma_t_floor = M.ref_sigma_t.plain ? 0.0f : M.ref_sigma_t.floor;
  W.ref_albedo_floor = M.ref_albedo.plain ? 0.0f : M.ref_albedo.floor;
  W.D = int32_t(M.D);
  W.H = int32_t(M.H);
  W.W = int32_t(M.W);
  for (int a = 0; a < 3; ++a) W.voxel[a] = M.voxel[a];
  W.g = S.g;
  W.ior = S.ior;
  W.face = S.sensor.face;
  W.seed = S.seed;
  W.max_depth = S.max_depth;
  W.rr_depth = S.rr_depth;
  W.spp = S.spp;
  return W;
}

// Face texels of chunk c (of this process's share) in tiles of kTile × kTile texels, tiles dealt to the chunks in
// turn: the paths of neighbouring texels read the same voxels, so a tile's grid stays in the caches (on a 760²
// slab, 1.4× faster than rows of texels).
constexpr int64_t kTile = 16;

template <typename T, typename F>
void for_tiled_face_elements(const Scene<T>& S, int64_t c, int64_t nchunks, const Share& share, const F& body) {
  const int64_t H = S.medium.H, W = S.medium.W;
  const int64_t faces = S.sensor.face == core::kFaceBoth ? 2 : 1;
  const int64_t ny = (H + kTile - 1) / kTile, nx = (W + kTile - 1) / kTile;
  for (int64_t q = c; q < faces * ny * nx; q += nchunks) {
    const int64_t f = q / (ny * nx), ty = (q % (ny * nx)) / nx, tx = q % nx;
    for (int64_t j = ty * kTile; j < std::min(H, (ty + 1) * kTile); ++j)
      for (int64_t i = tx * kTile; i < std::min(W, (tx + 1) * kTile); ++i) {
        const int64_t t = (f * H + j) * W + i;
        if (t % share.world == share.rank) body(t);
      }
  }
}

// The elements of chunk c: face texels in tiles, other sensors' elements in strided blocks.
template <typename T, typename F>
void for_chunk_elements(const Scene<T>& S, int64_t c, int64_t nchunks, const Share& share, const F& body) {
  if (S.sensor.kind == core::kFaceTexels) for_tiled_face_elements(S, c, nchunks, share, body);
  else for_elements_of_chunk(c, nchunks, share, body);
}

// Forward of one chunk with the SIMD walk: per batch of elements, every path's value, then the per-element sums in
// sample order (as the scalar kernel adds them, so the image does not depend on the order the lanes finish in).
template <bool DIEL, bool RATIO>
ForwardCounts simd_forward_chunk(const Scene<float>& S, const float* ref_pair, float* out, int64_t c, int64_t nchunks,
                                 const Share& share) {
  simd::SlabWalkScene W = simd_scene(S, ref_pair);
  W.dielectric = DIEL;
  struct Ctx {
    std::vector<float> values;
    int64_t ev = 0, cut = 0;
  } ctx;
  std::vector<int64_t> elems;
  elems.reserve(kSimdBatch);
  ForwardCounts counts;
  auto flush = [&]() {
    if (elems.empty()) return;
    const int64_t n = int64_t(elems.size());
    ctx.values.assign(size_t(n * S.spp * 3), 0.0f);
    slab_walks(W, elems.data(), nullptr, n, RATIO, nullptr,
               [](void* p, const simd::WalkOut& o) {
                 auto* x = static_cast<Ctx*>(p);
                 x->values[size_t(o.item)] = o.value;
                 x->ev += o.scatter_events;
                 x->cut += o.truncated;
               },
               &ctx);
    for (int64_t k = 0; k < n; ++k) {
      double acc[3] = {0, 0, 0};
      for (int64_t s = 0; s < S.spp; ++s)
        for (int ch = 0; ch < 3; ++ch) acc[ch] += double(ctx.values[size_t((k * S.spp + s) * 3 + ch)]);
      for (int ch = 0; ch < 3; ++ch)
        out[elems[k] * 3 + ch] = float(acc[ch] * double(S.emitter.radiance[ch]) / double(S.spp));
    }
    elems.clear();
  };
  for_tiled_face_elements(S, c, nchunks, share, [&](int64_t t) {
    elems.push_back(t);
    if (int64_t(elems.size()) == kSimdBatch) flush();
  });
  flush();
  counts.scatter_events = ctx.ev;
  counts.truncated_paths = ctx.cut;
  return counts;
}

template <typename T, int LANES, int B, bool DIEL, bool RATIO, bool HERO>
ForwardCounts forward_kernel(const Scene<T>& S, T* out, const Share& share) {
  const int64_t nchunks = num_chunks(share.count);
  const bool constant = S.emitter.kind == core::kConstant;
  std::vector<ForwardCounts> counts(nchunks);
  const Adjoint<T> none;
  const bool simd = simd_serves<T, LANES, B, HERO>(S);
  std::vector<float> ref_pair;
  if constexpr (std::is_same_v<T, float>)
    if (simd) ref_pair = pack_reference(S);
  for_each_chunk(nchunks, [&](int64_t c) {
    if constexpr (std::is_same_v<T, float> && LANES == 1 && B == core::kBoxBoundary && !HERO) {
      if (simd) {
        counts[c] = simd_forward_chunk<DIEL, RATIO>(S, ref_pair.data(), out, c, nchunks, share);
        return;
      }
    }
    int64_t ev = 0, cut = 0;
    for_chunk_elements(S, c, nchunks, share, [&](int64_t t) {
      double acc[3] = {0, 0, 0};
      T Le[3];
      for (int64_t s = 0; s < S.spp; ++s) {
        if (LANES == 3) {
          const auto r =
              core::trace_path<T, 3, B, DIEL, RATIO, false, false, HERO>(S, t, s, 0, nullptr, nullptr, none);
          ev += r.scatter_events;
          cut += r.truncated;
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
            if (constant) {
              acc[ch] += double(r.value[0]);
            } else if (r.escaped) {
              S.emitter.eval(r.direction, Le);
              acc[ch] += double(r.value[0]) * double(Le[ch]);
            }
          }
        }
      }
      for (int ch = 0; ch < 3; ++ch)
        out[t * 3 + ch] = constant ? T(acc[ch] * double(S.emitter.radiance[ch]) / double(S.spp))
                                   : T(acc[ch] / double(S.spp));
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

// Per-thread tape of the single-walk replay (core/tape.h). It starts small and doubles (up to a cap) when a path
// overflows it; a path that overflows is replayed with the two-pass method, so every path is exact.
std::atomic<int64_t> g_initial_tape_segments{int64_t(1) << 14};  // set_tape_capacity (tests)

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

// Replays one path: a single walk that records its events in the tape, then the deposit of ∂/∂θ (only escaped paths
// that see a non-zero emitter carry any). A path that does not fit the tape is walked once more, depositing as it
// goes (the two-pass replay). `g` is grad_output of the element (3 channels).
template <typename T, int LANES, int B, bool DIEL, bool HERO>
inline int64_t replay(const Scene<T>& S, int64_t t, int64_t s, int ch, const T* g, const Adjoint<T>& A,
                      TapeStore<T, LANES>& store) {
  auto& tape = store.tape;
  tape.clear();
  const auto r1 =
      core::trace_path<T, LANES, B, DIEL, true, false, true, HERO>(S, t, s, ch, nullptr, nullptr, A, &tape);
  if (!r1.escaped) return r1.scatter_events;
  T Le[3], adj[LANES];
  S.emitter.eval(r1.direction, Le);
  bool any = false;
  for (int l = 0; l < LANES; ++l) {
    const int c = LANES == 1 ? ch : l;
    adj[l] = g[c] * Le[c] / T(S.spp);
    any |= adj[l] != T(0);
  }
  if (!any) return r1.scatter_events;
  if (!tape.overflow) {
    core::deposit_tape<T, LANES>(tape, r1.value, r1.prod_nonzero, r1.zeros, ch, adj, A, S.medium.voxels());
    return r1.scatter_events;
  }
  store.grow();
  const auto r2 = core::trace_path<T, LANES, B, DIEL, true, true, false, HERO>(S, t, s, ch, &r1, adj, A);
  return r1.scatter_events + r2.scatter_events;
}

// core::deposit_tape<float, 1> for the SIMD walk's compact tape (slab_simd.h), with the σ_t deposits of one voxel in a
// row summed before they are added (a flight that ends by a collision and the next flight's first segment there).
void deposit_simd_tape(const simd::WalkOut& o, int ch, float adj, const Adjoint<float>& A, int64_t N) {
  float* gs = A.grad_sigma_t ? A.grad_sigma_t + ch * N : nullptr;
  float* ga = A.grad_albedo ? A.grad_albedo + ch * N : nullptr;
  const float av = adj * o.value;
  int64_t cur = -1;  // the voxel of the pending σ_t deposit
  float run = 0.0f;
  auto add_s = [&](int64_t v, float d) {
    if (v == cur) {
      run += d;
      return;
    }
    if (cur >= 0) gs[cur] += run;
    cur = v;
    run = d;
  };
  int64_t s = 0;
  for (int64_t k = 0; k < o.ncol; ++k) {
    const simd::TapeCollisionF& col = o.cols[k];
    if (gs) {
      for (; s < col.seg_end; ++s) add_s(o.segs[s].v, -(av * o.segs[s].len));
      add_s(col.v, adj * core::weight_without(col.fs, o.value, o.prod_nonzero, int(o.zeros)) / col.sref);
    }
    if (ga) ga[col.v] += adj * core::weight_without(col.fa, o.value, o.prod_nonzero, int(o.zeros)) * col.inv_psq;
  }
  if (gs) {
    for (; s < o.nseg; ++s) add_s(o.segs[s].v, -(av * o.segs[s].len));
    if (cur >= 0) gs[cur] += run;
  }
}

// Gradient replay of one chunk with the SIMD walk: the lanes record their paths' tapes, and each path is deposited
// (deposit_simd_tape) when it ends; a path longer than its lane's tape is replayed by the scalar
// code from the start (walk and deposit), so every deposit belongs to the walk that produced its weight.
template <bool DIEL>
int64_t simd_backward_chunk(const Scene<float>& S, const float* ref_pair, const float* grad_out,
                            const Adjoint<float>& A, TapeStore<float, 1>& store, int64_t c, int64_t nchunks,
                            const Share& share) {
  simd::SlabWalkScene W = simd_scene(S, ref_pair);
  W.dielectric = DIEL;
  const int64_t seg_cap = std::min(kSimdSegments, g_initial_tape_segments.load());  // (tests set it to 0 or 4)
  // the lanes' tapes, for all the batches of this chunk (not zeroed: only the pages the paths reach are touched)
  simd::LaneTapes tapes;
  tapes.seg_cap = seg_cap;
  tapes.col_cap = seg_cap / 2;
  std::unique_ptr<simd::TapeSegmentF[]> seg_buf(new simd::TapeSegmentF[size_t(simd::kMaxLanes * (seg_cap + 1))]);
  std::unique_ptr<simd::TapeCollisionF[]> col_buf(
      new simd::TapeCollisionF[size_t(simd::kMaxLanes * (tapes.col_cap + 1))]);
  tapes.segs = seg_buf.get();
  tapes.cols = col_buf.get();
  struct Ctx {
    const Scene<float>* S;
    const float* grad_out;
    const Adjoint<float>* A;
    TapeStore<float, 1>* store;
    const int64_t* elems;
    int64_t ev = 0;
  } ctx{&S, grad_out, &A, &store, nullptr};
  std::vector<int64_t> elems;
  std::vector<uint8_t> live;
  elems.reserve(kSimdBatch);
  live.reserve(kSimdBatch);
  const bool constant = S.emitter.kind == core::kConstant;
  auto flush = [&]() {
    if (elems.empty()) return;
    ctx.elems = elems.data();
    slab_walks(
        W, elems.data(), live.data(), int64_t(elems.size()), true, &tapes,
        [](void* p, const simd::WalkOut& o) {
          auto* x = static_cast<Ctx*>(p);
          const Scene<float>& S = *x->S;
          const int64_t spp = S.spp;
          const int ch = int(o.item % 3);
          const int64_t s = (o.item / 3) % spp, t = x->elems[o.item / (3 * spp)];
          const float* g = x->grad_out + t * 3;
          x->ev += o.scatter_events;
          if (o.overflow) {  // too long for the lane's tape: the scalar replay walks it again and deposits
            x->ev += replay<float, 1, core::kBoxBoundary, DIEL, false>(S, t, s, ch, g, *x->A, *x->store);
            return;
          }
          if (!o.escaped) return;
          const float adj[1] = {g[ch] * S.emitter.radiance[ch] / float(spp)};
          if (adj[0] == 0.0f) return;
          deposit_simd_tape(o, ch, adj[0], *x->A, S.medium.voxels());
        },
        &ctx);
    elems.clear();
    live.clear();
  };
  for_tiled_face_elements(S, c, nchunks, share, [&](int64_t t) {
    const float* g = grad_out + t * 3;
    uint8_t bitsv = 0;
    for (int ch = 0; ch < 3; ++ch)
      if (g[ch] != 0.0f && !(constant && S.emitter.radiance[ch] == 0.0f)) bitsv |= uint8_t(1 << ch);
    if (!bitsv) return;
    elems.push_back(t);
    live.push_back(bitsv);
    if (int64_t(elems.size()) == kSimdBatch) flush();
  });
  flush();
  return ctx.ev;
}

// A gradient buffer of n zeros from calloc: a large block comes fresh from the kernel, so the pages that the deposits
// never touch are never resident (an object's paths touch the voxels near its surface, not its whole bounding box).
template <typename T>
struct ZeroedBuffer {
  std::unique_ptr<T, void (*)(void*)> p{nullptr, std::free};
  explicit ZeroedBuffer(int64_t n) : p(static_cast<T*>(std::calloc(size_t(n), sizeof(T))), std::free) {
    TORCH_CHECK(p != nullptr, "volpath backward: could not allocate a gradient buffer of ", n * int64_t(sizeof(T)),
                " bytes");
  }
  T* data() const { return p.get(); }
};

template <typename T, int LANES, int B, bool DIEL, bool HERO>
int64_t backward_kernel(const Scene<T>& S, const T* grad_out, T* gs, T* ga, const Share& share) {
  const int64_t nchunks = num_chunks(share.count);
  const int64_t n = 3 * S.medium.voxels();
  // chunk 0 accumulates into the outputs; the others into their own buffers, summed in chunk order below
  std::vector<ZeroedBuffer<T>> bufs_s, bufs_a;
  for (int64_t c = 1; c < nchunks; ++c) {
    if (gs) bufs_s.emplace_back(n);
    if (ga) bufs_a.emplace_back(n);
  }
  std::vector<int64_t> events(nchunks, 0);
  const bool constant = S.emitter.kind == core::kConstant;
  const bool simd = simd_serves<T, LANES, B, HERO>(S);
  std::vector<float> ref_pair;
  if constexpr (std::is_same_v<T, float>)
    if (simd) ref_pair = pack_reference(S);
  for_each_chunk(nchunks, [&](int64_t c) {
    Adjoint<T> A;
    if (gs) {
      if (c == 0) A.grad_sigma_t = gs;
      else A.grad_sigma_t = bufs_s[c - 1].data();
    }
    if (ga) {
      if (c == 0) A.grad_albedo = ga;
      else A.grad_albedo = bufs_a[c - 1].data();
    }
    int64_t ev = 0;
    TapeStore<T, LANES> store;
    if constexpr (std::is_same_v<T, float> && LANES == 1 && B == core::kBoxBoundary && !HERO) {
      if (simd) {
        events[c] = simd_backward_chunk<DIEL>(S, ref_pair.data(), grad_out, A, store, c, nchunks, share);
        return;
      }
    }
    for_chunk_elements(S, c, nchunks, share, [&](int64_t t) {
      const T* g = grad_out + t * 3;
      bool live[3], any = false;  // channels whose paths can carry a derivative
      for (int ch = 0; ch < 3; ++ch) {
        live[ch] = g[ch] != T(0) && !(constant && S.emitter.radiance[ch] == T(0));
        any |= live[ch];
      }
      if (!any) return;
      for (int64_t s = 0; s < S.spp; ++s) {
        if constexpr (LANES == 3) {
          ev += replay<T, 3, B, DIEL, HERO>(S, t, s, 0, g, A, store);
        } else {
          for (int ch = 0; ch < 3; ++ch)
            if (live[ch]) ev += replay<T, 1, B, DIEL, false>(S, t, s, ch, g, A, store);
        }
      }
    });
    events[c] = ev;
  });
  // deterministic reduction in chunk order, parallel over voxels
  auto reduce = [&](T* out, const std::vector<ZeroedBuffer<T>>& bufs) {
    if (!out || bufs.empty()) return;
    at::parallel_for(0, n, 1 << 14, [&](int64_t b, int64_t e) {
      for (const auto& buf : bufs) {
        const T* x = buf.data();
        for (int64_t i = b; i < e; ++i) out[i] += x[i];
      }
    });
  };
  reduce(gs, bufs_s);
  reduce(ga, bufs_a);
  int64_t total = 0;
  for (int64_t e : events) total += e;
  return total;
}

// Runtime flags → template instance: f(lanes, hero, boundary kind, dielectric) (hero only with three lanes).
template <typename F>
void dispatch_scene(int64_t lanes, bool hero, int boundary, bool dielectric, const F& f) {
  auto with_diel = [&](auto lanes_c, auto hero_c, auto bound_c) {
    if (dielectric) f(lanes_c, hero_c, bound_c, std::true_type{});
    else f(lanes_c, hero_c, bound_c, std::false_type{});
  };
  auto with_bound = [&](auto lanes_c, auto hero_c) {
    if (boundary == core::kSDFBoundary)
      with_diel(lanes_c, hero_c, std::integral_constant<int, core::kSDFBoundary>{});
    else
      with_diel(lanes_c, hero_c, std::integral_constant<int, core::kBoxBoundary>{});
  };
  if (lanes == 3 && hero) with_bound(std::integral_constant<int, 3>{}, std::true_type{});
  else if (lanes == 3) with_bound(std::integral_constant<int, 3>{}, std::false_type{});
  else with_bound(std::integral_constant<int, 1>{}, std::false_type{});
}

void check_all(const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
               const torch::Tensor& ref_albedo, const SceneOptions& opt, double sigma_t_floor = 0) {
  check_grid(sigma_t, "sigma_t", sigma_t);
  check_grid(albedo, "albedo", sigma_t);
  check_grid(ref_sigma_t, "sampling_sigma_t", sigma_t);
  check_grid(ref_albedo, "sampling_albedo", sigma_t);
  check_scene(opt, sigma_t.size(1), sigma_t.size(2), sigma_t.size(3));
  AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "volpath_check", [&] {
    const scalar_t inf = std::numeric_limits<scalar_t>::max();
    check_values<scalar_t>(sigma_t, "sigma_t", 0, inf);
    check_values<scalar_t>(albedo, "albedo", 0, 1);
    if (!same_grid(ref_sigma_t, sigma_t)) check_values<scalar_t>(ref_sigma_t, "sampling_sigma_t", 0, inf);
    if (!same_grid(ref_albedo, albedo)) check_values<scalar_t>(ref_albedo, "sampling_albedo", 0, 1);
    if (opt.lanes == 3 && !opt.hero) {
      const scalar_t* r = ref_sigma_t.data_ptr<scalar_t>();
      const int64_t n = ref_sigma_t.numel() / 3;
      const auto f = scalar_t(sigma_t_floor);
      bool same = true;
      for (int64_t i = 0; i < n; ++i) {
        const scalar_t a = core::tmax(r[i], f);
        same &= (a == core::tmax(r[n + i], f)) & (a == core::tmax(r[2 * n + i], f));
      }
      TORCH_CHECK(same, "sampling_sigma_t: lanes=3 (one walk for all channels) needs equal channels");
    }
  });
}

std::vector<int64_t> image_shape(const SceneOptions& o, int64_t H, int64_t W) {
  switch (o.sensor.kind) {
    case core::kFaceTexels:
      if (o.sensor.face == core::kFaceBoth) return {2, H, W, 3};
      return {H, W, 3};
    case core::kSurfaceTexels: return {o.sensor.points.size(0), 3};
    default: return {o.sensor.rows, o.sensor.cols, 3};
  }
}

}  // namespace

int64_t set_simd(int64_t mode) {
  TORCH_CHECK(mode >= -1 && mode <= 2, "mode: expected -1 (automatic), 0 (scalar), 1 (AVX2) or 2 (AVX-512), got ",
              mode);
  TORCH_CHECK(mode <= cpu_simd_level(), "mode: this CPU cannot run ", mode == 2 ? "AVX-512F" : "AVX2");
  const int before = simd_level();
  g_simd.store(int(mode));
  return before;
}

int64_t set_tape_capacity(int64_t segments) {
  TORCH_CHECK(segments >= 0, "segments: expected >= 0, got ", segments);
  return g_initial_tape_segments.exchange(segments);
}

std::tuple<torch::Tensor, ForwardCounts> scene_forward_cpu(const torch::Tensor& sigma_t, const torch::Tensor& albedo,
                                                           const torch::Tensor& ref_sigma_t,
                                                           const torch::Tensor& ref_albedo, bool ratio,
                                                           const SceneOptions& opt) {
  check_all(sigma_t, albedo, ref_sigma_t, ref_albedo, opt);
  auto out = opt.part_world > 1 ? torch::zeros(image_shape(opt, sigma_t.size(2), sigma_t.size(3)), sigma_t.options())
                                : torch::empty(image_shape(opt, sigma_t.size(2), sigma_t.size(3)), sigma_t.options());
  ForwardCounts counts;
  AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "volpath_forward", [&] {
    using T = scalar_t;
    SceneStorage store;
    const Scene<T> S = make_scene<T>(opt, sigma_t, albedo, ref_sigma_t, ref_albedo, store);
    dispatch_scene(opt.lanes, opt.hero, opt.boundary.kind, opt.boundary.ior > 0,
                   [&](auto lanes_c, auto hero_c, auto bound_c, auto diel_c) {
      constexpr int L = decltype(lanes_c)::value;
      constexpr bool HERO = decltype(hero_c)::value;
      constexpr int B = decltype(bound_c)::value;
      constexpr bool DIEL = decltype(diel_c)::value;
      const Share share(S.elements(), opt.part_rank, opt.part_world);
      counts = ratio ? forward_kernel<T, L, B, DIEL, true, HERO>(S, out.data_ptr<T>(), share)
                     : forward_kernel<T, L, B, DIEL, false, HERO>(S, out.data_ptr<T>(), share);
    });
  });
  return {out, counts};
}

std::tuple<torch::Tensor, torch::Tensor, int64_t> scene_backward_cpu(
    const torch::Tensor& grad_output, const torch::Tensor& sigma_t, const torch::Tensor& albedo,
    const torch::Tensor& ref_sigma_t, const torch::Tensor& ref_albedo, bool need_sigma_t, bool need_albedo,
    const SceneOptions& opt, double sigma_t_floor, double albedo_floor) {
  TORCH_CHECK(std::isfinite(sigma_t_floor) && sigma_t_floor >= 0, "sigma_t_floor: expected a finite value >= 0, got ",
              sigma_t_floor);
  TORCH_CHECK(albedo_floor >= 0 && albedo_floor <= 1, "albedo_floor: expected a value in [0, 1], got ", albedo_floor);
  check_all(sigma_t, albedo, ref_sigma_t, ref_albedo, opt, sigma_t_floor);
  int64_t expected = 1;
  for (int64_t s : image_shape(opt, sigma_t.size(2), sigma_t.size(3))) expected *= s;
  TORCH_CHECK(grad_output.device().is_cpu() && grad_output.scalar_type() == sigma_t.scalar_type(),
              "grad_output: expected a CPU tensor of dtype ", sigma_t.scalar_type());
  TORCH_CHECK(grad_output.numel() == expected, "grad_output: expected ", expected, " elements, got ",
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
    SceneStorage store;
    Scene<T> S = make_scene<T>(opt, sigma_t, albedo, ref_sigma_t, ref_albedo, store);
    S.medium.ref_sigma_t.floor = T(sigma_t_floor);  // the sampling medium max(ref, floor), read without a copy
    S.medium.ref_albedo.floor = T(albedo_floor);
    S.medium.ref_sigma_t.plain = !(sigma_t_floor > 0);
    S.medium.ref_albedo.plain = !(albedo_floor > 0);
    T* pgs = need_sigma_t ? gs.data_ptr<T>() : nullptr;
    T* pga = need_albedo ? ga.data_ptr<T>() : nullptr;
    dispatch_scene(opt.lanes, opt.hero, opt.boundary.kind, opt.boundary.ior > 0,
                   [&](auto lanes_c, auto hero_c, auto bound_c, auto diel_c) {
      constexpr int L = decltype(lanes_c)::value;
      constexpr bool HERO = decltype(hero_c)::value;
      constexpr int B = decltype(bound_c)::value;
      constexpr bool DIEL = decltype(diel_c)::value;
      events = backward_kernel<T, L, B, DIEL, HERO>(S, g, pgs, pga,
                                                    Share(S.elements(), opt.part_rank, opt.part_world));
    });
  });
  return {gs, ga, events};
}

std::tuple<torch::Tensor, ForwardCounts> scene_forward_indexed_cpu(const torch::Tensor& index,
                                                                   const torch::Tensor& sigma_t_table,
                                                                   const torch::Tensor& albedo_table,
                                                                   const SceneOptions& opt) {
  TORCH_CHECK(index.defined() && index.device().is_cpu() && index.scalar_type() == at::kByte && index.dim() == 3 &&
                  index.is_contiguous(),
              "index: expected a contiguous CPU uint8 tensor of shape (D, H, W)");
  for (const auto* t : {&sigma_t_table, &albedo_table}) {
    const char* name = t == &sigma_t_table ? "sigma_t_table" : "albedo_table";
    TORCH_CHECK(t->defined() && t->device().is_cpu(), name, ": expected a CPU tensor");
    TORCH_CHECK(t->scalar_type() == at::kFloat || t->scalar_type() == at::kDouble, name,
                ": expected dtype float32 or float64, got ", t->scalar_type());
    TORCH_CHECK(t->dim() == 2 && t->size(0) == 3 && t->size(1) >= 1 && t->size(1) <= 256 && t->is_contiguous(), name,
                ": expected a contiguous (3, P) palette with 1 <= P <= 256, got ", t->sizes());
  }
  TORCH_CHECK(albedo_table.sizes() == sigma_t_table.sizes() && albedo_table.scalar_type() == sigma_t_table.scalar_type(),
              "albedo_table: expected the shape and dtype of sigma_t_table");
  const int64_t D = index.size(0), H = index.size(1), W = index.size(2), P = sigma_t_table.size(1);
  check_scene(opt, D, H, W);
  const uint8_t* idx = index.data_ptr<uint8_t>();
  uint8_t top = 0;
  for (int64_t i = 0; i < index.numel(); ++i) top = std::max(top, idx[i]);
  TORCH_CHECK(int64_t(top) < P, "index: expected entries < P = ", P, " (the palette size), got ", int(top));
  auto out = opt.part_world > 1 ? torch::zeros(image_shape(opt, H, W), sigma_t_table.options())
                                : torch::empty(image_shape(opt, H, W), sigma_t_table.options());
  ForwardCounts counts;
  AT_DISPATCH_FLOATING_TYPES(sigma_t_table.scalar_type(), "volpath_forward_indexed", [&] {
    using T = scalar_t;
    check_values<T>(sigma_t_table, "sigma_t_table", 0, std::numeric_limits<T>::max());
    check_values<T>(albedo_table, "albedo_table", 0, 1);
    if (opt.lanes == 3) {
      const T* r = sigma_t_table.data_ptr<T>();
      bool same = true;
      for (int64_t k = 0; k < P; ++k) same &= (r[k] == r[P + k]) & (r[k] == r[2 * P + k]);
      TORCH_CHECK(same, "sigma_t_table: lanes=3 (one walk for all channels) needs equal channels");
    }
    SceneStorage store;
    Scene<T> S = make_scene<T>(opt, D, H, W, sigma_t_table.scalar_type(), store);
    core::Channels<T> st, al;
    st.index = al.index = idx;
    st.voxels = al.voxels = D * H * W;
    st.entries = al.entries = P;
    st.plain = al.plain = false;
    st.palette = sigma_t_table.data_ptr<T>();
    al.palette = albedo_table.data_ptr<T>();
    S.medium.sigma_t = S.medium.ref_sigma_t = st;
    S.medium.albedo = S.medium.ref_albedo = al;
    dispatch_scene(opt.lanes, opt.hero, opt.boundary.kind, opt.boundary.ior > 0,
                   [&](auto lanes_c, auto hero_c, auto bound_c, auto diel_c) {
      constexpr int L = decltype(lanes_c)::value;
      constexpr bool HERO = decltype(hero_c)::value;
      constexpr int B = decltype(bound_c)::value;
      constexpr bool DIEL = decltype(diel_c)::value;
      counts = forward_kernel<T, L, B, DIEL, false, HERO>(S, out.data_ptr<T>(), Share(S.elements(), opt.part_rank,
                                                                                      opt.part_world));
    });
  });
  return {out, counts};
}

}  // namespace volpath
}  // namespace ta
