// Spherical-harmonics colour (degree 0..3), forward and VJP (upstream computeColorFromSH).
// rgb = sum_k basis_k(dir) sh_k + 0.5, then clamped at 0 (the clamp kills the gradient per
// channel). `sh` points at the [M, 3] coefficients of one Gaussian (M >= (deg+1)^2).
#pragma once

#include "host_device.h"
#include "math.h"

namespace grp {

constexpr float kShC0 = 0.28209479177387814f;
constexpr float kShC1 = 0.4886025119029199f;
// Scalars, not arrays: a namespace-scope constexpr array cannot be read in CUDA device code.
constexpr float kShC2_0 = 1.0925484305920792f;
constexpr float kShC2_1 = -1.0925484305920792f;
constexpr float kShC2_2 = 0.31539156525252005f;
constexpr float kShC2_3 = -1.0925484305920792f;
constexpr float kShC2_4 = 0.5462742152960396f;
constexpr float kShC3_0 = -0.5900435899266435f;
constexpr float kShC3_1 = 2.890611442640554f;
constexpr float kShC3_2 = -0.4570457994644658f;
constexpr float kShC3_3 = 0.3731763325901154f;
constexpr float kShC3_4 = -0.4570457994644658f;
constexpr float kShC3_5 = 1.445305721320277f;
constexpr float kShC3_6 = -0.5900435899266435f;

// Fills basis[0..(deg+1)^2) and, when grad != nullptr, d basis / d dir (x, y, z) per basis.
GRP_FORCE_INLINE int sh_basis(int deg, Vec3 d, float* basis, Vec3* grad) {
  const float x = d.x, y = d.y, z = d.z;
  basis[0] = kShC0;
  if (grad) grad[0] = {0.f, 0.f, 0.f};
  if (deg < 1) return 1;
  basis[1] = -kShC1 * y;
  basis[2] = kShC1 * z;
  basis[3] = -kShC1 * x;
  if (grad) {
    grad[1] = {0.f, -kShC1, 0.f};
    grad[2] = {0.f, 0.f, kShC1};
    grad[3] = {-kShC1, 0.f, 0.f};
  }
  if (deg < 2) return 4;
  const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  basis[4] = kShC2_0 * xy;
  basis[5] = kShC2_1 * yz;
  basis[6] = kShC2_2 * (2.f * zz - xx - yy);
  basis[7] = kShC2_3 * xz;
  basis[8] = kShC2_4 * (xx - yy);
  if (grad) {
    grad[4] = {kShC2_0 * y, kShC2_0 * x, 0.f};
    grad[5] = {0.f, kShC2_1 * z, kShC2_1 * y};
    grad[6] = {-2.f * kShC2_2 * x, -2.f * kShC2_2 * y, 4.f * kShC2_2 * z};
    grad[7] = {kShC2_3 * z, 0.f, kShC2_3 * x};
    grad[8] = {2.f * kShC2_4 * x, -2.f * kShC2_4 * y, 0.f};
  }
  if (deg < 3) return 9;
  basis[9] = kShC3_0 * y * (3.f * xx - yy);
  basis[10] = kShC3_1 * xy * z;
  basis[11] = kShC3_2 * y * (4.f * zz - xx - yy);
  basis[12] = kShC3_3 * z * (2.f * zz - 3.f * xx - 3.f * yy);
  basis[13] = kShC3_4 * x * (4.f * zz - xx - yy);
  basis[14] = kShC3_5 * z * (xx - yy);
  basis[15] = kShC3_6 * x * (xx - 3.f * yy);
  if (grad) {
    grad[9] = {kShC3_0 * 6.f * xy, kShC3_0 * 3.f * (xx - yy), 0.f};
    grad[10] = {kShC3_1 * yz, kShC3_1 * xz, kShC3_1 * xy};
    grad[11] = {-2.f * kShC3_2 * xy, kShC3_2 * (4.f * zz - xx - 3.f * yy), 8.f * kShC3_2 * yz};
    grad[12] = {-6.f * kShC3_3 * xz, -6.f * kShC3_3 * yz, kShC3_3 * (6.f * zz - 3.f * xx - 3.f * yy)};
    grad[13] = {kShC3_4 * (4.f * zz - 3.f * xx - yy), -2.f * kShC3_4 * xy, 8.f * kShC3_4 * xz};
    grad[14] = {2.f * kShC3_5 * xz, -2.f * kShC3_5 * yz, kShC3_5 * (xx - yy)};
    grad[15] = {kShC3_6 * 3.f * (xx - yy), -6.f * kShC3_6 * xy, 0.f};
  }
  return 16;
}

// x unchanged; on the host compiler, opaque to the optimiser, so that a product passed through it
// is rounded on its own and never fused into an FMA with the sum it feeds (whether GCC fuses a
// product otherwise depends on how it vectorised the surrounding loop).
GRP_INLINE float round_here(float x) {
#if !defined(__CUDACC__) && defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
  __asm__("" : "+x"(x));
#endif
  return x;
}

// Unit view direction of mean m seen from campos; also returns |m - campos|. The squares are
// rounded before they are summed (round_here): which one GCC fused otherwise depended on the
// function the code was inlined into.
GRP_INLINE Vec3 view_dir(Vec3 m, Vec3 campos, float& norm) {
  const Vec3 v = {m.x - campos.x, m.y - campos.y, m.z - campos.z};
  norm = sqrtf(round_here(v.x * v.x) + round_here(v.y * v.y) + round_here(v.z * v.z));
  const float inv = 1.f / norm;
  return {v.x * inv, v.y * inv, v.z * inv};
}

// Forward: raw (unclamped) colour + 0.5; the caller clamps at 0 and keeps the masks. Forced inline:
// GCC's unit-growth heuristic otherwise left it out of line in the CPU preprocess (-8% forward).
// The products are rounded before they are summed, in order of k, in every context it is inlined
// into (the CPU preprocess on vectors does the same: cpu/preprocess_simd.h, and the backward
// recomputes it for the clamp masks).
GRP_FORCE_INLINE Vec3 eval_sh(int deg, const float* sh, Vec3 m, Vec3 campos) {
  float norm;
  const Vec3 d = view_dir(m, campos, norm);
  float basis[16];
  const int n = sh_basis(deg, d, basis, nullptr);
  Vec3 rgb = {0.f, 0.f, 0.f};
  for (int k = 0; k < n; ++k) {
    rgb.x += round_here(basis[k] * sh[3 * k + 0]);
    rgb.y += round_here(basis[k] * sh[3 * k + 1]);
    rgb.z += round_here(basis[k] * sh[3 * k + 2]);
  }
  return {rgb.x + 0.5f, rgb.y + 0.5f, rgb.z + 0.5f};
}

// VJP: dL_drgb is the gradient of the clamped colour; channels whose raw value was < 0 get none.
// Writes dL_dsh[0..(deg+1)^2) (3 per coefficient) when non-null and returns dL/d(m - campos)
// (unnormalised v).
GRP_FORCE_INLINE Vec3 eval_sh_vjp(int deg, const float* sh, Vec3 m, Vec3 campos, Vec3 dL_drgb,
                                  float* dL_dsh) {
  float norm;
  const Vec3 d = view_dir(m, campos, norm);
  float basis[16];
  Vec3 grad[16];
  const int n = sh_basis(deg, d, basis, grad);
  // Recompute the forward exactly so that the clamp decision is the same.
  const Vec3 fwd = eval_sh(deg, sh, m, campos);
  const Vec3 g = {fwd.x < 0.f ? 0.f : dL_drgb.x, fwd.y < 0.f ? 0.f : dL_drgb.y,
                  fwd.z < 0.f ? 0.f : dL_drgb.z};
  Vec3 dL_ddir = {0.f, 0.f, 0.f};
  for (int k = 0; k < n; ++k) {
    if (dL_dsh != nullptr) {
      dL_dsh[3 * k + 0] = basis[k] * g.x;
      dL_dsh[3 * k + 1] = basis[k] * g.y;
      dL_dsh[3 * k + 2] = basis[k] * g.z;
    }
    const float s = sh[3 * k + 0] * g.x + sh[3 * k + 1] * g.y + sh[3 * k + 2] * g.z;
    dL_ddir.x += grad[k].x * s;
    dL_ddir.y += grad[k].y * s;
    dL_ddir.z += grad[k].z * s;
  }
  // d = v / |v|: dL/dv = (g - d (d.g)) / |v|
  const float dd = dot3(d, dL_ddir);
  const float inv = 1.f / norm;
  return {(dL_ddir.x - d.x * dd) * inv, (dL_ddir.y - d.y * dd) * inv, (dL_ddir.z - d.z * dd) * inv};
}

}  // namespace grp
