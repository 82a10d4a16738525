// Shared definitions of the torch-free tracing core: the host/device marker and the few math helpers the core
// uses, written so that a CUDA build compiles the same headers (no std:: algorithms in device code).
//
// The core's only libc needs are here. Under NVRTC (__CUDACC_RTC__; the CUDA glue of csrc/cuda/, compiled at run
// time) there is no libc: the math functions are CUDA's device built-ins, the fixed-width integers are declared
// below (LP64 on Linux, LLP64 on Windows, as the host compiler's), and the two things the host path takes from
// libc or GCC (INFINITY, __builtin_memcpy) have device equivalents. The host build is unchanged.
#pragma once

#if defined(__CUDACC_RTC__)
typedef signed char int8_t;
typedef unsigned char uint8_t;
typedef short int16_t;
typedef unsigned short uint16_t;
typedef int int32_t;
typedef unsigned int uint32_t;
#if defined(_WIN64)
typedef long long int64_t;
typedef unsigned long long uint64_t;
#else
typedef long int64_t;
typedef unsigned long uint64_t;
#endif
static_assert(sizeof(int64_t) == 8 && sizeof(uint64_t) == 8, "64-bit integers");
#else
#include <math.h>
#include <stdint.h>
#endif

#if defined(__CUDACC__)
#define TA_HD __host__ __device__
#else
#define TA_HD
#endif

// The walk's steps (integrator.h) are inlined into the walk whatever the caller's size: each is called once per walk
// instance, and the path state that they share by reference stays in registers, as in the one function they were
// carved from (left to the compiler, fly and collide stayed out of line and the scalar replay measured slower).
// The small helpers of the walk's inner loops (the voxel DDA, the optics, the sensors' ray generation, the entry
// search) are forced inline too: once the steps are inlined the walk is large, GCC's growth limits then left them
// out of line, and a call per voxel step made objects 10-15 % slower than the one-function walk (c845e46).
// TA_INLINE_LAMBDA does the same for a lambda (placed after its parameter list).
#if defined(__CUDACC__)
#define TA_INLINE __forceinline__
#define TA_INLINE_LAMBDA
#elif defined(__GNUC__)
#define TA_INLINE inline __attribute__((always_inline))
#define TA_INLINE_LAMBDA __attribute__((always_inline))
#else
#define TA_INLINE inline
#define TA_INLINE_LAMBDA
#endif

namespace ta {
namespace core {

template <typename T>
TA_HD inline T tmin(T a, T b) { return (b < a) ? b : a; }  // same tie rule as std::min
template <typename T>
TA_HD inline T tmax(T a, T b) { return (a < b) ? b : a; }  // same tie rule as std::max

TA_HD inline float tsqrt(float x) { return sqrtf(x); }

// A hint that *p will be read soon: no effect on any result (a no-op on a GPU or without the builtin).
template <typename T>
TA_HD TA_INLINE void prefetch(const T* p) {
#if defined(__GNUC__) && !defined(__CUDA_ARCH__)
  __builtin_prefetch(p);
#else
  (void)p;
#endif
}
TA_HD inline double tsqrt(double x) { return sqrt(x); }
TA_HD inline float texp(float x) { return expf(x); }
TA_HD inline double texp(double x) { return exp(x); }
TA_HD inline float tlog(float x) { return logf(x); }
TA_HD inline double tlog(double x) { return log(x); }
TA_HD inline float tsin(float x) { return sinf(x); }
TA_HD inline double tsin(double x) { return sin(x); }
TA_HD inline float tcos(float x) { return cosf(x); }
TA_HD inline double tcos(double x) { return cos(x); }
TA_HD inline float tabs(float x) { return fabsf(x); }
TA_HD inline double tabs(double x) { return fabs(x); }
TA_HD inline float tcopysign(float x, float y) { return copysignf(x, y); }
TA_HD inline double tcopysign(double x, double y) { return copysign(x, y); }
// The bits of a float and back (a device has intrinsics for it; the host a memcpy, which compiles to a move).
TA_HD inline uint32_t float_bits(float x) {
#if defined(__CUDACC_RTC__)
  return __float_as_uint(x);
#else
  uint32_t b;
  __builtin_memcpy(&b, &x, 4);
  return b;
#endif
}
TA_HD inline float bits_float(uint32_t b) {
#if defined(__CUDACC_RTC__)
  return __uint_as_float(b);
#else
  float r;
  __builtin_memcpy(&r, &b, 4);
  return r;
#endif
}
// nextafterf without the call into libm (the root search of boundary.h steps by it): the same result for any x, y
TA_HD inline float tnextafter(float x, float y) {
  if (x != x || y != y) return x + y;  // NaN
  if (x == y) return y;
  uint32_t b = float_bits(x);
  if (x == 0.0f) b = (y > 0.0f ? 0u : 0x80000000u) | 1u;  // the smallest subnormal toward y
  else b += ((x < y) == (x > 0.0f)) ? 1u : 0xffffffffu;   // |x| one unit in the last place up or down
  return bits_float(b);
}
TA_HD inline double tnextafter(double x, double y) { return nextafter(x, y); }
TA_HD inline float tatan2(float y, float x) { return atan2f(y, x); }
TA_HD inline double tatan2(double y, double x) { return atan2(y, x); }
TA_HD inline float tacos(float x) { return acosf(x); }
TA_HD inline double tacos(double x) { return acos(x); }
TA_HD inline float tfloor(float x) { return floorf(x); }
TA_HD inline double tfloor(double x) { return floor(x); }

template <typename T>
TA_HD inline T tinf() {
#if defined(__CUDACC_RTC__)
  return T(__int_as_float(0x7f800000));  // +inf (no INFINITY macro without libc)
#else
  return T(INFINITY);
#endif
}

template <typename T>
TA_HD inline T dot3(const T a[3], const T b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

template <typename T>
TA_HD inline void normalize3(T a[3]) {
  const T inv = T(1) / tsqrt(dot3(a, a));
  for (int k = 0; k < 3; ++k) a[k] *= inv;
}

constexpr double kPi = 3.14159265358979323846;

}  // namespace core
}  // namespace ta
