// Counter-based random numbers: Philox4x32-10 (Salmon et al. 2011). The counter is
// (sensor element, sample, channel, event) and the key is the seed, so any draw is reproducible on its own,
// independent of thread scheduling: path replay relies on it.
#pragma once

#include "core/defs.h"

namespace ta {
namespace core {

struct Philox4x32 {
  TA_HD static inline void round(uint32_t c[4], const uint32_t k[2]) {
    const uint64_t p0 = uint64_t(0xD2511F53u) * c[0];
    const uint64_t p1 = uint64_t(0xCD9E8D57u) * c[2];
    const uint32_t n0 = uint32_t(p1 >> 32) ^ c[1] ^ k[0];
    const uint32_t n2 = uint32_t(p0 >> 32) ^ c[3] ^ k[1];
    c[1] = uint32_t(p1);
    c[3] = uint32_t(p0);
    c[0] = n0;
    c[2] = n2;
  }
  TA_HD static inline void generate(uint32_t c[4], uint64_t key) {
    uint32_t k[2] = {uint32_t(key), uint32_t(key >> 32)};
    for (int r = 0; r < 10; ++r) {
      round(c, k);
      k[0] += 0x9E3779B9u;
      k[1] += 0xBB67AE85u;
    }
  }
};

template <typename T>
TA_HD inline T to_unit_open(uint32_t x);  // uniform in the open interval (0, 1)
template <>
TA_HD inline float to_unit_open<float>(uint32_t x) {
  return (float(x >> 9) + 0.5f) * (1.0f / 8388608.0f);  // 23 bits: x + 0.5 stays exact, so u < 1
}
template <>
TA_HD inline double to_unit_open<double>(uint32_t x) {
  return (double(x) + 0.5) * (1.0 / 4294967296.0);
}

template <typename T>
struct PathRng {
  uint64_t key;
  uint32_t element, sample, channel;
  // Four uniforms in (0, 1) for event number `event` of this path.
  TA_HD TA_INLINE void draw(uint32_t event, T u[4]) const {
    uint32_t c[4] = {element, sample, channel, event};
    Philox4x32::generate(c, key);
    for (int i = 0; i < 4; ++i) u[i] = to_unit_open<T>(c[i]);
  }
};

}  // namespace core
}  // namespace ta
