// Where the adjoint goes and how it gets there: the gradient buffers of a walk (channel-planar like the grids, null
// when not requested) and the one deposit policy that every gradient deposit goes through. The CPU glue gives each
// thread its own buffers, so the policy there is a plain add; a GPU build, whose threads share the buffers, passes a
// policy with an atomic add instead.
#pragma once

#include "core/defs.h"

namespace ta {
namespace core {

// buffer[i] += x: the deposit of a thread that owns its buffer.
struct PlainAdd {
  template <typename T>
  TA_HD static inline void add(T* buffer, int64_t i, T x) { buffer[i] += x; }
};

template <typename T, typename Deposit = PlainAdd>
struct Adjoint {
  T* grad_sigma_t = nullptr;
  T* grad_albedo = nullptr;
  // Adds x to ∂/∂σ_t (∂/∂α) of the flat grid index i (channel · voxels + voxel).
  TA_HD inline void sigma_t(int64_t i, T x) const { Deposit::add(grad_sigma_t, i, x); }
  TA_HD inline void albedo(int64_t i, T x) const { Deposit::add(grad_albedo, i, x); }
};

}  // namespace core
}  // namespace ta
