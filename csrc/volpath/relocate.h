// Scene relocation: a copy of a built core::Scene<T> whose every pointer points into buffers placed by the caller
// (device memory for the CUDA glue, fresh host buffers for the tests). Scene<T> is a plain struct of numbers and
// pointers, trivially copyable, so a relocated scene travels to a kernel as its bytes (a kernel parameter by value,
// csrc/cuda/launch.cuh).
//
// scene_pointers lists every pointer member of Scene<T> with the bytes it points to, computed from the scene's own
// sizes (grid, palette, bricks, texels, map); relocate_scene calls `place` once per distinct buffer (pointers that
// share a buffer, as the reference medium and the parameters of a forward without ratio weights do, share the
// placed copy, so pointer equalities the walks test stay true). The diagnostics tally (one buffer per CPU thread)
// cannot be relocated: a scene with a tally is refused.
//
// A member added to Scene<T> or to one of its pieces changes sizeof(Scene<T>): the static_asserts below then fail
// until scene_pointers lists the new pointer (or the assert is updated for a member that is no pointer).
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <functional>
#include <map>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#include "core/integrator.h"

namespace ta {
namespace volpath {
namespace detail {

static_assert(std::is_trivially_copyable_v<core::Scene<float>> && std::is_trivially_copyable_v<core::Scene<double>>,
              "core::Scene<T> travels to a kernel as its bytes: it must stay trivially copyable");
static_assert(std::is_standard_layout_v<core::Scene<float>> && std::is_standard_layout_v<core::Scene<double>>,
              "core::Scene<T>: offsetof of its pointer members needs a standard-layout struct");
#if defined(__x86_64__) || defined(__aarch64__)
// LP64: when these fail, a member was added or removed; list every new pointer in scene_pointers, then update them
static_assert(sizeof(core::Scene<float>) == 632, "core::Scene<float> changed: update scene_pointers");
static_assert(sizeof(core::Scene<double>) == 784, "core::Scene<double> changed: update scene_pointers");
#endif

// One pointer member of a Scene<T>: its name (the member's path), its byte offset in the scene and the bytes of the
// buffer it points to.
struct PointerSlot {
  const char* name;
  size_t offset;
  int64_t bytes;
};

// The pointer read from / written to a slot of the scene (memcpy: no type punning).
inline const void* slot_pointer(const void* scene, const PointerSlot& s) {
  const void* p;
  std::memcpy(&p, static_cast<const char*>(scene) + s.offset, sizeof(p));
  return p;
}
inline void set_slot_pointer(void* scene, const PointerSlot& s, const void* p) {
  std::memcpy(static_cast<char*>(scene) + s.offset, &p, sizeof(p));
}

// Every pointer member of Scene<T>, with the size of its buffer in S (0 where the pointer is null or unused).
template <typename T>
std::vector<PointerSlot> scene_pointers(const core::Scene<T>& S) {
  using Sc = core::Scene<T>;
  const auto& M = S.medium;
  const int64_t N = M.voxels(), t = int64_t(sizeof(T));
  std::vector<PointerSlot> out;
  const size_t med = offsetof(Sc, medium);
  const auto channels = [&](const char* data, const char* index, const char* palette, size_t off,
                            const core::Channels<T>& c) {
    using Ch = core::Channels<T>;
    out.push_back({data, med + off + offsetof(Ch, data), c.data != nullptr ? 3 * N * t : 0});
    out.push_back({index, med + off + offsetof(Ch, index), c.index != nullptr ? N : 0});
    out.push_back({palette, med + off + offsetof(Ch, palette), c.palette != nullptr ? 3 * c.entries * t : 0});
  };
  using Med = core::Medium<T>;
  channels("medium.sigma_t.data", "medium.sigma_t.index", "medium.sigma_t.palette", offsetof(Med, sigma_t),
           M.sigma_t);
  channels("medium.albedo.data", "medium.albedo.index", "medium.albedo.palette", offsetof(Med, albedo), M.albedo);
  channels("medium.ref_sigma_t.data", "medium.ref_sigma_t.index", "medium.ref_sigma_t.palette",
           offsetof(Med, ref_sigma_t), M.ref_sigma_t);
  channels("medium.ref_albedo.data", "medium.ref_albedo.index", "medium.ref_albedo.palette",
           offsetof(Med, ref_albedo), M.ref_albedo);
  const int64_t core_bricks = M.core_bricks[0] * M.core_bricks[1] * M.core_bricks[2];
  out.push_back({"medium.core", med + offsetof(Med, core), M.core != nullptr ? core_bricks : 0});
  using Sdf = core::SDFGrid<T>;
  const size_t sdf = offsetof(Sc, sdf);
  const int64_t corners = (M.D + 1) * (M.H + 1) * (M.W + 1);
  const int64_t skip_bricks = S.sdf.bricks[0] * S.sdf.bricks[1] * S.sdf.bricks[2];
  out.push_back({"sdf.sdf", sdf + offsetof(Sdf, sdf), S.sdf.sdf != nullptr ? corners * t : 0});
  out.push_back({"sdf.cell", sdf + offsetof(Sdf, cell), S.sdf.cell != nullptr ? N : 0});
  out.push_back({"sdf.skip", sdf + offsetof(Sdf, skip), S.sdf.skip != nullptr ? skip_bricks : 0});
  using Sen = core::Sensor<T>;
  const size_t sen = offsetof(Sc, sensor);
  out.push_back({"sensor.points", sen + offsetof(Sen, points),
                 S.sensor.points != nullptr ? 3 * S.sensor.count * t : 0});
  out.push_back({"sensor.normals", sen + offsetof(Sen, normals),
                 S.sensor.normals != nullptr ? 3 * S.sensor.count * t : 0});
  out.push_back({"sensor.radius", sen + offsetof(Sen, radius), S.sensor.radius != nullptr ? S.sensor.count * t : 0});
  using Em = core::Emitter<T>;
  out.push_back({"emitter.map", offsetof(Sc, emitter) + offsetof(Em, map),
                 S.emitter.map != nullptr ? S.emitter.map_h * S.emitter.map_w * 3 * t : 0});
  out.push_back({"tally_bin", offsetof(Sc, tally_bin), S.tally_bin != nullptr ? N : 0});
  out.push_back({"tally", offsetof(Sc, tally), 0});
  return out;
}

// A copy of S whose every non-null pointer is place(name, pointer, bytes)'s answer, called once per distinct buffer
// (the first slot's name). `skip` (tests only) names a slot left pointing at the original, to show that a test of
// the relocation notices a pointer left behind. Throws std::invalid_argument for a scene with a tally (the CPU's
// per-thread diagnostics) or two slots that share a pointer with different sizes.
template <typename T>
core::Scene<T> relocate_scene(const core::Scene<T>& S,
                              const std::function<const void*(const char*, const void*, int64_t)>& place,
                              const std::string& skip = "") {
  if (S.tally != nullptr || S.tally_bin != nullptr)
    throw std::invalid_argument("scene: a scene with a tally (the CPU's per-thread diagnostics) cannot be relocated");
  core::Scene<T> R = S;
  std::map<const void*, std::pair<const void*, int64_t>> placed;
  for (const PointerSlot& s : scene_pointers(S)) {
    const void* p = slot_pointer(&S, s);
    if (p == nullptr || s.name == skip) continue;
    if (s.bytes <= 0)
      throw std::invalid_argument(std::string("scene: pointer ") + s.name + " is set but its buffer has no size");
    auto it = placed.find(p);
    if (it == placed.end()) it = placed.emplace(p, std::make_pair(place(s.name, p, s.bytes), s.bytes)).first;
    else if (it->second.second != s.bytes)
      throw std::invalid_argument(std::string("scene: pointer ") + s.name + " shares a buffer of " +
                                  std::to_string(it->second.second) + " bytes but needs " + std::to_string(s.bytes));
    set_slot_pointer(&R, s, it->second.first);
  }
  return R;
}

}  // namespace detail
}  // namespace volpath
}  // namespace ta
