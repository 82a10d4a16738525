// Local optics: Henyey–Greenstein sampling, direction frames, smooth-dielectric Fresnel, reflection, refraction.
#pragma once

#include "core/defs.h"

namespace ta {
namespace core {

// Henyey–Greenstein: cosine of the angle between the old and new propagation directions, sampled exactly.
template <typename T>
TA_HD TA_INLINE T sample_hg_cos(T g, T u) {
  if (tabs(g) < T(1e-3)) return T(1) - T(2) * u;
  const T s = (T(1) - g * g) / (T(1) - g + T(2) * g * u);
  const T c = (T(1) + g * g - s * s) / (T(2) * g);
  return tmin(T(1), tmax(T(-1), c));
}

// Orthonormal tangent vectors b1, b2 of the unit vector n (branchless frame of Duff et al. 2017).
template <typename T>
TA_HD inline void tangent_frame(const T n[3], T b1[3], T b2[3]) {
  const T sign = tcopysign(T(1), n[2]);
  const T a = T(-1) / (sign + n[2]);
  const T b = n[0] * n[1] * a;
  b1[0] = T(1) + sign * n[0] * n[0] * a;
  b1[1] = sign * b;
  b1[2] = -sign * n[0];
  b2[0] = b;
  b2[1] = sign + n[1] * n[1] * a;
  b2[2] = -n[1];
}

// New unit direction at angle acos(cos_t) from d, azimuth 2π·u.
template <typename T>
TA_HD TA_INLINE void rotate_direction(T d[3], T cos_t, T u) {
  const T sin_t = tsqrt(tmax(T(0), T(1) - cos_t * cos_t));
  const T phi = T(6.283185307179586) * u;
  const T sp = tsin(phi), cp = tcos(phi);
  T b1[3], b2[3];
  tangent_frame(d, b1, b2);
  T n[3];
  for (int k = 0; k < 3; ++k) n[k] = sin_t * (cp * b1[k] + sp * b2[k]) + cos_t * d[k];
  const T inv = T(1) / tsqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
  for (int k = 0; k < 3; ++k) d[k] = n[k] * inv;
}

// Unpolarised Fresnel reflectance for light going from index n_i to n_t, eta = n_i / n_t, cos_i in [0, 1].
// Returns 1 under total internal reflection.
template <typename T>
TA_HD TA_INLINE T fresnel_dielectric(T cos_i, T eta) {
  const T sin2_t = eta * eta * (T(1) - cos_i * cos_i);
  if (sin2_t >= T(1)) return T(1);
  const T cos_t = tsqrt(T(1) - sin2_t);
  const T rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
  const T rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
  return T(0.5) * (rs * rs + rp * rp);
}

// Mirror reflection of the propagation direction d at a surface whose unit normal n_inc faces the incident side
// (dot(d, n_inc) = −cos_i <= 0).
template <typename T>
TA_HD TA_INLINE void reflect(T d[3], const T n_inc[3], T cos_i) {
  for (int k = 0; k < 3; ++k) d[k] += T(2) * cos_i * n_inc[k];
  normalize3(d);
}

// Snell refraction of d through a surface with unit normal n_inc on the incident side, eta = n_i / n_t
// (callers only refract when fresnel_dielectric < 1, i.e. no total internal reflection).
template <typename T>
TA_HD TA_INLINE void refract(T d[3], const T n_inc[3], T cos_i, T eta) {
  const T sin2_t = eta * eta * (T(1) - cos_i * cos_i);
  const T cos_t = tsqrt(tmax(T(0), T(1) - sin2_t));
  for (int k = 0; k < 3; ++k) d[k] = eta * d[k] + (eta * cos_i - cos_t) * n_inc[k];
  normalize3(d);
}

}  // namespace core
}  // namespace ta
