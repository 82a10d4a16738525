// Runtime scene flags → template instance of the kernels.
#pragma once

#include "core/boundary.h"
#include "volpath/volpath.h"

namespace ta {
namespace volpath {
namespace detail {

// f.template operator()<LANES, HERO, BOUNDARY, DIELECTRIC>() for the scene flags of `opt` (hero only with three
// lanes): call sites pass a template lambda, [&]<int L, bool HERO, int B, bool DIEL>() { ... }.
template <typename F>
void dispatch_scene(const SceneOptions& opt, const F& f) {
  auto with_diel = [&]<int L, bool HERO, int B>() {
    if (opt.boundary.ior > 0) f.template operator()<L, HERO, B, true>();
    else f.template operator()<L, HERO, B, false>();
  };
  auto with_bound = [&]<int L, bool HERO>() {
    if (opt.boundary.kind == core::kSDFBoundary) with_diel.template operator()<L, HERO, core::kSDFBoundary>();
    else with_diel.template operator()<L, HERO, core::kBoxBoundary>();
  };
  if (opt.lanes == 3 && opt.hero) with_bound.template operator()<3, true>();
  else if (opt.lanes == 3) with_bound.template operator()<3, false>();
  else with_bound.template operator()<1, false>();
}

}  // namespace detail
}  // namespace volpath
}  // namespace ta
