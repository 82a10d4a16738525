// Tracing core of the heterogeneous-volume path tracer: plain C++17, no PyTorch.
//
// Everything a random walk needs lives here: the counter-based RNG, Henyey–Greenstein sampling, Fresnel,
// exact regular tracking through a piecewise-constant voxel grid (DDA with the analytic transmittance of each
// voxel), and the walk itself, written once and specialised by template parameters so a scene pays only for
// what it uses:
//
//   LANES       1: one walk per colour channel (chromatic sampling density);
//               3: one walk serves all three channels (achromatic sampling density).
//   DIELECTRIC  smooth dielectric box boundary (Fresnel, TIR) or index matched (no boundary code at all).
//   RATIO       the walk is sampled from a reference medium that may differ from the parameters, and carries the
//               ratio weights f(θ)/p_ref. Off for the default forward pass (reference = parameters).
//   ADJOINT     path replay of radiative backpropagation: deposit ∂/∂θ of the path contribution.
//
// Estimator (per channel c, for one path x sampled from the reference medium σ̂, α̂):
//   V_c(x) = L_env,c · Π_flights exp(−Σ_voxels (σ_c − σ̂)·ℓ) · Π_collisions (σ_c/σ̂) · (α_c / (p_s·q))
// where p_s is the probability of continuing at a collision (α̂_c for one lane, max_c α̂_c for three lanes) and q
// the Russian-roulette survival probability computed from the reference throughput only (so V is smooth in θ for
// a fixed reference and seed). Absorbed, roulette-killed and depth-truncated paths contribute 0.
// Its derivative is deposited by path replay:
//   ∂V_c/∂σ_c(v) = V_c·(−ℓ_v) for every flight segment in v   +   V_c^{¬σ-factor}/σ̂(v) for a collision in v
//   ∂V_c/∂α_c(v) = V_c^{¬α-factor}/(p_s·q)                     for a scattering collision in v
// where V^{¬f} (V without factor f) is evaluated zero-safely (σ_c = 0 or α_c = 0 factors give exact derivatives).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

