// The scene of a render on another device (the CUDA glue's launcher, torch_appearance/render/cuda_launch.py): built on
// the host exactly as the CPU entry points build theirs (make_scene, the floors of the replay, build_core), then
// relocated (relocate.h) into tensors on the target device, and handed over as the bytes of the core::Scene<T>.
//
// The checks and the scene's derived buffers (the SDF's cell kinds and skip distances, the homogeneous core) are
// computed on the host, from host copies of the grids when these live on the device (one device-to-host copy of the
// four grids per call; the device's copies of the grids are used by the walk as they are, not copied back).
#include <algorithm>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "volpath/checks.h"
#include "volpath/relocate.h"
#include "volpath/scene_build.h"
#include "volpath/volpath.h"

namespace ta {
namespace volpath {
namespace {

using detail::SceneStorage;

torch::Tensor host(const torch::Tensor& x) { return x.defined() ? x.to(torch::kCPU) : x; }

// opt with every tensor of the scene's pieces on the host (the scene's own tensors follow the grids' device).
SceneOptions host_options(const SceneOptions& opt) {
  SceneOptions o = opt;
  o.boundary.sdf = host(opt.boundary.sdf);
  o.sensor.points = host(opt.sensor.points);
  o.sensor.normals = host(opt.sensor.normals);
  o.sensor.radius = host(opt.sensor.radius);
  o.emitter.map = host(opt.emitter.map);
  o.grad_support = host(opt.grad_support);
  return o;
}

// Tests: overwrites every buffer a built scene may point into, found through the storage and the grids, not through
// relocate.h's list of pointers (so a pointer missing from that list is left pointing at poison). Buffers of T get
// bytes 0x3F (every float 0.747, every double 4.8e-4: finite, positive, below 1, so a walk that reads them stays a
// valid walk of another scene, no NaN, no endless loop); cell kinds all outside; brick distances 255.
void poison(SceneStorage& store, const std::vector<torch::Tensor>& grids) {
  constexpr uint8_t kValue = 0x3F;
  for (const torch::Tensor* x : {&store.sdf, &store.points, &store.normals, &store.radius, &store.map})
    if (x->defined() && x->numel() > 0) std::memset(x->data_ptr(), kValue, x->nbytes());
  for (const auto& x : grids)
    if (x.defined() && x.numel() > 0) std::memset(x.data_ptr(), kValue, x.nbytes());
  std::fill(store.cells.begin(), store.cells.end(), uint8_t(core::kCellOutside));
  std::fill(store.skip.begin(), store.skip.end(), uint8_t(255));
  std::fill(store.core.begin(), store.core.end(), uint8_t(255));
}

// How the relocation places the buffers: on `device`, copied from the host; a buffer listed in `given` (the host
// copy of a grid that is on the device already) becomes that device buffer instead. Tests: `copy_all` copies the
// grids too, `poison` overwrites every original buffer after the copy (poison(); they stay alive in the keep list),
// `skip` leaves one pointer behind.
struct Placement {
  torch::Device device = torch::kCPU;
  std::map<const void*, const void*> given;
  bool poison = false;
  std::string skip;
  std::vector<torch::Tensor> keep;
};

template <typename T>
std::tuple<torch::Tensor, std::vector<torch::Tensor>> relocate(const core::Scene<T>& S,
                                                               std::shared_ptr<SceneStorage> store, Placement& P) {
  const auto place = [&](const char*, const void* p, int64_t bytes) -> const void* {
    if (const auto it = P.given.find(p); it != P.given.end()) return it->second;
    auto src = torch::from_blob(const_cast<void*>(p), {bytes}, torch::TensorOptions().dtype(torch::kUInt8));
    auto dst = torch::empty({bytes}, torch::TensorOptions().dtype(torch::kUInt8).device(P.device));
    dst.copy_(src);
    P.keep.push_back(dst);
    return dst.data_ptr();
  };
  core::Scene<T> R;
  try {
    R = detail::relocate_scene(S, place, P.skip);
  } catch (const std::invalid_argument& e) {
    TORCH_CHECK_VALUE(false, e.what());
  }
  // the host storage (the originals) stays alive as long as the keep list: a pointer left behind (skip) reads poison,
  // never freed memory
  void* handle = store.get();
  P.keep.push_back(torch::from_blob(
      handle, {0}, [store](void*) mutable { store.reset(); }, torch::TensorOptions().dtype(torch::kUInt8)));
  auto bytes = torch::empty({int64_t(sizeof(R))}, torch::TensorOptions().dtype(torch::kUInt8));
  std::memcpy(bytes.data_ptr(), &R, sizeof(R));
  return {bytes, P.keep};
}

// The dense-grid scene (forward, or with `replay` the gradient replay's: floors, core without the asked voxels).
std::tuple<torch::Tensor, std::vector<torch::Tensor>> dense_scene(
    const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
    const torch::Tensor& ref_albedo, const SceneOptions& opt, double sigma_t_floor, double albedo_floor, bool replay,
    Placement& P, bool copy_all) {
  TORCH_CHECK_VALUE(sigma_t.defined() && albedo.defined() && ref_sigma_t.defined() && ref_albedo.defined(),
                    "sigma_t, albedo, ref_sigma_t, ref_albedo: expected four tensors");
  for (const auto* x : {&albedo, &ref_sigma_t, &ref_albedo})
    TORCH_CHECK_VALUE(x->device() == sigma_t.device(), "grids: expected the four grids on one device, got ",
                      sigma_t.device(), " and ", x->device());
  // host copies (a grid that aliases another keeps aliasing: the walks test pointer equality)
  std::vector<torch::Tensor> in = {sigma_t, albedo, ref_sigma_t, ref_albedo}, h(4);
  for (int i = 0; i < 4; ++i) {
    h[i] = in[i];
    if (!in[i].device().is_cpu()) {
      for (int j = 0; j < i; ++j)
        if (in[j].data_ptr() == in[i].data_ptr() && in[j].sizes() == in[i].sizes() &&
            in[j].scalar_type() == in[i].scalar_type())
          h[i] = h[j];
      if (!h[i].device().is_cpu() || h[i].is_same(in[i])) h[i] = in[i].to(torch::kCPU);
    }
  }
  const SceneOptions o = host_options(opt);
  if (replay) detail::check_floors(sigma_t_floor, albedo_floor);
  detail::check_all(h[0], h[1], h[2], h[3], o, replay ? sigma_t_floor : 0.0);
  if (!copy_all && sigma_t.device() == P.device)
    for (int i = 0; i < 4; ++i) P.given[h[i].data_ptr()] = in[i].data_ptr();
  std::tuple<torch::Tensor, std::vector<torch::Tensor>> out;
  AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "scene_to_device", [&] {
    using T = scalar_t;
    auto store = std::make_shared<SceneStorage>();
    core::Scene<T> S = detail::make_scene<T>(o, h[0], h[1], h[2], h[3], *store);
    if (replay) {  // as scene_backward_cpu: the sampling medium max(ref, floor), the core outside the asked voxels
      S.medium.ref_sigma_t.floor = T(sigma_t_floor);
      S.medium.ref_albedo.floor = T(albedo_floor);
      S.medium.ref_sigma_t.plain = !(sigma_t_floor > 0);
      S.medium.ref_albedo.plain = !(albedo_floor > 0);
      if (o.grad_support.defined()) detail::build_core(S, *store, o.grad_support.data_ptr<bool>());
    } else {
      detail::build_core(S, *store, nullptr);
    }
    out = relocate(S, store, P);  // (the host copies h live until the relocation is done)
    if (P.poison) poison(*store, h);
  });
  return out;
}

}  // namespace

std::tuple<torch::Tensor, std::vector<torch::Tensor>> scene_to_device(
    const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
    const torch::Tensor& ref_albedo, const SceneOptions& opt, double sigma_t_floor, double albedo_floor, bool replay,
    const torch::Device& device) {
  Placement P;
  P.device = device;
  return dense_scene(sigma_t, albedo, ref_sigma_t, ref_albedo, opt, sigma_t_floor, albedo_floor, replay, P, false);
}

std::tuple<torch::Tensor, std::vector<torch::Tensor>> scene_to_device_indexed(const torch::Tensor& index,
                                                                              const torch::Tensor& sigma_t_table,
                                                                              const torch::Tensor& albedo_table,
                                                                              const SceneOptions& opt,
                                                                              const torch::Device& device) {
  TORCH_CHECK_VALUE(index.defined() && sigma_t_table.defined() && albedo_table.defined(),
                    "index, sigma_t_table, albedo_table: expected three tensors");
  const auto hi = host(index).contiguous(), hs = host(sigma_t_table).contiguous(), ha = host(albedo_table).contiguous();
  const SceneOptions o = host_options(opt);
  detail::check_palette(hi, hs, ha, o);
  Placement place;
  place.device = device;
  std::tuple<torch::Tensor, std::vector<torch::Tensor>> out;
  AT_DISPATCH_FLOATING_TYPES(hs.scalar_type(), "scene_to_device_indexed", [&] {
    using T = scalar_t;
    auto store = std::make_shared<SceneStorage>();
    const core::Scene<T> S = detail::make_palette_scene<T>(o, hi, hs, ha, *store);  // as scene_forward_indexed_cpu
    out = relocate(S, store, place);
  });
  return out;
}

std::tuple<torch::Tensor, std::vector<torch::Tensor>> relocate_scene_for_test(
    const torch::Tensor& sigma_t, const torch::Tensor& albedo, const torch::Tensor& ref_sigma_t,
    const torch::Tensor& ref_albedo, const SceneOptions& opt, bool replay, double sigma_t_floor,
    double albedo_floor, const std::string& skip) {
  TORCH_CHECK_VALUE(sigma_t.device().is_cpu(), "sigma_t: the relocation test hook takes CPU grids, got ",
                    sigma_t.device());
  Placement P;
  P.device = torch::kCPU;
  P.poison = true;
  P.skip = skip;
  if (!skip.empty()) {
    bool known = false;
    AT_DISPATCH_FLOATING_TYPES(sigma_t.scalar_type(), "relocate_scene_for_test", [&] {
      for (const auto& s : detail::scene_pointers(core::Scene<scalar_t>())) known |= skip == s.name;
    });
    TORCH_CHECK_VALUE(known, "skip: expected the name of a pointer member of the scene, got '", skip, "'");
  }
  // the scene's own tensors as private copies: they are poisoned too, the caller's options stay as they are
  SceneOptions o = opt;
  for (torch::Tensor* x : {&o.boundary.sdf, &o.sensor.points, &o.sensor.normals, &o.sensor.radius, &o.emitter.map})
    if (x->defined()) *x = x->clone();
  auto out = dense_scene(sigma_t, albedo, ref_sigma_t, ref_albedo, o, sigma_t_floor, albedo_floor, replay, P, true);
  // the caller's grids are originals too: keep them (poisoned) beside the copies
  for (const auto* x : {&sigma_t, &albedo, &ref_sigma_t, &ref_albedo}) std::get<1>(out).push_back(*x);
  return out;
}

SceneLayout scene_layout(at::ScalarType dtype) {
  SceneLayout L;
  AT_DISPATCH_FLOATING_TYPES(dtype, "scene_layout", [&] {
    using T = scalar_t;
    using Sc = core::Scene<T>;
    L.size = int64_t(sizeof(Sc));
    L.align = int64_t(alignof(Sc));
    for (const auto& s : detail::scene_pointers(Sc())) L.pointers.emplace_back(s.name, int64_t(s.offset));
    const auto f = [&](const char* name, size_t off) { L.fields.emplace_back(name, int64_t(off)); };
    f("medium", offsetof(Sc, medium));
    f("medium.sigma_t", offsetof(Sc, medium) + offsetof(core::Medium<T>, sigma_t));
    f("medium.core_sigma_t", offsetof(Sc, medium) + offsetof(core::Medium<T>, core_sigma_t));
    f("sdf", offsetof(Sc, sdf));
    f("sensor", offsetof(Sc, sensor));
    f("sensor.tan_half_fov", offsetof(Sc, sensor) + offsetof(core::Sensor<T>, tan_half_fov));
    f("emitter", offsetof(Sc, emitter));
    f("emitter.map_w", offsetof(Sc, emitter) + offsetof(core::Emitter<T>, map_w));
    f("g", offsetof(Sc, g));
    f("ior", offsetof(Sc, ior));
    f("spp", offsetof(Sc, spp));
    f("seed", offsetof(Sc, seed));
    f("max_depth", offsetof(Sc, max_depth));
    f("rr_depth", offsetof(Sc, rr_depth));
  });
  return L;
}

}  // namespace volpath
}  // namespace ta
