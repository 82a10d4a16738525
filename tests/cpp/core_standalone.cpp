// The tracing core compiled on its own, without PyTorch (tests/test_core_standalone.py builds and runs it):
// a white-furnace sphere (SDF boundary, dielectric, perspective camera) must give exactly 1 for every path, and a
// non-scattering index-matched sphere must give exp(−σ ℓ) along the axis. Exit code 0 on success.
#include <cmath>
#include <cstdio>
#include <vector>

#include "core/integrator.h"

using namespace ta::core;

int main() {
  const int n = 10;
  const double h = 0.1, R = 0.35, o = -0.5;
  std::vector<double> sdf((n + 1) * (n + 1) * (n + 1));
  std::vector<uint8_t> cells(n * n * n);
  for (int k = 0; k <= n; ++k)
    for (int j = 0; j <= n; ++j)
      for (int i = 0; i <= n; ++i) {
        const double x = o + i * h, y = o + j * h, z = o + k * h;
        sdf[(k * (n + 1) + j) * (n + 1) + i] = std::sqrt(x * x + y * y + z * z) - R;
      }
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) {
        bool neg = true, pos = true;
        for (int c = 0; c < 8; ++c) {
          const double v = sdf[((k + (c >> 2)) * (n + 1) + j + ((c >> 1) & 1)) * (n + 1) + i + (c & 1)];
          neg &= v < 0;
          pos &= v > 0;
        }
        cells[(k * n + j) * n + i] = neg ? kCellInside : (pos ? kCellOutside : kCellMixed);
      }
  std::vector<double> sigma(3 * n * n * n, 7.0), white(3 * n * n * n, 1.0), black(3 * n * n * n, 0.0);
  Scene<double> S;
  S.medium.D = S.medium.H = S.medium.W = n;
  for (int a = 0; a < 3; ++a) {
    S.medium.voxel[a] = h;
    S.medium.origin[a] = o;
  }
  S.medium.sigma_t = S.medium.ref_sigma_t = sigma.data();
  S.medium.albedo = S.medium.ref_albedo = white.data();
  S.sdf.sdf = sdf.data();
  S.sdf.cell = cells.data();
  S.sensor.kind = kPerspective;
  const double eye[3] = {0.9, 0.6, 0.7};
  double f[3] = {-eye[0], -eye[1], -eye[2]};
  normalize3(f);
  double up0[3] = {0, 0, 1}, r[3] = {f[1] * up0[2] - f[2] * up0[1], f[2] * up0[0] - f[0] * up0[2], 0};
  r[2] = f[0] * up0[1] - f[1] * up0[0];
  normalize3(r);
  const double u[3] = {r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0]};
  for (int k = 0; k < 3; ++k) {
    S.sensor.origin[k] = eye[k];
    S.sensor.forward[k] = f[k];
    S.sensor.right[k] = r[k];
    S.sensor.up[k] = u[k];
  }
  S.sensor.rows = S.sensor.cols = 8;
  S.sensor.tan_half_fov = std::tan(0.3);
  S.ior = 1.5;
  S.g = 0.3;
  S.max_depth = 1 << 20;
  S.rr_depth = 1 << 20;
  const Adjoint<double> none;
  int bad = 0;
  const int64_t paths = S.elements() * 16;
  for (int64_t e = 0; e < S.elements(); ++e)
    for (int s = 0; s < 16; ++s) {
      const auto res = trace_path<double, 3, kSDFBoundary, true, false, false>(S, e, s, 0, nullptr, nullptr, none);
      bad += !(res.escaped && res.value[0] == 1.0 && res.value[2] == 1.0);
    }
  // Beer–Lambert along the axis (index matched, albedo 0, almost no collisions in the reference medium)
  std::vector<double> tiny(3 * n * n * n, 1e-12);
  S.medium.albedo = black.data();
  S.medium.ref_sigma_t = tiny.data();
  S.medium.ref_albedo = tiny.data();
  S.sensor.kind = kOrthographic;
  const double down[3] = {0, 0, -1}, ex[3] = {1, 0, 0}, ey[3] = {0, 1, 0};
  for (int k = 0; k < 3; ++k) {
    S.sensor.origin[k] = k == 2 ? 2.0 : 0.0;
    S.sensor.forward[k] = down[k];
    S.sensor.right[k] = ex[k];
    S.sensor.up[k] = ey[k];
  }
  S.sensor.rows = S.sensor.cols = 1;
  S.sensor.width = S.sensor.height = 1e-9;
  const auto res = trace_path<double, 3, kSDFBoundary, false, true, false>(S, 0, 0, 0, nullptr, nullptr, none);
  // x = y = 0 is a line of voxel corners: along it the trilinear field is the linear interpolation of the corner
  // distances, which cross zero between z = ±0.3 and ±0.4
  const double f3 = std::sqrt(0.3 * 0.3) - R, f4 = std::sqrt(0.4 * 0.4) - R;  // −0.05, +0.05
  const double cross = 0.3 + 0.1 * (-f3) / (f4 - f3);                          // linear along the edge
  const double expected = std::exp(-7.0 * 2 * cross);
  const bool beer = res.escaped && std::abs(res.value[0] - expected) < 1e-9;
  std::printf("white furnace: %d bad paths of %lld; Beer-Lambert %.12f vs %.12f\n", bad, (long long)paths,
              res.value[0], expected);
  return (bad == 0 && beer) ? 0 : 1;
}
