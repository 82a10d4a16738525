// The input checks of the entry points (see checks.h).
#include "volpath/checks.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/defs.h"

namespace ta {
namespace volpath {
namespace detail {
namespace {

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

}  // namespace

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
template void check_values<float>(const torch::Tensor&, const char*, float, float);
template void check_values<double>(const torch::Tensor&, const char*, double, double);

template <typename T>
void check_finite(const torch::Tensor& x, const char* name) {
  bool finite = true;
  const T* g = x.data_ptr<T>();
  for (int64_t i = 0; i < x.numel(); ++i) finite &= std::isfinite(g[i]);
  TORCH_CHECK(finite, name, ": expected finite values");
}
template void check_finite<float>(const torch::Tensor&, const char*);
template void check_finite<double>(const torch::Tensor&, const char*);

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
  if (o.grad_support.defined()) {
    const auto& m = o.grad_support;
    TORCH_CHECK(m.device().is_cpu() && m.scalar_type() == at::kBool && m.is_contiguous() && m.dim() == 3 &&
                    m.size(0) == D && m.size(1) == H && m.size(2) == W,
                "grad_support: expected a contiguous CPU bool tensor of the grid's shape (", D, ", ", H, ", ", W,
                "), got ", m.scalar_type(), " ", m.sizes());
  }
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

void check_all(const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
               const torch::Tensor& ref_albedo, const SceneOptions& opt, double sigma_t_floor) {
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

void check_palette(const torch::Tensor& index, const torch::Tensor& sigma_t_table, const torch::Tensor& albedo_table,
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
  AT_DISPATCH_FLOATING_TYPES(sigma_t_table.scalar_type(), "volpath_check_palette", [&] {
    using T = scalar_t;
    check_values<T>(sigma_t_table, "sigma_t_table", 0, std::numeric_limits<T>::max());
    check_values<T>(albedo_table, "albedo_table", 0, 1);
    if (opt.lanes == 3) {
      const T* r = sigma_t_table.data_ptr<T>();
      bool same = true;
      for (int64_t k = 0; k < P; ++k) same &= (r[k] == r[P + k]) & (r[k] == r[2 * P + k]);
      TORCH_CHECK(same, "sigma_t_table: lanes=3 (one walk for all channels) needs equal channels");
    }
  });
}

void check_floors(double sigma_t_floor, double albedo_floor) {
  TORCH_CHECK(std::isfinite(sigma_t_floor) && sigma_t_floor >= 0, "sigma_t_floor: expected a finite value >= 0, got ",
              sigma_t_floor);
  TORCH_CHECK(albedo_floor >= 0 && albedo_floor <= 1, "albedo_floor: expected a value in [0, 1], got ", albedo_floor);
}

void check_grad_output(const torch::Tensor& grad_output, const torch::Tensor& sigma_t, int64_t expected) {
  TORCH_CHECK(grad_output.device().is_cpu() && grad_output.scalar_type() == sigma_t.scalar_type(),
              "grad_output: expected a CPU tensor of dtype ", sigma_t.scalar_type());
  TORCH_CHECK(grad_output.numel() == expected, "grad_output: expected ", expected, " elements, got ",
              grad_output.numel());
}

}  // namespace detail
}  // namespace volpath
}  // namespace ta
