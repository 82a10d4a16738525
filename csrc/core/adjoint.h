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
  int64_t plane = 0;              // values per channel in the buffers: the grid's voxels, or the asked ones (rank)
  const int32_t* rank = nullptr;  // or null; else voxel v's place among the asked voxels (grad_support), −1: not asked
  // Adds x to ∂/∂σ_t (∂/∂α) of channel c of voxel v (the buffers channel-planar: c · plane + v, or c · plane +
  // rank[v] in compact buffers, where a voxel that was not asked for gets nothing).
  TA_HD inline void sigma_t(int c, int64_t v, T x) const { add(grad_sigma_t, c, v, x); }
  TA_HD inline void albedo(int c, int64_t v, T x) const { add(grad_albedo, c, v, x); }

 private:
  TA_HD inline void add(T* buffer, int c, int64_t v, T x) const {
    if (rank != nullptr) {
      v = rank[v];
      if (v < 0) return;
    }
    Deposit::add(buffer, c * plane + v, x);
  }
};

}  // namespace core
}  // namespace ta
