// Runtime scene flags → template instance of the kernels.
#pragma once

#include <cstdint>
#include <type_traits>

#include "core/boundary.h"

namespace ta {
namespace volpath {
namespace detail {

// f(lanes, hero, boundary kind, dielectric) as integral constants (hero only with three lanes).
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

}  // namespace detail
}  // namespace volpath
}  // namespace ta