namespace ta {
namespace volpath {

// ------------------------------------------------------------------------------------------------ RNG
// Philox4x32-10 (Salmon et al. 2011): a counter-based generator. The counter is
// (texel, sample, channel, event), the key is the seed: any draw is reproducible on its own, independent of
// thread scheduling, which is what path replay relies on.
struct Philox4x32 {
  static inline void round(uint32_t c[4], const uint32_t k[2]) {
    const uint64_t p0 = uint64_t(0xD2511F53u) * c[0];
    const uint64_t p1 = uint64_t(0xCD9E8D57u) * c[2];
    const uint32_t n0 = uint32_t(p1 >> 32) ^ c[1] ^ k[0];
    const uint32_t n2 = uint32_t(p0 >> 32) ^ c[3] ^ k[1];
    c[1] = uint32_t(p1);
    c[3] = uint32_t(p0);
    c[0] = n0;
    c[2] = n2;
  }
  static inline void generate(uint32_t c[4], uint64_t key) {
    uint32_t k[2] = {uint32_t(key), uint32_t(key >> 32)};
    for (int r = 0; r < 10; ++r) {
      round(c, k);
      k[0] += 0x9E3779B9u;
      k[1] += 0xBB67AE85u;
    }
  }
};

template <typename T>
inline T to_unit_open(uint32_t x);  // uniform in the open interval (0, 1)
template <>
inline float to_unit_open<float>(uint32_t x) {
  return (float(x >> 9) + 0.5f) * (1.0f / 8388608.0f);  // 23 bits: x + 0.5 stays exact, so u < 1
}
template <>
inline double to_unit_open<double>(uint32_t x) {
  return (double(x) + 0.5) * (1.0 / 4294967296.0);
}

template <typename T>
struct PathRng {
  uint64_t key;
  uint32_t texel, sample, channel;
  // Four uniforms in (0, 1) for event number `event` of this path.
  inline void draw(uint32_t event, T u[4]) const {
    uint32_t c[4] = {texel, sample, channel, event};
    Philox4x32::generate(c, key);
    for (int i = 0; i < 4; ++i) u[i] = to_unit_open<T>(c[i]);
  }
};

// ------------------------------------------------------------------------------------------------ params
struct Face {
  enum : int { Top = 0, Bottom = 1, Both = 2 };
};

template <typename T>
struct Params {
  int64_t D = 0, H = 0, W = 0;  // grid size (z, y, x)
  T voxel[3] = {1, 1, 1};       // voxel edges along x, y, z in mm (anisotropic printers: 600×300×940 DPI)
  T g = 0;                      // Henyey–Greenstein parameter, |g| < 1
  T ior = 1;                    // only used with DIELECTRIC
  T env[3] = {1, 1, 1};         // environment radiance, linear RGB
  int64_t spp = 1;
  uint64_t seed = 0;
  int64_t max_depth = 1;  // interactions (scatterings + internal reflections) before a path is cut
  int64_t rr_depth = 1;   // interactions before Russian roulette starts
  int face = Face::Top;
  int64_t voxels() const { return D * H * W; }
  int64_t texels_per_face() const { return H * W; }
  int faces() const { return face == Face::Both ? 2 : 1; }
};

// Channel-planar grids (3, D, H, W), all of the same scalar type. ref_* is the sampling (reference) medium.
template <typename T>
struct Grids {
  const T* sigma_t;
  const T* albedo;
  const T* ref_sigma_t;
  const T* ref_albedo;
};

// Where the adjoint goes (chunk-local buffers, channel-planar like the grids); null when not requested.
template <typename T>
struct Adjoint {
  T* grad_sigma_t = nullptr;
  T* grad_albedo = nullptr;
};

// ------------------------------------------------------------------------------------------------ optics
// Henyey–Greenstein: cosine of the angle between the old and new propagation directions, sampled exactly.
template <typename T>
inline T sample_hg_cos(T g, T u) {
  if (std::abs(g) < T(1e-3)) return T(1) - T(2) * u;
  const T s = (T(1) - g * g) / (T(1) - g + T(2) * g * u);
  const T c = (T(1) + g * g - s * s) / (T(2) * g);
  return std::min(T(1), std::max(T(-1), c));
}

// New unit direction at angle acos(cos_t) from d, azimuth 2π·u (frame of Duff et al. 2017).
template <typename T>
inline void rotate_direction(T d[3], T cos_t, T u) {
  const T sin_t = std::sqrt(std::max(T(0), T(1) - cos_t * cos_t));
  const T phi = T(6.283185307179586) * u;
  const T sp = std::sin(phi), cp = std::cos(phi);
  const T sign = std::copysign(T(1), d[2]);
  const T a = T(-1) / (sign + d[2]);
  const T b = d[0] * d[1] * a;
  const T b1[3] = {T(1) + sign * d[0] * d[0] * a, sign * b, -sign * d[0]};
  const T b2[3] = {b, sign + d[1] * d[1] * a, -d[1]};
  T n[3];
  for (int k = 0; k < 3; ++k) n[k] = sin_t * (cp * b1[k] + sp * b2[k]) + cos_t * d[k];
  const T inv = T(1) / std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
  for (int k = 0; k < 3; ++k) d[k] = n[k] * inv;
}

// Unpolarised Fresnel reflectance for light going from index n_i to n_t, eta = n_i / n_t, cos_i in [0, 1].
// Returns 1 under total internal reflection.
template <typename T>
inline T fresnel_dielectric(T cos_i, T eta) {
  const T sin2_t = eta * eta * (T(1) - cos_i * cos_i);
  if (sin2_t >= T(1)) return T(1);
  const T cos_t = std::sqrt(T(1) - sin2_t);
  const T rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
  const T rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
  return T(0.5) * (rs * rs + rp * rp);
}

// ------------------------------------------------------------------------------------------------ walk
// What a walk leaves behind, per lane: V = 0 unless escaped; prod_nonzero and zeros make V^{¬f} zero-safe.
template <typename T, int LANES>
struct PathResult {
  bool escaped = false;
  bool truncated = false;  // cut by max_depth (a bias the caller reports)
  T value[LANES];         // V_c / L_env,c  (the path weight; 0 if not escaped)
  T prod_nonzero[LANES];  // product of all non-zero factors
  int zeros[LANES];       // number of exactly-zero factors (σ_c = 0 or α_c = 0 at a collision)
  int64_t scatter_events = 0;
};

template <typename T>
inline T weight_without(T factor, T value, T prod_nonzero, int zeros) {
  if (factor != T(0)) return zeros == 0 ? value / factor : T(0);
  return zeros == 1 ? prod_nonzero : T(0);
}

// One random walk of the path that starts at texel `texel` (face-major index), sample `sample`.
// `chan` is the channel for LANES == 1 (lanes map to channels 0..2 for LANES == 3).
// With ADJOINT, `pass1` holds this path's result from a non-adjoint replay and `adj[l]` = grad_out·L_env/spp.
template <typename T, int LANES, bool DIELECTRIC, bool RATIO, bool ADJOINT>
inline PathResult<T, LANES> trace_path(const Params<T>& P, const Grids<T>& G, int64_t texel, int64_t sample,
                                       int chan, const PathResult<T, LANES>* pass1, const T* adj,
                                       const Adjoint<T>& A) {
  static_assert(!ADJOINT || RATIO, "the adjoint replay always carries ratio weights");
  PathResult<T, LANES> res;
  for (int l = 0; l < LANES; ++l) {
    res.value[l] = T(0);
    res.prod_nonzero[l] = T(1);
    res.zeros[l] = 0;
  }
  const int64_t N = P.voxels();
  const int64_t HW = P.texels_per_face();
  const int face = P.face == Face::Both ? int(texel / HW) : P.face;
  const int64_t ti = texel % HW;
  const int64_t tj = ti / P.W, tx = ti % P.W;
  const T* vs = P.voxel;
  const int ch0 = LANES == 1 ? chan : 0;  // the channel whose reference density drives the walk

  const PathRng<T> rng{P.seed, uint32_t(texel), uint32_t(sample), uint32_t(LANES == 1 ? chan : 3)};
  uint32_t event = 0;
  T u[4];
  rng.draw(event++, u);

  // Start on the face, inside the texel's footprint, pointing along the inward normal (positions in mm).
  T p[3] = {(T(tx) + u[0]) * vs[0], (T(tj) + u[1]) * vs[1], face == Face::Top ? T(P.D) * vs[2] : T(0)};
  T d[3] = {0, 0, face == Face::Top ? T(-1) : T(1)};
  int64_t idx[3] = {tx, tj, face == Face::Top ? P.D - 1 : 0};
  const int64_t dims[3] = {P.W, P.H, P.D};

  if (DIELECTRIC) {  // specular reflection of the environment at the entry face (normal incidence)
    const T r = fresnel_dielectric(T(1), T(1) / P.ior);
    if (u[2] < r) {
      res.escaped = true;
      for (int l = 0; l < LANES; ++l) res.value[l] = T(1);
      return res;
    }
  }

  T w[LANES], wref[LANES];  // path weight (with zero factors) and reference-only weight (for roulette)
  for (int l = 0; l < LANES; ++l) w[l] = wref[l] = T(1);
  int64_t depth = 0;

  for (;;) {
    rng.draw(event++, u);
    const T tau = -std::log(u[0]);  // optical depth to the next collision, in the reference medium

    // ---- exact regular tracking through the voxels (DDA), analytic transmittance per voxel
    T tnext[3], tdelta[3];
    int64_t step[3];
    for (int a = 0; a < 3; ++a) {
      if (d[a] > T(0)) {
        step[a] = 1;
        tdelta[a] = vs[a] / d[a];
        tnext[a] = std::max(T(0), (T(idx[a] + 1) * vs[a] - p[a]) / d[a]);
      } else if (d[a] < T(0)) {
        step[a] = -1;
        tdelta[a] = -vs[a] / d[a];
        tnext[a] = std::max(T(0), (T(idx[a]) * vs[a] - p[a]) / d[a]);
      } else {
        step[a] = 0;
        tdelta[a] = std::numeric_limits<T>::infinity();
        tnext[a] = std::numeric_limits<T>::infinity();
      }
    }
    T t = 0, acc = 0;
    T excess[LANES];  // Σ (σ_c − σ̂)·ℓ over the flight, for the transmittance ratio
    for (int l = 0; l < LANES; ++l) excess[l] = T(0);
    bool collided = false;
    int exit_axis = -1;
    int64_t v = 0;
    for (;;) {
      v = (idx[2] * P.H + idx[1]) * P.W + idx[0];
      const int a = tnext[0] < tnext[1] ? (tnext[0] < tnext[2] ? 0 : 2) : (tnext[1] < tnext[2] ? 1 : 2);
      const T seg = std::max(T(0), tnext[a] - t);
      const T sref = G.ref_sigma_t[ch0 * N + v];  // reference density, mm⁻¹ (t is in mm)
      const T od = sref * seg;
      T len = seg;
      if (acc + od >= tau) {  // collision inside this voxel
        len = (tau - acc) / sref;
        collided = true;
      }
      if (RATIO) {
        for (int l = 0; l < LANES; ++l) {
          const int c = LANES == 1 ? chan : l;
          excess[l] += (G.sigma_t[c * N + v] - G.ref_sigma_t[ch0 * N + v]) * len;
        }
      }
      if (ADJOINT && A.grad_sigma_t && len > T(0)) {
        for (int l = 0; l < LANES; ++l) {
          const int c = LANES == 1 ? chan : l;
          A.grad_sigma_t[c * N + v] -= adj[l] * pass1->value[l] * len;
        }
      }
      if (collided) {
        t += len;
        break;
      }
      acc += od;
      t = tnext[a];
      idx[a] += step[a];
      if (idx[a] < 0 || idx[a] >= dims[a]) {
        idx[a] -= step[a];
        exit_axis = a;
        break;
      }
      tnext[a] += tdelta[a];
    }
    for (int k = 0; k < 3; ++k) p[k] += d[k] * t;
    if (RATIO) {
      for (int l = 0; l < LANES; ++l) {
        const T f = std::exp(-excess[l]);
        w[l] *= f;
        res.prod_nonzero[l] *= f;
      }
    }

    if (collided) {
      // keep the point inside the voxel the DDA found (no drift into a neighbour through rounding)
      for (int k = 0; k < 3; ++k) p[k] = std::min(T(idx[k] + 1) * vs[k], std::max(T(idx[k]) * vs[k], p[k]));
      if (++depth > P.max_depth) {  // truncated: contributes 0
        res.truncated = true;
        return res;
      }
      ++res.scatter_events;
      // continuation probability: reference albedo (max over lanes), times roulette on the reference weight
      T ps, aref[LANES];
      if (LANES == 1) {
        aref[0] = G.ref_albedo[chan * N + v];
        ps = aref[0];
      } else {
        ps = 0;
        for (int l = 0; l < LANES; ++l) {
          aref[l] = G.ref_albedo[l * N + v];
          ps = std::max(ps, aref[l]);
        }
      }
      T q = T(1);
      if (depth > P.rr_depth) {
        T m = 0;
        for (int l = 0; l < LANES; ++l) m = std::max(m, wref[l] * aref[l] / ps);
        q = std::min(T(1), m);
      }
      if (!(u[1] < ps * q)) return res;  // absorbed or killed by roulette: contributes 0
      const T inv_psq = T(1) / (ps * q);
      for (int l = 0; l < LANES; ++l) {
        const int c = LANES == 1 ? chan : l;
        wref[l] *= aref[l] * inv_psq;
        const T fa = G.albedo[c * N + v] * inv_psq;  // albedo factor α_c/(p_s q)
        T fs = T(1);                                 // collision factor σ_c/σ̂
        if (RATIO) fs = G.sigma_t[c * N + v] / G.ref_sigma_t[ch0 * N + v];
        if (ADJOINT) {
          if (A.grad_sigma_t)
            A.grad_sigma_t[c * N + v] += adj[l] *
                weight_without(fs, pass1->value[l], pass1->prod_nonzero[l], pass1->zeros[l]) /
                G.ref_sigma_t[ch0 * N + v];
          if (A.grad_albedo)
            A.grad_albedo[c * N + v] += adj[l] *
                weight_without(fa, pass1->value[l], pass1->prod_nonzero[l], pass1->zeros[l]) * inv_psq;
        }
        if (RATIO || LANES > 1) {
          w[l] *= fs * fa;
          if (fs == T(0)) ++res.zeros[l]; else res.prod_nonzero[l] *= fs;
          if (fa == T(0)) ++res.zeros[l]; else res.prod_nonzero[l] *= fa;
        }
      }
      rotate_direction(d, sample_hg_cos(P.g, u[2]), u[3]);
      continue;
    }

    // ---- reached the box boundary on axis exit_axis
    p[exit_axis] = d[exit_axis] > T(0) ? T(dims[exit_axis]) * vs[exit_axis] : T(0);
    if (DIELECTRIC) {
      const T r = fresnel_dielectric(std::abs(d[exit_axis]), P.ior);
      if (u[1] < r) {  // internal reflection (total when r == 1)
        if (++depth > P.max_depth) {
          res.truncated = true;
          return res;
        }
        d[exit_axis] = -d[exit_axis];
        continue;
      }
    }
    res.escaped = true;
    for (int l = 0; l < LANES; ++l) res.value[l] = w[l];
    return res;
  }
}

}  // namespace volpath
}  // namespace ta
