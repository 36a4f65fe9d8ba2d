// Vectors of the machine's native width for the CPU kernel (GCC/Clang vector extensions: 16 lanes
// with AVX-512, 8 with AVX, 4 otherwise). Every lane does the same IEEE maths whatever the width.
// (A vector wider than the machine's, e.g. 16 lanes on AVX2, is lowered in pieces, and GCC turns
// its comparisons and selects into lane-by-lane scalar code: several times slower.)
#pragma once

#include <cmath>
#include <cstdint>

#if defined(__AVX__)
#include <immintrin.h>
#endif

namespace grp {
namespace cpu {

#if defined(__AVX512F__)
constexpr int kLanes = 16;
#elif defined(__AVX__)
constexpr int kLanes = 8;
#else
constexpr int kLanes = 4;
#endif
typedef float vf __attribute__((vector_size(4 * kLanes)));
typedef int32_t vi __attribute__((vector_size(4 * kLanes)));

inline vf splat(float v) {
  vf r;
  for (int i = 0; i < kLanes; ++i) r[i] = v;
  return r;
}
inline vi splat_i(int32_t v) {
  vi r;
  for (int i = 0; i < kLanes; ++i) r[i] = v;
  return r;
}

// Correctly rounded lane-wise square root (the bits of sqrtf).
inline vf vsqrt(vf x) {
#if defined(__AVX512F__)
  return (vf)_mm512_sqrt_ps((__m512)x);
#elif defined(__AVX__)
  return (vf)_mm256_sqrt_ps((__m256)x);
#else
  vf r;
  for (int i = 0; i < kLanes; ++i) r[i] = std::sqrt(x[i]);
  return r;
#endif
}

// Lane-wise ceil (the bits of ceilf).
inline vf vceil(vf x) {
#if defined(__AVX512F__)
  return (vf)_mm512_roundscale_ps((__m512)x, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC);
#elif defined(__AVX__)
  return (vf)_mm256_round_ps((__m256)x, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC);
#else
  vf r;
  for (int i = 0; i < kLanes; ++i) r[i] = std::ceil(x[i]);
  return r;
#endif
}

// Sum of the lanes of v by a fixed tree (the upper half added to the lower, then again): the
// same bits on every call and thread, not those of a left-to-right sum.
inline float hsum(vf v) {
#if defined(__AVX512F__)
  return _mm512_reduce_add_ps((__m512)v);
#else
  float s[kLanes];
  for (int i = 0; i < kLanes; ++i) s[i] = v[i];
  for (int w = kLanes / 2; w >= 1; w /= 2)
    for (int i = 0; i < w; ++i) s[i] += s[i + w];
  return s[0];
#endif
}

// Lane-wise |x| (clears the sign bit, as fabsf).
inline vf vabs(vf x) { return (vf)((vi)x & splat_i(0x7fffffff)); }

// x unchanged, but opaque to the optimiser: a product passed through it is rounded on its own
// and never fused into an FMA with the sum it feeds.
inline vf round_here(vf x) {
#if defined(__AVX512F__)
  __asm__("" : "+v"(x));
#else
  __asm__("" : "+x"(x));
#endif
  return x;
}

// Vector twin of exp_nonpos (common/math.h): same reduction and polynomial, lane-wise.
inline vf vexp_nonpos(vf x) {
  x = x < splat(-87.f) ? splat(-87.f) : x;
  x = x > splat(0.f) ? splat(0.f) : x;
  const vf v = x * 1.44269504088896341f;
  const vi n = __builtin_convertvector(v - 0.5f, vi);  // round to nearest for v <= 0
  const vf fn = __builtin_convertvector(n, vf);
  vf r = x - fn * 0.693359375f;
  r = r - fn * -2.12194440e-4f;
  vf p = splat(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const vf y = p * r * r + r + 1.0f;
  const vi bits = (n + 127) << 23;
  return y * (vf)bits;
}

}  // namespace cpu
}  // namespace grp
